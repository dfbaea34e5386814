"""Before the uplink runs: its TLS context, password and outbox checked, each problem said with the
field it comes from and the kind of sysexits code it deserves."""

from __future__ import annotations

import errno
import os
import socket
import sqlite3
import ssl
import stat
import time
from pathlib import Path

from cmcan.errors import CmcanError, Kind
from cmcan.service.statefile import LockFileError, LockHeld, StateLock
from cmcan.uplink.config import MqttSettings, TlsSettings
from cmcan.uplink.outbox import Outbox, OutboxError, open_outbox, problem_kind, record_corrupt, set_aside

_KINDS = {
    "config": Kind.CONFIG,
    "noinput": Kind.NO_INPUT,
    "data": Kind.DATA,
    "unavailable": Kind.UNAVAILABLE,
    "cantcreat": Kind.CANT_CREATE,
    "ioerr": Kind.IO_ERROR,
    "noperm": Kind.NO_PERMISSION,
    "tempfail": Kind.TEMPFAIL,
}
# An outbox that cannot be opened, by what a restart can do about it: another process's lock and a
# full disk pass (75: the unit restarts the uplink later), an I/O error may (74, restarted too);
# permissions and a missing folder need a person (77, 73: not restarted in a loop).
_OUTBOX_PROBLEMS = {"busy": "tempfail", "full": "tempfail", "io": "ioerr", "denied": "noperm", "cantopen": "cantcreat"}
MAX_PASSWORD_BYTES = 65535  # MQTT's binary data field


class SetupError(CmcanError):
    """The uplink cannot start (or ``--check`` failed); ``problem`` names it the uplink's way
    ('config', 'noinput', 'data', 'unavailable', 'cantcreat', 'ioerr', 'noperm', 'tempfail'),
    ``kind`` is its Kind."""

    def __init__(self, message: str, problem: str) -> None:
        super().__init__(message, _KINDS[problem])
        self.problem = problem


# -- setup ----------------------------------------------------------------------------------------


def tls_context(tls: TlsSettings, source: str = "config") -> ssl.SSLContext | None:
    """The TLS context from the configuration, with every file checked now (not at the first connect)."""
    if not tls.enabled:
        return None
    for name, p in (("ca_file", tls.ca_file), ("cert_file", tls.cert_file), ("key_file", tls.key_file)):
        if p is not None and not p.is_file():
            raise SetupError(f"{source}: uplink.mqtt.tls.{name}: {p}: file not found", "noinput")
    try:
        ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(tls.ca_file) if tls.ca_file else None)
    except (ssl.SSLError, OSError) as exc:
        raise SetupError(
            f"{source}: uplink.mqtt.tls.ca_file: {tls.ca_file}: not a PEM CA certificate ({_ssl_reason(exc)})", "config"
        ) from None
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.check_hostname = tls.verify_hostname
    if tls.cert_file is not None:
        try:
            ctx.load_cert_chain(str(tls.cert_file), str(tls.key_file) if tls.key_file else None, password=_no_password)
        except (ssl.SSLError, OSError, _EncryptedKey) as exc:
            raise SetupError(
                f"{source}: uplink.mqtt.tls.cert_file: {tls.cert_file} with key {tls.key_file}: "
                f"not a usable client certificate and key ({_ssl_reason(exc)})",
                "config",
            ) from None
    return ctx


class _EncryptedKey(Exception):
    def __str__(self) -> str:
        return "the key is encrypted; the uplink needs an unencrypted key (protect it with file permissions)"


def _no_password() -> str:
    raise _EncryptedKey()


def _ssl_reason(exc: BaseException) -> str:
    reason = getattr(exc, "reason", None)
    return str(reason).replace("_", " ").lower() if reason else str(exc)


def read_password(m: MqttSettings, source: str = "config") -> str | None:
    """The password file's one line: a regular file (a FIFO or a device neither blocks nor fills
    memory), UTF-8, at most MQTT's 65535 bytes."""
    if m.password_file is None:
        return None
    where = f"{source}: uplink.mqtt.password_file: {m.password_file}"
    try:
        fd = os.open(m.password_file, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise SetupError(f"{where}: file not found", "noinput") from None
    except OSError as exc:
        raise SetupError(
            f"{where}: {exc.strerror}", "noperm" if isinstance(exc, PermissionError) else "noinput"
        ) from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise SetupError(f"{where}: not a regular file", "config")
        data = os.read(fd, MAX_PASSWORD_BYTES + 3)
    except OSError as exc:
        raise SetupError(f"{where}: {exc.strerror}", "ioerr") from None
    finally:
        os.close(fd)
    try:
        pw = data.decode("utf-8").rstrip("\r\n")
    except UnicodeDecodeError as exc:
        raise SetupError(f"{where}: not UTF-8 text (byte {exc.start})", "config") from None
    if not pw:
        raise SetupError(f"{where}: empty", "config")
    if len(pw.encode("utf-8")) > MAX_PASSWORD_BYTES:
        raise SetupError(f"{where}: longer than MQTT's {MAX_PASSWORD_BYTES} bytes", "config")
    return pw


class OutboxLock(StateLock):
    """One uplink per outbox: an exclusive ``flock`` on ``<outbox>.lock`` beside it, held for the
    uplink's life (the daemon's state lock, on another file: the daemon and the uplink share the
    outbox, two uplinks must not). Two uplinks on one outbox would publish every entry twice and,
    with one client id, take the broker session from each other every second or two (subscribers see
    the machine flap offline). As the state lock, the kernel drops it however the holder ends."""

    def __init__(self, outbox: Path) -> None:
        super().__init__(outbox.parent)
        self.outbox = outbox
        self.path = outbox.with_name(outbox.name + ".lock")

    def acquire(self) -> OutboxLock:
        """Take the lock, or raise a temporary failure (75) naming the lock file and the holder's pid;
        a lock file that cannot be made or written is said with its cause (a full disk: 75)."""
        try:  # opened here first for the cause of a failure, which the state lock's message leaves out
            self._probe()
            super().acquire()
        except OSError as exc:  # creating the file, or writing the pid into it on a full disk
            problem = _OUTBOX_PROBLEMS.get(problem_kind(exc, "cantopen"), "ioerr")
            raise SetupError(f"{self.path}: cannot take the outbox lock: {exc.strerror}", problem) from None
        except LockHeld:
            pid = self.holder()
            who = f"pid {pid}" if pid and pid > 0 else "another process"
            raise SetupError(
                f"{self.path}: the outbox {self.outbox.name} is in use by another cmcan uplink ({who} holds the "
                "lock); one uplink per outbox",
                "tempfail",
            ) from None
        except LockFileError as exc:  # writing the pid into the lock file failed (a full disk: 75)
            problem = next(p for p, k in _KINDS.items() if k is exc.kind)
            raise SetupError(f"{self.path}: cannot take the outbox lock: {exc.strerror}", problem) from None
        return self

    def _probe(self) -> None:
        """The lock file made if there is none, as the state directory's lock and request files are
        opened: never through a link (whoever can write the folder could point it at any file the
        uplink's user may open, or a FIFO that blocks it), never blocking, a regular file only."""
        flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
        try:
            fd = os.open(self.path, flags, 0o640)
        except OSError as exc:
            if exc.errno == errno.ELOOP:  # (O_NOFOLLOW: the last part of the path is a symbolic link)
                raise SetupError(
                    f"{self.path}: a symbolic link, not the outbox lock (lock files are never opened through one)",
                    "cantcreat",
                ) from None
            raise
        try:
            mode = os.fstat(fd).st_mode
        finally:
            os.close(fd)
        if not stat.S_ISREG(mode):
            raise SetupError(f"{self.path}: not a regular file, expected the outbox lock", "cantcreat")


def require_folder(path: Path, source: str = "the configuration") -> None:
    """The outbox's folder (the state directory) exists: nothing else is made without it."""
    if not path.parent.is_dir():
        raise SetupError(
            f"{path.parent}: state directory does not exist (state.directory, uplink.outbox.file in {source})",
            "cantcreat",
        )


def open_for_uplink(path: Path, keep_aside: bool = True, source: str = "the configuration") -> Outbox:
    """The outbox for publishing; a corrupt file is kept aside and reported (the next start, or the
    daemon, begins a new one), a missing folder or a newer format is reported. Without
    ``keep_aside`` (``--status``, a query) a corrupt file is reported and left as it is."""
    require_folder(path, source)
    try:
        box = open_outbox(path, durable=False, keep_aside=False)
        if keep_aside:  # the uplink proper (not a query): a restart of the gateway is recorded at once
            box.note_restart()
        return box
    except (sqlite3.Error, OSError) as exc:  # recording the restart: the outbox could be read, not written
        raise SetupError(
            f"{path}: cannot write the outbox: {exc}", _OUTBOX_PROBLEMS.get(problem_kind(exc), "ioerr")
        ) from None
    except OutboxError as exc:
        if exc.kind == "corrupt" and not keep_aside:
            raise SetupError(f"{exc}; left as it is (cmcan uplink keeps it aside when it runs)", "data") from None
        if exc.kind == "corrupt":
            try:
                aside = set_aside(path)
                box = open_outbox(path, durable=False)
                record_corrupt(box, aside, time.time(), time.time())
                box.close()
            except (OSError, OutboxError, sqlite3.Error) as err:
                raise SetupError(f"{exc}; it could not be kept aside: {err}", "data") from None
            raise SetupError(
                f"{exc}; kept as {aside.name}, a new outbox is started (the next start publishes from it)", "data"
            ) from None
        if exc.kind == "version":
            raise SetupError(str(exc), "data") from None
        raise SetupError(str(exc), _OUTBOX_PROBLEMS.get(exc.kind, "ioerr")) from None


def describe_connect_error(exc: BaseException, m: MqttSettings) -> str:
    where = f"{m.host}:{m.port}"
    if isinstance(exc, socket.gaierror):
        return f"cannot resolve {m.host} ({exc.strerror})"
    if isinstance(exc, ssl.SSLCertVerificationError):
        return f"{where}: the broker's certificate is not trusted ({exc.verify_message}; see uplink.mqtt.tls.ca_file)"
    if isinstance(exc, ssl.SSLError):
        return f"{where}: TLS handshake failed ({_ssl_reason(exc)})"
    if isinstance(exc, ConnectionRefusedError):
        return f"{where}: connection refused (is the broker running?)"
    if isinstance(exc, TimeoutError | socket.timeout):
        return f"{where}: no answer within {m.connect_timeout_s:g} s"
    if isinstance(exc, OSError):
        return f"{where}: {exc.strerror or exc}"
    return f"{where}: {exc}"
