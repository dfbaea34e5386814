"""One evaluation tick's result: the operating point's verdict, prediction, ratio and warning state."""

from __future__ import annotations

from dataclasses import dataclass

from cmcan.monitor.gating import Gate
from cmcan.monitor.warnings import Level, Reason

LEVEL_NAMES = {Level.OK: "ok", Level.LOW: "low", Level.HIGH: "high", Level.FAULT: "fault"}


@dataclass(frozen=True, slots=True, kw_only=True)
class Tick:
    t_s: float
    gate: Gate
    # The output quantity (motor speed in rpm or flow in l/min): measured, predicted by the gray box,
    # by its white-box baseline; the predictions are 0 where the point was not evaluated.
    measured: float
    predicted: float
    whitebox: float
    ratio_raw_pct: float  # 0 where the point was not evaluated
    ratio_filt_pct: float
    extra_leak_lpm: float
    filt_valid: bool
    level: Level
    reason: Reason
    time_below_s: float
    run_shift_s: float = 0.0  # t_s + this: the tick on the run's continuous time base (Monitor.run_shift_s)
