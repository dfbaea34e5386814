"""The operating clock: the hours a machine ran, from the times of its ticks with input.

The time between two ticks with input is operating time unless it is longer than ``max_gap_s`` (the
machine was off) or not positive (a clock set back across a restart). A tick without input (the
daemon's ticks on a silent bus; a log has none there) neither adds nor moves the last tick, so the
daemon and a replay of its log count the same hours. A logger that records bursts some minutes
apart counts the time between them: each burst stands for the operation up to the next.

The prognosis counts its hours on it, and the on-board baseline its learning; one tick at a time
(:meth:`OperatingClock.hours`) or a stretch of ticks (:meth:`OperatingClock.seconds_columns`), the
same additions in the same order.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.schema import finite_number


class OperatingClock:
    def __init__(self, max_gap_s: float, operating_s: float = 0.0, last_t_s: float = math.nan) -> None:
        self.max_gap_s = max_gap_s
        self.operating_s = operating_s  # seconds of operation so far
        self.last_t_s = last_t_s  # the run time of the last tick with input (NaN: none yet)

    def hours(self, t_run_s: float, has_input: bool = True) -> float:
        """The operating hour of a tick at ``t_run_s`` (its time on the run's continuous base)."""
        if not has_input:
            return self.operating_s / 3600.0
        dt = t_run_s - self.last_t_s  # NaN for the first tick ever: adds nothing
        if 0.0 < dt <= self.max_gap_s:
            self.operating_s += dt
        self.last_t_s = t_run_s
        return self.operating_s / 3600.0

    def seconds_columns(
        self, t_run_s: NDArray[np.float64], has_input: NDArray[np.bool_], upto: int | None = None
    ) -> NDArray[np.float64]:
        """The operating seconds at every tick of a stretch, as :meth:`hours` tick after tick; the
        clock is left as the first ``upto`` ticks leave it (default: all)."""
        n = len(t_run_s)
        if not n:
            return np.empty(0)
        live = np.flatnonzero(has_input)
        t = t_run_s[live]
        prev = np.concatenate(([self.last_t_s], t[:-1]))
        dt = t - prev
        with np.errstate(invalid="ignore"):
            dt = np.where((dt > 0.0) & (dt <= self.max_gap_s), dt, 0.0)
        op_live = np.cumsum(np.concatenate(([self.operating_s], dt)))
        # a tick without input keeps the seconds of the last tick with input before it
        at = np.searchsorted(live, np.arange(n), side="right")
        op = op_live[at]
        upto = n if upto is None else upto
        if upto > 0:
            k = int(at[upto - 1])  # the ticks with input among the first upto
            self.operating_s = float(op_live[k])
            if k:
                self.last_t_s = float(t[k - 1])
        return op

    def to_dict(self) -> dict[str, Any]:
        last = self.last_t_s if math.isfinite(self.last_t_s) else None
        return {"operating_s": self.operating_s, "last_t_s": last}

    @staticmethod
    def state_from(c: Any, field: str) -> tuple[float, float]:
        """(operating_s, last_t_s) from a saved clock; ValueError naming ``field`` otherwise."""
        ok = isinstance(c, dict) and finite_number(c.get("operating_s")) and c["operating_s"] >= 0
        last = c.get("last_t_s") if isinstance(c, dict) else None
        if not (ok and (last is None or finite_number(last))):
            expected = "{operating_s: seconds, last_t_s: seconds or null}"
            raise ValueError(f"field {field!r}: expected {expected}, got {c!r:.80}")
        return float(c["operating_s"]), math.nan if last is None else float(last)
