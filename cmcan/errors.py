"""Domain errors and their kinds: every layer raises what went wrong; the command line alone maps
each kind to a sysexits(3) code (``cmcan.cli.errors.EXIT_CODES``)."""

from __future__ import annotations

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
