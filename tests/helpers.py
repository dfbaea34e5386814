"""Shared builders for monitor, replay and daemon tests."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import numpy as np
import pytest

from cmcan import config as cfgmod
from cmcan.assemble import assemble, dbc_for
from cmcan.can.frame import Frame
from cmcan.io.candump import write_candump
from cmcan.monitor.core import Monitor
from cmcan.monitor.tick import Tick, TickColumns
from cmcan.sim import scenario as scn
from cmcan.sim.frames import Frames, frames_from_run
from cmcan.sim.run import Run, simulate


class TickLog(list):
    """A tick listener that keeps every tick the monitor evaluates (memory grows with the run)."""

    def tick(self, tick: Tick) -> None:
        self.append(tick)

    def ticks(self, chunk: TickColumns) -> None:
        self.extend(chunk.tick(i) for i in range(len(chunk)))


def timeline(mon: Monitor) -> TickLog:
    """The ticks ``mon`` evaluated since :func:`monitor` made it (or since first asked)."""
    for x in mon.listeners:
        if isinstance(x, TickLog):
            return x
    log = TickLog()
    mon.listeners.append(log)
    return log


def monitor(cfg: cfgmod.Config | None = None, totals=None, **assembled) -> Monitor:
    """The shipped configuration's monitor (or ``cfg``'s), keeping its ticks (:func:`timeline`)."""
    mon = assemble(cfg or cfgmod.load(), totals=totals, **assembled).monitor
    timeline(mon)
    return mon


def frame(t: float, can_id: int, data: bytes, extended=False, remote=False, error=False, channel="can0") -> Frame:
    return Frame(float(t), channel, int(can_id), extended, remote, error, False, bytes(data))


def sim_frames(name: str = "two_set_validation", **over) -> tuple[Run, Frames]:
    s = scn.load(scn.shipped(name))
    s = s.with_overrides(**over) if over else s
    db = dbc_for(cfgmod.load())
    run = simulate(s, db)
    return run, frames_from_run(run, db)


def write_log(path: Path, frames: Frames) -> Path:
    write_candump(path, frames.timestamp_s, frames.arbitration_id, frames.dlc, frames.data)
    return path


def messages(frames: Frames) -> list[can.Message]:
    return [
        can.Message(timestamp=t, arbitration_id=i, data=bytes(d), is_extended_id=False)
        for t, i, d in zip(frames.timestamp_s.tolist(), frames.arbitration_id.tolist(), frames.data, strict=True)
    ]


def as_frames(frames: Frames, channel: str = "can0") -> list[Frame]:
    return [
        frame(t, i, d, channel=channel)
        for t, i, d in zip(frames.timestamp_s.tolist(), frames.arbitration_id.tolist(), frames.data, strict=True)
    ]


def feed_all(mon, frames: Frames) -> list:
    out = []
    ts = frames.timestamp_s.tolist()
    ids = frames.arbitration_id.tolist()
    for t, i, d in zip(ts, ids, frames.data, strict=True):
        out += mon.feed(frame(t, i, d))
    out += mon.flush()
    return out


def first_warnings(history: list[dict], start_epoch_s: float) -> list[tuple[float, str]]:
    return [((h["t_s"] - start_epoch_s) / 3600.0, h["to"]) for h in history]


def ratio_ok(x: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(x)))


IMPLS = ("native", "numpy")  # the replay's reading and writing: by the C helpers, or with numpy


@contextmanager
def helpers_impl(impl: str) -> Iterator[None]:
    """Read and write logs with the C helpers (skipped where the install could not build them) or
    with the numpy code that stands in for them."""
    from cmcan.io import native

    saved = native.LIB
    if impl == "native" and saved is None:
        pytest.skip("the C helpers are not built here (no C compiler at install)")
    native.LIB = saved if impl == "native" else None
    try:
        yield
    finally:
        native.LIB = saved


def systemd_verify(unit: str, file_name: str) -> None:
    """``systemd-analyze verify`` of the unit text ``unit`` saved as ``file_name``: it must pass with
    no unknown or ignored setting."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / file_name
        p.write_text(unit)
        res = subprocess.run(["systemd-analyze", "verify", str(p)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "Unknown" not in res.stderr and "ignoring" not in res.stderr.lower(), res.stderr
