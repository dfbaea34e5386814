"""Before the uplink runs: its TLS context, password and outbox checked, each problem said with the
field it comes from and the kind of sysexits code it deserves."""

from __future__ import annotations

import socket
import sqlite3
import ssl
import time
from pathlib import Path

from cmcan.errors import CmcanError, Kind
from cmcan.uplink.config import MqttSettings, TlsSettings
from cmcan.uplink.outbox import Outbox, OutboxError, open_outbox, record_corrupt, set_aside

_KINDS = {
    "config": Kind.CONFIG,
    "noinput": Kind.NO_INPUT,
    "data": Kind.DATA,
    "unavailable": Kind.UNAVAILABLE,
    "cantcreat": Kind.CANT_CREATE,
    "tempfail": Kind.TEMPFAIL,
}


class SetupError(CmcanError):
    """The uplink cannot start (or ``--check`` failed); ``problem`` names it the uplink's way
    ('config', 'noinput', 'data', 'unavailable', 'cantcreat', 'tempfail'), ``kind`` is its Kind."""

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
    if m.password_file is None:
        return None
    try:
        text = m.password_file.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SetupError(f"{source}: uplink.mqtt.password_file: {m.password_file}: file not found", "noinput") from None
    except OSError as exc:
        raise SetupError(f"{source}: uplink.mqtt.password_file: {m.password_file}: {exc.strerror}", "noinput") from None
    pw = text.rstrip("\r\n")
    if not pw:
        raise SetupError(f"{source}: uplink.mqtt.password_file: {m.password_file}: empty", "config")
    return pw


def open_for_uplink(path: Path, keep_aside: bool = True, source: str = "the configuration") -> Outbox:
    """The outbox for publishing; a corrupt file is kept aside and reported (the next start, or the
    daemon, begins a new one), a missing folder or a newer format is reported. Without
    ``keep_aside`` (``--status``, a query) a corrupt file is reported and left as it is."""
    if not path.parent.is_dir():
        raise SetupError(
            f"{path.parent}: state directory does not exist (state.directory, uplink.outbox.file in {source})",
            "cantcreat",
        )
    try:
        return open_outbox(path, durable=False, keep_aside=False)
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
        raise SetupError(str(exc), "cantcreat") from None


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
