"""The ``uplink:`` configuration section: its schema and the frozen settings built from it."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cmcan.schema import Bool, Num, Obj, SchemaError, Str, show


class OptStr(Str):
    """A string that may be left unset (absent or null); checking a checked value again is a no-op."""

    def check(self, value: Any, src: str, path: str) -> str | None:
        return None if value is None else super().check(value, src, path)


# Whole-string patterns (fullmatch: '$' would let a trailing newline through). A topic segment: no
# wildcards, no separators, nothing a broker may refuse; a host: a name, IPv4 or IPv6 literal.
_SEGMENT = re.compile(r"[A-Za-z0-9._-]{1,64}")
_PREFIX = re.compile(r"[A-Za-z0-9._-]{1,64}(?:/[A-Za-z0-9._-]{1,64}){0,7}")
_HOST = re.compile(r"[A-Za-z0-9._:%-]{1,253}")
MQTT_MAX_BYTES = 65535  # an MQTT string's length field is 16 bits (3.1.1 section 1.5.3, 5.0 section 1.5.4)
TOPIC_KINDS = ("event", "summary", "dropped", "status", "health")


def mqtt_string_problem(value: str) -> str | None:
    """Why ``value`` cannot go into an MQTT UTF-8 string field (client id, user name, topic), or None.

    MQTT forbids U+0000 and surrogates and a length over 65535 bytes; a broker may close the
    connection on control characters and non-characters (they SHOULD NOT be sent): a client would
    then reconnect for ever, so these are refused as well."""
    try:
        n = len(value.encode("utf-8"))
    except UnicodeEncodeError:
        return "is not valid UTF-8 (it holds a lone surrogate)"
    if n > MQTT_MAX_BYTES:
        return f"is {n} bytes long in UTF-8, more than MQTT's {MQTT_MAX_BYTES}"
    for ch in value:
        c = ord(ch)
        if c < 0x20 or 0x7F <= c <= 0x9F or 0xFDD0 <= c <= 0xFDEF or (c & 0xFFFE) == 0xFFFE:
            return f"holds the control character or non-character U+{c:04X}, which MQTT forbids or a broker refuses"
    return None


def publish_topic_problem(topic: str) -> str | None:
    """Why ``topic`` cannot be published to, or None: not empty, no wildcard, an MQTT string."""
    if not topic:
        return "is empty"
    if "+" in topic or "#" in topic:
        return "holds a wildcard ('+' or '#'), which a publish topic must not"
    return mqtt_string_problem(topic)


def _rule(u: dict[str, Any]) -> tuple[str, str] | None:
    if u["enabled"] and u["machine_id"] is None:
        return "machine_id", "missing; every machine needs its own id in the topics and payloads when enabled"
    if u["machine_id"] is not None and not _SEGMENT.fullmatch(u["machine_id"]):
        return "machine_id", f"expected 1-64 letters, digits, '.', '_' or '-', got {show(u['machine_id'])}"
    m = u["mqtt"]
    if not _PREFIX.fullmatch(m["topic_prefix"]):
        got = show(m["topic_prefix"])
        return "mqtt.topic_prefix", f"expected segments of letters, digits, '.', '_', '-' joined by '/', got {got}"
    for kind in TOPIC_KINDS:  # what is published: the prefix, the machine and the kind
        problem = publish_topic_problem(f"{m['topic_prefix']}/{u['machine_id'] or 'unnamed'}/{kind}")
        if problem:
            return "mqtt.topic_prefix", f"the topics {problem}"
    if not _HOST.fullmatch(m["host"]):
        return "mqtt.host", f"expected a host name or an IPv4 or IPv6 address, got {show(m['host'])}"
    for name in ("client_id", "username"):
        problem = None if m[name] is None else mqtt_string_problem(m[name])
        if problem:
            return f"mqtt.{name}", f"{problem}: {show(m[name])}"
    if m["reconnect_min_s"] > m["reconnect_max_s"]:
        return "mqtt.reconnect_min_s", f"must not exceed reconnect_max_s ({m['reconnect_max_s']:g})"
    if m["password_file"] is not None and m["username"] is None:
        return "mqtt.password_file", "needs mqtt.username"
    t = m["tls"]
    if (t["cert_file"] is None) != (t["key_file"] is None):
        return "mqtt.tls.cert_file", "cert_file and key_file go together (the client certificate and its key)"
    if not t["enabled"] and any(t[k] is not None for k in ("ca_file", "cert_file", "key_file")):
        return "mqtt.tls.enabled", "certificate files are given but TLS is not enabled"
    return None


UPLINK = Obj(
    {
        "enabled": Bool(default=False),
        "machine_id": OptStr(default=None),
        "summary_every_s": Num(10, 86400, "s", default=900.0),
        "outbox": Obj(
            {
                "file": Str(default="outbox.sqlite"),
                "max_mb": Num(0.1, 1e6, "MiB", default=64.0),
                "max_age_days": Num(0.001, 3650, "days", default=90.0),
                "queue_size": Num(16, 1_000_000, default=4096, integer=True),
            },
            default={},
        ),
        "mqtt": Obj(
            {
                "host": Str(default="localhost"),
                "port": Num(1, 65535, default=None, integer=True),
                "protocol": Str(default="3.1.1", choices=("3.1.1", "5")),
                "client_id": OptStr(default=None),
                "topic_prefix": Str(default="cmcan"),
                "keepalive_s": Num(5, 3600, "s", default=60, integer=True),
                "connect_timeout_s": Num(1, 300, "s", default=15.0),
                "username": OptStr(default=None),
                "password_file": OptStr(default=None),
                "tls": Obj(
                    {
                        "enabled": Bool(default=False),
                        "ca_file": OptStr(default=None),
                        "cert_file": OptStr(default=None),
                        "key_file": OptStr(default=None),
                        "verify_hostname": Bool(default=True),
                    },
                    default={},
                ),
                "max_inflight": Num(1, 1000, default=20, integer=True),
                "ack_timeout_s": Num(1, 3600, "s", default=60.0),
                "reconnect_min_s": Num(0.05, 3600, "s", default=1.0),
                "reconnect_max_s": Num(0.05, 86400, "s", default=300.0),
                "health_every_s": Num(1, 86400, "s", default=60.0),
                "late_after_s": Num(0, 86400 * 365, "s", default=60.0),
            },
            default={},
        ),
    },
    default={},
    rule=_rule,
)


@dataclass(frozen=True)
class TlsSettings:
    enabled: bool
    ca_file: Path | None  # None: the system's trusted CAs
    cert_file: Path | None
    key_file: Path | None
    verify_hostname: bool


@dataclass(frozen=True)
class MqttSettings:
    host: str
    port: int
    protocol: str
    client_id: str
    topic_prefix: str
    keepalive_s: int
    connect_timeout_s: float
    username: str | None
    password_file: Path | None
    tls: TlsSettings
    max_inflight: int
    ack_timeout_s: float
    reconnect_min_s: float
    reconnect_max_s: float
    health_every_s: float
    late_after_s: float


@dataclass(frozen=True)
class OutboxSettings:
    path: Path
    max_bytes: int
    max_age_s: float
    queue_size: int


@dataclass(frozen=True)
class UplinkSettings:
    enabled: bool
    machine_id: str
    summary_every_s: float
    outbox: OutboxSettings
    mqtt: MqttSettings

    def topic(self, kind: str) -> str:
        return f"{self.mqtt.topic_prefix}/{self.machine_id}/{kind}"

    @classmethod
    def from_raw(
        cls, raw: dict[str, Any] | None, state_dir: str | Path, base_dir: str | Path = ".", source: str = "config"
    ) -> UplinkSettings:
        """Settings from the ``uplink:`` section (validated here when not yet), paths resolved: the
        outbox relative to the state directory (itself resolved against ``base_dir`` here when it is
        relative), certificate and password files relative to ``base_dir`` (the configuration file's
        folder)."""
        u = UPLINK.check(raw if raw is not None else {}, source, "uplink")
        base = Path(base_dir)

        def resolve(p: str | Path) -> Path:
            q = Path(p)
            return q if q.is_absolute() else (base / q).resolve()

        def path(p: str | None) -> Path | None:
            return None if p is None else resolve(p)

        m, t, o = u["mqtt"], u["mqtt"]["tls"], u["outbox"]
        machine = u["machine_id"] or "unnamed"
        out = Path(o["file"])
        return cls(
            enabled=u["enabled"],
            machine_id=machine,
            summary_every_s=float(u["summary_every_s"]),
            outbox=OutboxSettings(
                path=out if out.is_absolute() else resolve(state_dir) / out,
                max_bytes=int(o["max_mb"] * 1024 * 1024),
                max_age_s=float(o["max_age_days"]) * 86400.0,
                queue_size=int(o["queue_size"]),
            ),
            mqtt=MqttSettings(
                host=m["host"],
                port=int(m["port"] if m["port"] is not None else (8883 if t["enabled"] else 1883)),
                protocol=m["protocol"],
                client_id=m["client_id"] or f"cmcan-{machine}",
                topic_prefix=m["topic_prefix"],
                keepalive_s=int(m["keepalive_s"]),
                connect_timeout_s=float(m["connect_timeout_s"]),
                username=m["username"],
                password_file=path(m["password_file"]),
                tls=TlsSettings(
                    enabled=t["enabled"],
                    ca_file=path(t["ca_file"]),
                    cert_file=path(t["cert_file"]),
                    key_file=path(t["key_file"]),
                    verify_hostname=t["verify_hostname"],
                ),
                max_inflight=int(m["max_inflight"]),
                ack_timeout_s=float(m["ack_timeout_s"]),
                reconnect_min_s=float(m["reconnect_min_s"]),
                reconnect_max_s=float(m["reconnect_max_s"]),
                health_every_s=float(m["health_every_s"]),
                late_after_s=float(m["late_after_s"]),
            ),
        )


__all__ = ["UPLINK", "MqttSettings", "OutboxSettings", "SchemaError", "TlsSettings", "UplinkSettings"]
