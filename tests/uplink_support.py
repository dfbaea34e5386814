"""A real mosquitto broker, an MQTT subscriber and throwaway certificates for the uplink tests."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

MOSQUITTO = shutil.which("mosquitto") or next(
    (p for p in ("/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto") if os.access(p, os.X_OK)), None
)
needs_mosquitto = pytest.mark.skipif(
    MOSQUITTO is None, reason="mosquitto is not installed (apt-get install mosquitto; CI installs it)"
)
needs_openssl = pytest.mark.skipif(shutil.which("openssl") is None, reason="the openssl command is not installed")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def closed_port() -> Iterator[int]:
    """A port nothing listens on for as long as the block runs: bound here, never listening, so a
    connection is refused and no other process (a broker of another test) can take it meanwhile."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        yield s.getsockname()[1]


def wait_port(port: int, up: bool = True, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                if up:
                    return
        except OSError:
            if not up:
                return
        time.sleep(0.02)
    raise TimeoutError(f"port {port} did not come {'up' if up else 'down'} within {timeout_s} s")


class Broker:
    """mosquitto on a free loopback port: ``-p PORT`` with no configuration file, or with ``conf``
    lines (a listener on the port is added) for persistence or TLS."""

    def __init__(self, workdir: Path, conf: list[str] | None = None, port: int | None = None) -> None:
        assert MOSQUITTO is not None
        self.port = port or free_port()
        self.workdir = workdir
        self.conf = conf
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = workdir / f"mosquitto-{self.port}.log"

    def start(self, wait: bool = True) -> Broker:
        if self.conf is None:
            cmd = [MOSQUITTO, "-p", str(self.port)]
        else:
            path = self.workdir / f"mosquitto-{self.port}.conf"
            # As root mosquitto would drop to its own user, which cannot reach pytest's private tmp.
            keep_user = ["user root"] if os.geteuid() == 0 else []
            path.write_text("\n".join([f"listener {self.port} 127.0.0.1", *keep_user, *self.conf]) + "\n")
            cmd = [MOSQUITTO, "-c", str(path)]
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=self.workdir)
        if wait:
            wait_port(self.port)
        return self

    def kill(self, sig: int = signal.SIGKILL) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(10)
        self.proc = None

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def log_text(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""


@dataclass
class Received:
    topic: str
    payload: dict[str, Any]


@dataclass
class Subscriber:
    """A QoS 1 subscriber with a persistent session that reconnects by itself."""

    port: int
    topic: str
    client_id: str = "test-subscriber"
    tls: dict[str, Any] | None = None
    messages: list[Received] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    subscribed: threading.Event = field(default_factory=threading.Event)

    def start(self) -> Subscriber:
        c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=self.client_id, clean_session=False)
        if self.tls is not None:
            c.tls_set(**self.tls)
        c.reconnect_delay_set(0.05, 0.2)

        def on_connect(client: mqtt.Client, _u: Any, _f: Any, rc: Any, _p: Any) -> None:
            if not rc.is_failure:
                client.subscribe(self.topic, qos=1)

        def on_subscribe(*_a: Any) -> None:
            self.subscribed.set()

        def on_message(_c: mqtt.Client, _u: Any, m: mqtt.MQTTMessage) -> None:
            with self.lock:
                self.messages.append(Received(m.topic, json.loads(m.payload)))

        c.on_connect = on_connect
        c.on_subscribe = on_subscribe
        c.on_message = on_message
        c.connect_async("127.0.0.1", self.port)
        c.loop_start()
        self.client = c
        if not self.subscribed.wait(10):
            raise TimeoutError("the subscriber did not get its SUBACK")
        return self

    def stop(self) -> None:
        with contextlib.suppress(Exception):
            self.client.disconnect()
        self.client.loop_stop()

    def snapshot(self) -> list[Received]:
        with self.lock:
            return list(self.messages)

    def data(self) -> list[Received]:
        return [m for m in self.snapshot() if m.payload.get("kind") in ("event", "summary", "dropped")]

    def wait_for(self, pred: Any, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if pred(self.snapshot()):
                return
            time.sleep(0.05)
        raise TimeoutError(f"subscriber: {what} not seen within {timeout_s} s")


def make_certs(d: Path) -> dict[str, Path]:
    """A throwaway CA, a broker certificate for 127.0.0.1/localhost, a client certificate, and a
    second CA that signed nothing of these (for the untrusted case)."""

    def ssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)

    for ca in ("ca", "other-ca"):
        ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", f"/CN=cmcan test {ca}",
            "-keyout", f"{ca}.key", "-out", f"{ca}.crt")  # fmt: skip
    (d / "san.ext").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    for name, cn, ext in (("server", "localhost", ["-extfile", "san.ext"]), ("client", "cmcan-wl-0042", [])):
        ssl(
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-subj",
            f"/CN={cn}",
            "-keyout",
            f"{name}.key",
            "-out",
            f"{name}.csr",
        )
        ssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.crt", "-CAkey", "ca.key", "-CAcreateserial", "-days", "2",
            "-out", f"{name}.crt", *ext)  # fmt: skip
    return {n: d / n for n in ("ca.crt", "other-ca.crt", "server.crt", "server.key", "client.crt", "client.key")}


def uplink_config(path: Path, state_dir: Path, port: int, **uplink: Any) -> Path:
    """A configuration for the reference drive with an enabled uplink section."""
    from cmcan.config import default_config_path
    from cmcan.schema import load_yaml

    root = default_config_path().parent
    raw = load_yaml(default_config_path())
    raw["dbc"] = str((root / raw["dbc"]).resolve())
    raw["state"] = {"directory": str(state_dir)}
    mqtt_over = uplink.pop("mqtt", {})
    raw["uplink"] = {
        "enabled": True,
        "machine_id": "wl-0042",
        **uplink,
        "mqtt": {"host": "127.0.0.1", "port": port, "reconnect_min_s": 0.2, "reconnect_max_s": 1.0, **mqtt_over},
    }
    import yaml

    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path
