"""Domain errors and their kinds: every layer raises what went wrong; the command line alone maps
each kind to a sysexits(3) code (``cmcan.cli.errors.EXIT_CODES``)."""

from __future__ import annotations

import errno
from enum import Enum


class Kind(Enum):
    USAGE = "usage"  # the command was called wrongly
    DATA = "data"  # an input file's content is wrong
    NO_INPUT = "no input"  # an input file does not exist or cannot be read
    UNAVAILABLE = "unavailable"  # a service, device or optional package is missing
    CANT_CREATE = "cannot create"  # an output cannot be written
    IO_ERROR = "input/output error"  # a file exists but reading or writing it failed (EIO and the like)
    NO_PERMISSION = "permission denied"  # a file exists but this user may not read or write it
    TEMPFAIL = "temporary failure"  # try again later (e.g. another instance holds a lock)
    CONFIG = "configuration"  # the configuration (or what it names: DBC, model) is wrong
    SOFTWARE = "internal"  # a bug


class CmcanError(Exception):
    """An error the user can act on; ``str()`` names the file, field or frame and what was expected."""

    kind: Kind = Kind.SOFTWARE

    def __init__(self, message: str, kind: Kind | None = None) -> None:
        super().__init__(message)
        if kind is not None:
            self.kind = kind


# What the operating system said about a file, as a kind: a full disk or quota is a temporary failure
# (free space and try again: systemd restarts the service), an I/O error or a file over its size
# limit an I/O error, no permission its own kind, a place that cannot exist (read-only file system,
# missing folder, a file where a folder should be) cannot create, out of descriptors or memory temporary.
_ERRNO_KINDS = {
    errno.ENOSPC: Kind.TEMPFAIL,
    errno.EDQUOT: Kind.TEMPFAIL,
    errno.EFBIG: Kind.IO_ERROR,
    errno.EIO: Kind.IO_ERROR,
    errno.EACCES: Kind.NO_PERMISSION,
    errno.EPERM: Kind.NO_PERMISSION,
    errno.EROFS: Kind.CANT_CREATE,
    errno.ENOENT: Kind.CANT_CREATE,
    errno.ENOTDIR: Kind.CANT_CREATE,
    errno.EISDIR: Kind.CANT_CREATE,
    errno.ENAMETOOLONG: Kind.CANT_CREATE,
    errno.EMFILE: Kind.TEMPFAIL,
    errno.ENFILE: Kind.TEMPFAIL,
    errno.ENOMEM: Kind.TEMPFAIL,
}
DISK_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def kind_of_oserror(exc: OSError) -> Kind:
    """The kind of an OSError on a file cmcan writes or reads (:data:`_ERRNO_KINDS`; others: I/O error)."""
    return _ERRNO_KINDS.get(exc.errno or 0, Kind.IO_ERROR)
