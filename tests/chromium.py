"""Headless Chromium driven over its DevTools protocol on a pipe (stdlib only): open a page, collect
console errors, uncaught exceptions and network requests, evaluate a script, take a screenshot.

Debian's ``chromium`` runs as root here with ``--no-sandbox``; the background-networking flags keep
it from calling out at start (the machine has no network but the package registries)."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import queue
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-quic",
    "--disable-extensions",
    "--remote-debugging-pipe",
)


def chromium_path() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


@dataclass
class PageResult:
    errors: list[str] = field(default_factory=list)  # console errors, uncaught exceptions, failed loads
    requests: list[str] = field(default_factory=list)  # every URL the page asked for
    values: dict[str, Any] = field(default_factory=dict)  # results of the evaluated expressions
    screenshot: Path | None = None


class _Pipe:
    def __init__(self, exe: str, profile: str) -> None:
        to_r, self._to_w = os.pipe()  # we write, Chromium reads fd 3
        self._from_r, from_w = os.pipe()  # Chromium writes fd 4, we read

        def fds() -> None:  # in the child, before exec: the pipes on fds 3 and 4
            a, b = os.dup(to_r), os.dup(from_w)
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.proc = subprocess.Popen(
            [exe, *FLAGS, f"--user-data-dir={profile}", "about:blank"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=fds,
            close_fds=False,
        )
        os.close(to_r)
        os.close(from_w)
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self.replies: dict[int, dict[str, Any]] = {}
        self.cv = threading.Condition()
        self.next_id = 0
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        buf = b""
        while True:
            chunk = os.read(self._from_r, 1 << 16)
            if not chunk:
                return
            buf += chunk
            while b"\0" in buf:
                raw, buf = buf.split(b"\0", 1)
                msg = json.loads(raw)
                if "id" in msg:
                    with self.cv:
                        self.replies[msg["id"]] = msg
                        self.cv.notify_all()
                else:
                    self.events.put(msg)

    def call(
        self, method: str, params: dict[str, Any] | None = None, session: str | None = None, timeout: float = 60.0
    ) -> dict[str, Any]:
        self.next_id += 1
        i = self.next_id
        msg: dict[str, Any] = {"id": i, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self._to_w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        with self.cv:
            while i not in self.replies:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"Chromium did not answer {method} within {timeout} s")
                self.cv.wait(left)
            reply = self.replies.pop(i)
        if "error" in reply:
            raise RuntimeError(f"{method}: {reply['error']}")
        return reply.get("result", {})

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.call("Browser.close", timeout=10)
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._to_w)


def open_page(
    url: str,
    screenshot: Path | None,
    expressions: dict[str, str] | None = None,
    width: int = 1280,
    height: int = 2400,
    timeout: float = 60.0,
) -> PageResult:
    exe = chromium_path()
    if exe is None:
        raise FileNotFoundError("chromium is not installed (Debian package chromium)")
    res = PageResult()
    with tempfile.TemporaryDirectory(prefix="cmcan-chromium-") as profile:
        p = _Pipe(exe, profile)
        try:
            target = p.call("Target.createTarget", {"url": "about:blank"})["targetId"]
            s = p.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
            for domain in ("Runtime", "Log", "Network", "Page"):
                p.call(f"{domain}.enable", session=s)
            p.call(
                "Emulation.setDeviceMetricsOverride",
                {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
                session=s,
            )
            p.call("Page.navigate", {"url": url}, session=s)
            deadline = time.monotonic() + timeout
            loaded = False
            while not loaded:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"{url} did not finish loading within {timeout} s")
                ev = p.events.get(timeout=left)
                loaded = _note(ev, res) == "loaded"
            time.sleep(0.3)  # late console messages
            while not p.events.empty():
                _note(p.events.get_nowait(), res)
            for name, expr in (expressions or {}).items():
                r = p.call("Runtime.evaluate", {"expression": expr, "returnByValue": True}, session=s)
                if "exceptionDetails" in r:
                    res.errors.append(f"evaluating {name}: {r['exceptionDetails'].get('text')}")
                res.values[name] = r.get("result", {}).get("value")
            if screenshot is not None:
                shot = p.call("Page.captureScreenshot", {"format": "png"}, session=s)
                screenshot.parent.mkdir(parents=True, exist_ok=True)
                screenshot.write_bytes(base64.b64decode(shot["data"]))
                res.screenshot = screenshot
            while not p.events.empty():
                _note(p.events.get_nowait(), res)
        finally:
            p.close()
    return res


def _note(ev: dict[str, Any], res: PageResult) -> str | None:
    m, prm = ev.get("method"), ev.get("params", {})
    if m == "Page.loadEventFired":
        return "loaded"
    if m == "Runtime.exceptionThrown":
        res.errors.append(f"exception: {prm.get('exceptionDetails', {}).get('text')}")
    elif m == "Runtime.consoleAPICalled" and prm.get("type") in ("error", "assert"):
        res.errors.append(
            "console: " + " ".join(str(a.get("value", a.get("description"))) for a in prm.get("args", []))
        )
    elif m == "Log.entryAdded" and prm.get("entry", {}).get("level") == "error":
        res.errors.append(f"log: {prm['entry'].get('text')} {prm['entry'].get('url', '')}")
    elif m == "Network.requestWillBeSent":
        res.requests.append(prm.get("request", {}).get("url", ""))
    elif m == "Network.loadingFailed":
        res.errors.append(f"load failed: {prm.get('errorText')}")
    return None
