"""Replay: a CAN log through the monitor core, exactly as the daemon would have processed it."""

from __future__ import annotations

import csv
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from cmcan.io.candump import Frame
from cmcan.monitor.core import LEVEL_NAMES, Monitor, OutputFrame, Tick

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
    frames_out: list[OutputFrame] = field(default_factory=list)
    first_t: float | None = None
    last_t: float | None = None


def replay(monitor: Monitor, frames_in: Iterable[Frame | can.Message], emit: bool = True) -> ReplayResult:
    """Feed every frame to the monitor in log order; the output frames it would have sent.

    ``frames_in`` holds ``can.Message`` objects or the plain tuples of :mod:`cmcan.io.candump`.
    """
    res = ReplayResult()
    feed = monitor.feed
    out = res.frames_out
    first = None
    last = None
    for m in frames_in:
        if isinstance(m, can.Message):
            m = (m.timestamp, m.arbitration_id, bytes(m.data), m.is_extended_id, m.is_remote_frame, m.is_error_frame)
        t = m[0]
        if first is None:
            first = t
        last = t
        frames = feed(*m)
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


def plot_ratio(
    ticks: list[Tick],
    t0: float,
    low_pct: float,
    high_pct: float,
    path: str | Path,
    failures_h: list[float] | None = None,
    title: str = "CM ratio",
) -> None:
    """CM ratio over operating hours with the thresholds (the paper's Figure 9)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    ev = [k for k in ticks if k.ratio_raw_pct > 0]
    fv = [k for k in ticks if k.filt_valid]
    fig, ax = plt.subplots(figsize=(11, 4.2))
    if ev:
        ax.plot(
            (np.array([k.t_s for k in ev]) - t0) / 3600,
            [k.ratio_raw_pct for k in ev],
            ".",
            ms=1,
            alpha=0.3,
            color="tab:gray",
            label="raw",
        )
    if fv:
        h = (np.array([k.t_s for k in fv]) - t0) / 3600
        ax.plot(h, [k.ratio_filt_pct for k in fv], "-", lw=1.2, color="tab:blue", label="filtered")
        for level, color in (("low", "tab:orange"), ("high", "tab:purple"), ("fault", "tab:red")):
            mask = np.array([LEVEL_NAMES[k.level] == level for k in fv])
            if mask.any():
                ax.plot(
                    h[mask],
                    np.array([k.ratio_filt_pct for k in fv])[mask],
                    "o",
                    ms=2,
                    color=color,
                    label=f"warning {level}",
                )
    ax.axhline(low_pct, color="tab:orange", ls="--", lw=1, label=f"low {low_pct:g} %")
    ax.axhline(high_pct, color="tab:purple", ls="--", lw=1, label=f"high {high_pct:g} %")
    for f in failures_h or []:
        ax.axvline(f, color="tab:red", lw=1, alpha=0.6)
    ax.set_xlabel("operating hours (h)")
    ax.set_ylabel("CM ratio (%)")
    lo = min([low_pct - 3] + [k.ratio_filt_pct for k in fv]) if fv else low_pct - 3
    hi = max([high_pct + 3] + [k.ratio_filt_pct for k in fv]) if fv else high_pct + 3
    ax.set_ylim(max(lo, 50), min(hi, 150))
    ax.set_title(title)
    ax.legend(loc="lower left", fontsize=7, ncol=3, markerscale=3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_emitted(path: str | Path, frames: list[OutputFrame], channel: str = "can0") -> None:
    import numpy as np

    from cmcan.io.candump import write_candump

    n = len(frames)
    data = np.zeros((n, 8), dtype=np.uint8)
    dlc = np.empty(n, dtype=np.int64)
    for i, f in enumerate(frames):
        data[i, : len(f.data)] = np.frombuffer(f.data, dtype=np.uint8)
        dlc[i] = len(f.data)
    write_candump(
        path, np.array([f.timestamp_s for f in frames]), np.array([f.frame_id for f in frames]), dlc, data, channel
    )
