"""Where the vcan tests can run: natively (vcan0 here, or creatable), or in the throwaway VM."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from tests.vcan.vm import VmError, cache_dir, guest_script, run_in_vm


class SocketListener:
    """A thread that keeps what a socket receives, each item stamped on arrival (not when the wait
    began); a subclass says how one item is read (:meth:`read`) and sets up what that needs before
    calling this ``__init__``, which starts the thread."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        sock.settimeout(0.2)
        self.got: list = []
        self.stop = False
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def read(self) -> tuple:
        raise NotImplementedError

    def _loop(self) -> None:
        while not self.stop:
            try:
                item = self.read()
            except (TimeoutError, OSError):
                continue
            self.got.append((time.monotonic(), *item))

    def close(self) -> None:
        self.stop = True
        self.thread.join(2)
        self.sock.close()


PROJECT = Path(__file__).resolve().parents[2]
TEST_FILE = "tests/vcan/test_vcan.py"


def in_vm() -> bool:
    return os.environ.get("CMCAN_IN_VM") == "1"


def vcan_here() -> bool:
    """True when this kernel speaks CAN and vcan0 is up (creating it when we may)."""
    if in_vm():
        return True
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (OSError, AttributeError):
        return False
    for dev in ("vcan0", "vcan1"):
        if not Path(f"/sys/class/net/{dev}").exists() and os.geteuid() == 0 and shutil.which("ip"):
            subprocess.run(["ip", "link", "add", "dev", dev, "type", "vcan"], capture_output=True)
            subprocess.run(["ip", "link", "set", "up", dev], capture_output=True)
    return Path("/sys/class/net/vcan0").exists() and all(shutil.which(t) for t in ("candump", "canplayer"))


@dataclass
class VmRun:
    """The outcome of the vcan tests run once inside the VM, by test name."""

    exit_code: int | None = None
    error: str | None = None
    outcomes: dict[str, tuple[str, str]] = field(default_factory=dict)
    console_tail: str = ""

    def report(self, name: str) -> tuple[str, str]:
        if self.error is not None:
            return "failed", f"the VM could not run the vcan tests: {self.error}"
        if name not in self.outcomes:
            return "failed", (
                f"the VM run (exit code {self.exit_code}) did not report {name}; console tail:\n" + self.console_tail
            )
        return self.outcomes[name]


def parse_junit(path: Path) -> dict[str, tuple[str, str]]:
    out = {}
    for case in ET.parse(path).getroot().iter("testcase"):
        name = case.get("name", "")
        kind, text = "passed", ""
        for child in case:
            if child.tag in ("failure", "error"):
                kind, text = "failed", (child.get("message") or "") + "\n" + (child.text or "")
            elif child.tag == "skipped":
                kind, text = "skipped", child.get("message") or ""
        out[name] = (kind, text)
    return out


def run_vcan_tests_in_vm(pytest_args: list[str] | None = None, echo: bool = True) -> VmRun:
    results = cache_dir() / "runs" / str(os.getpid())
    if results.exists():
        shutil.rmtree(results)
    results.mkdir(parents=True)
    junit = results / "junit.xml"
    cmd = [
        sys.executable,
        "-m",
        "pytest",
        "-m",
        "vcan",
        TEST_FILE,
        "-p",
        "no:cacheprovider",
        "-n0",  # one process in the VM: its timing tests want the guest's CPU to themselves
        "-v",
        "-rA",
        f"--junitxml={junit}",
        *(pytest_args or []),
    ]
    run = VmRun()
    try:
        res = run_in_vm(guest_script(PROJECT, results, cmd), PROJECT, results, timeout_s=1500, echo=echo)
    except VmError as exc:
        run.error = str(exc)
        return run
    run.exit_code = res.exit_code
    run.console_tail = res.console[-3000:]
    if junit.exists():
        run.outcomes = parse_junit(junit)
    else:
        run.error = f"no test report came back (exit code {res.exit_code}); console tail:\n{run.console_tail}"
    return run
