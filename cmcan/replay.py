"""Replay: a CAN log through the monitor core, exactly as the daemon would have processed it."""

from __future__ import annotations

import csv
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cmcan.frame import Frame
from cmcan.monitor.core import Monitor
from cmcan.monitor.tick import LEVEL_NAMES, Tick

TIMELINE_COLUMNS = (
    "time_s",
    "operating_h",
    "gate",
    "motor_speed_meas_rpm",
    "motor_speed_pred_rpm",
    "motor_speed_whitebox_rpm",
    "cm_ratio_raw_pct",
    "cm_ratio_filt_pct",
    "cm_filt_valid",
    "extra_leak_lpm",
    "warning_level",
    "warning_reason",
    "time_below_threshold_s",
)


@dataclass
class ReplayResult:
    frames_out: list[Frame] = field(default_factory=list)
    first_t: float | None = None
    last_t: float | None = None


def replay(monitor: Monitor, frames_in: Iterable[Frame], emit: bool = True) -> ReplayResult:
    """Feed every frame to the monitor in log order; the output frames it would have sent."""
    res = ReplayResult()
    feed = monitor.feed
    out = res.frames_out
    first = None
    last = None
    for f in frames_in:
        t = f.timestamp_s
        if first is None:
            first = t
        last = t
        frames = feed(f)
        if frames and emit:
            out.extend(frames)
    tail = monitor.flush()
    if emit:
        out.extend(tail)
    res.first_t, res.last_t = first, last
    return res


def write_timeline(path: str | Path, ticks: list[Tick], t0: float) -> None:
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "w", newline="", encoding="ascii") as f:
        w = csv.writer(f)
        w.writerow(TIMELINE_COLUMNS)
        for k in ticks:
            w.writerow(
                [
                    f"{k.t_s:.3f}",
                    f"{(k.t_s - t0) / 3600.0:.6f}",
                    k.gate.name.lower(),
                    f"{k.motor_speed_meas_rpm:.2f}",
                    f"{k.motor_speed_pred_rpm:.2f}",
                    f"{k.motor_speed_whitebox_rpm:.2f}",
                    f"{k.ratio_raw_pct:.3f}",
                    f"{k.ratio_filt_pct:.3f}",
                    int(k.filt_valid),
                    f"{k.extra_leak_lpm:.3f}",
                    LEVEL_NAMES[k.level],
                    k.reason.name.lower(),
                    f"{k.time_below_s:.1f}",
                ]
            )
    tmp.replace(p)


def warnings_summary(monitor: Monitor, t0: float) -> list[dict[str, Any]]:
    """Level changes with their times (frame time and hours since the log's first frame)."""
    return [{**h, "operating_h": (h["t_s"] - t0) / 3600.0} for h in monitor.totals.history]


def write_emitted(path: str | Path, frames: list[Frame], channel: str = "can0") -> None:
    """The frames the daemon would have sent, as a candump -l log (each on its own channel)."""
    from cmcan.io.candump import write_frames

    write_frames(path, frames, channel)
