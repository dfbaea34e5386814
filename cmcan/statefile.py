"""The daemon's persisted state: one JSON file in the state directory, written atomically, and the
lock that keeps a second daemon off the directory."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import stat
from pathlib import Path

from cmcan.errors import CmcanError, Kind, kind_of_oserror
from cmcan.monitor.totals import StateError, Totals

log = logging.getLogger("cmcan.state")
STATE_FILE = "state.json"
LOCK_FILE = "cmcan.lock"
NODE_FILE = "j1939-node.json"
# ``cmcan baseline reset`` asks the running daemon through this file and a reload (never two writers)
BASELINE_REQUEST_FILE = (
    "baseline-reset.json"  # the J1939 node's address claim as the daemon last saw it (uplink health)
)


class StateStore:
    def __init__(self, directory: str | Path) -> None:
        self.dir = Path(directory)
        self.path = self.dir / STATE_FILE

    def check_writable(self) -> str | None:
        """None when the directory can hold the state, else why not."""
        if not self.dir.exists():
            return f"{self.dir}: state directory does not exist"
        if not self.dir.is_dir():
            return f"{self.dir}: not a directory"
        if not os.access(self.dir, os.W_OK | os.X_OK):
            return f"{self.dir}: state directory is not writable by this user"
        return None

    def read(self) -> Totals:
        """The saved totals (fresh ones when there is no file), changing nothing. A file whose content
        cannot be used (not a regular file, not UTF-8, not JSON, NaN or Infinity, a field out of range)
        raises ``StateError`` (a data error) naming the file and the field; a file that is there but
        cannot be read (permissions, an I/O error) raises ``StateAccessError``: that is no corruption,
        and what the file holds may be perfectly good."""
        try:
            raw = _read_regular(self.path)
        except FileNotFoundError:
            return Totals()
        except OSError as exc:
            raise StateAccessError(self.path, exc) from None
        if raw is None:
            raise StateError(f"{self.path}: not a regular file, expected a state file")
        try:
            doc = json.loads(raw.decode("utf-8"), parse_constant=_no_constant)
            return Totals.from_dict(doc)
        except StateError as exc:
            raise StateError(f"{self.path}: {exc}") from None
        except ValueError as exc:  # not UTF-8, not JSON, NaN or Infinity
            raise StateError(f"{self.path}: not a readable state file: {exc}") from None

    def load(self) -> Totals:
        """The saved totals for the daemon; a missing file is a fresh start, a corrupt one is kept
        aside (``state.json.corrupt-N``), not lost, and the daemon starts with fresh totals. A file
        that cannot be read (``StateAccessError``) stops the start: starting afresh would throw the
        machine's history away at the next save, and a restart or a fixed permission brings it back."""
        try:
            return self.read()
        except StateError as exc:
            aside = self._aside()
            self.path.replace(aside)
            log.error("unreadable state: %s; kept as %s, starting with fresh totals", exc, aside)
            return Totals()

    def _aside(self) -> Path:
        n = 1
        while (candidate := self.dir / f"{STATE_FILE}.corrupt-{n}").exists():
            n += 1
        return candidate

    def save(self, totals: Totals) -> None:
        """Write a temporary file, fsync it, rename it over the old one, fsync the directory: a crash
        or power cut leaves either the old or the new state, never a torn one."""
        tmp = self.dir / f".{STATE_FILE}.tmp"
        data = json.dumps(totals.to_dict(), indent=1).encode("utf-8")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o640)
        try:
            os.write(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)
        dfd = os.open(self.dir, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def write_baseline_request(directory: str | Path, reason: str, at: str) -> Path:
    """Leave a baseline reset for the daemon (written atomically: it reads all of it or nothing)."""
    path = Path(directory) / BASELINE_REQUEST_FILE
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps({"reason": reason, "at": at}) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path


def read_baseline_request(directory: str | Path) -> dict[str, str] | None:
    """The reset a ``cmcan baseline reset`` left; None when there is none. A file that is not such a
    request says so in ``reason`` with ``bad`` set (remove it with :func:`done_baseline_request`: it
    must not block later resets)."""
    path = Path(directory) / BASELINE_REQUEST_FILE
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        return {"reason": f"unreadable request {path} ({exc.strerror})", "at": "", "bad": "1"}
    try:
        doc = json.loads(raw.decode("utf-8"))
        return {"reason": str(doc["reason"])[:200], "at": str(doc.get("at", ""))[:40]}
    except (ValueError, KeyError, TypeError):
        return {"reason": f"unreadable request {path}", "at": "", "bad": "1"}


def done_baseline_request(directory: str | Path) -> None:
    """The request carried out and saved (the command waiting for it sees the file go only now)."""
    with contextlib.suppress(OSError):
        (Path(directory) / BASELINE_REQUEST_FILE).unlink()


def write_node_status(directory: str | Path, status: dict[str, object]) -> None:
    """The J1939 node's state (claimed, lost, its address) in the state directory, replaced
    atomically, for ``cmcan uplink``'s health messages and ``cmcan check --state``."""
    d = Path(directory)
    tmp = d / f".{NODE_FILE}.tmp"
    tmp.write_text(json.dumps(status, indent=1, default=str), encoding="utf-8")
    os.replace(tmp, d / NODE_FILE)


def read_node_status(directory: str | Path) -> dict[str, object] | None:
    """What :func:`write_node_status` wrote (None: no file, or not one it wrote)."""
    try:
        raw = _read_regular(Path(directory) / NODE_FILE)
        doc = json.loads(raw.decode("utf-8")) if raw is not None else None
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


class StateAccessError(CmcanError):
    """The state file is there but the operating system refused to read it: no permission
    (EACCES, EPERM: e.g. a backup restored as root) or an I/O error (EIO and the like)."""

    def __init__(self, path: Path, exc: OSError) -> None:
        denied = exc.errno in (errno.EACCES, errno.EPERM)
        name = errno.errorcode.get(exc.errno or 0, "")
        why = f"{exc.strerror or exc} ({name})" if name else str(exc.strerror or exc)
        hint = "; the daemon's user needs to read and write it" if denied else ""
        super().__init__(
            f"{path}: cannot read the state file: {why}{hint}; nothing was changed",
            Kind.NO_PERMISSION if denied else Kind.IO_ERROR,
        )
        self.path = path
        self.errno = exc.errno


def _read_regular(path: Path) -> bytes | None:
    """The bytes of the file at ``path``, or None when it is no regular file (a folder, a FIFO, a
    device: nothing a state file can be). Non-blocking open: a FIFO must not hang the start."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        chunks = []
        while chunk := os.read(fd, 1 << 20):
            chunks.append(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number a state file holds")


class LockHeld(CmcanError):
    """Another process holds a lock cmcan wants (a temporary failure: that one may end)."""


class LockFileError(CmcanError):
    """A lock file that cannot be opened or written; ``strerror`` is the system's reason."""

    def __init__(self, message: str, exc: OSError) -> None:
        super().__init__(f"{message}: {exc.strerror}", kind_of_oserror(exc))
        self.strerror = exc.strerror or str(exc)


class StateLock:
    """An exclusive ``flock`` on ``cmcan.lock`` in the state directory, held for the daemon's life:
    two daemons on one directory would overwrite each other's state. The kernel drops the lock when
    the process ends however it ends (kill -9 included), so a lock file left behind never blocks a
    start; the file says which process holds the lock."""

    def __init__(self, directory: str | Path) -> None:
        self.path = Path(directory) / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> StateLock:
        """Take the lock or raise a temporary failure naming the lock file and the holder's pid."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o640)
        except OSError as exc:
            raise LockFileError(f"{self.path}: cannot open the state lock", exc) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = _read_pid(fd)
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise CmcanError(f"{self.path}: cannot lock: {exc.strerror}", Kind.CANT_CREATE) from None
            who = f"pid {holder}" if holder else "another process"
            raise LockHeld(
                f"{self.path}: the state directory is in use by another cmcan ({who} holds the lock); "
                "one daemon per state directory",
                Kind.TEMPFAIL,
            ) from None
        try:  # the holder's pid, for whoever finds the lock taken
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as exc:
            os.close(fd)
            raise LockFileError(f"{self.path}: cannot write the state lock", exc) from None
        self._fd = fd
        return self

    def holder(self) -> int | None:
        """The pid holding the lock now, or None when nobody does (read-only: for ``cmcan check``)."""
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            return None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except OSError:
                return _read_pid(fd) or -1
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        finally:
            os.close(fd)

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", errors="replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None
