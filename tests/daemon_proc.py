"""``cmcan run`` as a real process on python-can's virtual bus, with a notify socket to see READY,
RELOADING and STATUS as systemd would (for the signal, lock and reload tests)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import yaml

from tests.conftest import ROOT


def virtual_config(tmp: Path, name: str = "cmcan.yaml", **sections) -> Path:
    """The shipped configuration on the virtual interface, state in ``tmp/state``; ``sections``
    update top-level sections (e.g. ``thresholds={"low_pct": 97}``)."""
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    raw["bus"].update(interface="virtual", channel=f"t-{os.getpid()}-{tmp.name}")
    raw["state"]["directory"] = str(tmp / "state")
    for key, value in sections.items():
        if isinstance(value, dict) and isinstance(raw.get(key), dict):
            raw[key].update(value)
        else:
            raw[key] = value
    (tmp / "state").mkdir(exist_ok=True)
    p = tmp / name
    p.write_text(yaml.safe_dump(raw))
    return p


class DaemonProc:
    """One ``cmcan run`` process; ``notes`` collects what it sends to its notify socket."""

    def __init__(
        self, tmp: Path, cfg: Path, name: str = "d", wait_ready: bool = True, launcher: list[str] | None = None
    ) -> None:
        self.sock_path = tmp / f"{name}.sock"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(self.sock_path))
        self.sock.settimeout(0.1)
        self.notes: list[str] = []
        self._stop = False
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()
        self.err_path = tmp / f"{name}.stderr"
        self._err = open(self.err_path, "w")  # noqa: SIM115 - written by the process until it ends
        env = {**os.environ, "NOTIFY_SOCKET": str(self.sock_path), "PYTHONUNBUFFERED": "1"}
        self.proc = subprocess.Popen(
            [*(launcher or [sys.executable, "-m", "cmcan"]), "run", "--config", str(cfg)],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=self._err,
            cwd=ROOT,
        )
        if wait_ready:
            assert self.wait_for(lambda: self.count("READY=1") >= 1 or self.proc.poll() is not None, 120)
            assert self.proc.poll() is None, self.stderr()

    def _listen(self) -> None:
        while not self._stop:
            try:
                self.notes.append(self.sock.recv(65536).decode())
            except (TimeoutError, OSError):
                continue

    def count(self, field: str) -> int:
        return sum(field in n.split("\n") for n in list(self.notes))

    def stderr(self) -> str:
        return self.err_path.read_text()

    def wait_for(self, pred, timeout: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred():
                return True
            time.sleep(0.05)
        return bool(pred())

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def wait(self, timeout: float = 30.0) -> int:
        try:
            return self.proc.wait(timeout)
        finally:
            self.close()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)
        self._stop = True
        self._thread.join(2)
        self.sock.close()
        self._err.close()
