"""One evaluation tick's result, many ticks as columns, and the one way ticks leave the core.

Every tick the monitor evaluates goes to its :class:`TickListener` s: one tick at a time
(``tick``) from the per-frame path, a stretch of ticks as columns (``ticks``) from the array path,
in the order they were evaluated. The daemon's uplink, the replay's files and the fleet's data set
listen this way; nothing polls the monitor for its last tick.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.gating import Gate
from cmcan.monitor.warnings import Level, Reason
from cmcan.roles import MODEL_INPUTS

# A tick's operating point: the model's inputs, each a field of :class:`Tick` under its role's name
OPERATING_POINT: tuple[str, ...] = MODEL_INPUTS
# The on-board baseline's progress on every tick: hours learned, envelope covered, distance from the type
BASELINE_PROGRESS = ("baseline_learned_h", "baseline_coverage_pct", "baseline_distance_lpm")
# The prognosis's codes and hours on every tick (together cmcan.monitor.prognosis.FIELDS)
PROGNOSIS_CODES = ("prognosis_state", "prognosis_direction")
PROGNOSIS_HOURS = (
    "prognosis_to_warning_h",
    "prognosis_to_eol_p10_h",
    "prognosis_to_eol_p50_h",
    "prognosis_to_eol_p90_h",
)
LEVEL_NAMES = {Level.OK: "ok", Level.LOW: "low", Level.HIGH: "high", Level.FAULT: "fault"}


class Tick(NamedTuple):
    """One evaluated tick (made by keyword; a tuple: a frozen dataclass's init of these fields costs
    microseconds at every tick on the daemon's path)."""

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
    # The operating point: the window means of the model's inputs at the tick (NaN where a role had no
    # sample in its window), what a fleet's type model trains on (:data:`OPERATING_POINT`)
    pump_speed_rpm: float = math.nan
    pump_disp_cc: float = math.nan
    dp_bar: float = math.nan
    temp_c: float = math.nan
    # the on-board baseline (cmcan.monitor.baseline): 0 none configured, else its Mode; its progress
    baseline_state: int = 0
    baseline_learned_h: float = 0.0
    baseline_coverage_pct: float = 0.0
    baseline_distance_lpm: float = 0.0
    # the prognosis where configured (cmcan.monitor.prognosis): 0 none configured, else 1 none, 2 trend,
    # 3 imminent; the trend's direction (0 none, 1 low: wear, 2 high: the ratio rising); operating
    # hours to that side's warning (p50) and to end of life (p10, p50, p90), NaN without a trend, inf
    # where the estimate never gets there
    prognosis_state: int = 0
    prognosis_direction: int = 0
    prognosis_to_warning_h: float = math.nan
    prognosis_to_eol_p10_h: float = math.nan
    prognosis_to_eol_p50_h: float = math.nan
    prognosis_to_eol_p90_h: float = math.nan


@dataclass(frozen=True)
class TickColumns:
    """A chunk of evaluation ticks, one array per field of :class:`Tick`."""

    t_s: NDArray[np.float64]
    gate: NDArray[np.int8]
    measured: NDArray[np.float64]  # the output quantity: motor speed (rpm) or flow (l/min)
    predicted: NDArray[np.float64]
    whitebox: NDArray[np.float64]
    ratio_raw_pct: NDArray[np.float64]
    ratio_filt_pct: NDArray[np.float64]
    extra_leak_lpm: NDArray[np.float64]
    filt_valid: NDArray[np.bool_]
    level: NDArray[np.int8]
    reason: NDArray[np.int8]
    time_below_s: NDArray[np.float64]
    # t_s + this: each tick on the run's continuous time base (the wall clock's steps undone); zeros
    # when not given
    run_shift_s: NDArray[np.float64] = None  # type: ignore[assignment]
    # the operating point (window means of the model's inputs; NaN when not given)
    pump_speed_rpm: NDArray[np.float64] = None  # type: ignore[assignment]
    pump_disp_cc: NDArray[np.float64] = None  # type: ignore[assignment]
    dp_bar: NDArray[np.float64] = None  # type: ignore[assignment]
    temp_c: NDArray[np.float64] = None  # type: ignore[assignment]
    baseline_state: NDArray[np.int8] = None  # type: ignore[assignment]
    baseline_learned_h: NDArray[np.float64] = None  # type: ignore[assignment]
    baseline_coverage_pct: NDArray[np.float64] = None  # type: ignore[assignment]
    baseline_distance_lpm: NDArray[np.float64] = None  # type: ignore[assignment]
    prognosis_state: NDArray[np.int8] = None  # type: ignore[assignment]
    prognosis_direction: NDArray[np.int8] = None  # type: ignore[assignment]
    prognosis_to_warning_h: NDArray[np.float64] = None  # type: ignore[assignment]
    prognosis_to_eol_p10_h: NDArray[np.float64] = None  # type: ignore[assignment]
    prognosis_to_eol_p50_h: NDArray[np.float64] = None  # type: ignore[assignment]
    prognosis_to_eol_p90_h: NDArray[np.float64] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        for name in PROGNOSIS_CODES:
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.zeros(len(self.t_s), dtype=np.int8))
        for name in PROGNOSIS_HOURS:
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(len(self.t_s), np.nan))
        if self.baseline_state is None:
            object.__setattr__(self, "baseline_state", np.zeros(len(self.t_s), dtype=np.int8))
        for name in BASELINE_PROGRESS:
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.zeros(len(self.t_s)))
        if self.run_shift_s is None:
            object.__setattr__(self, "run_shift_s", np.zeros(len(self.t_s)))
        for name in OPERATING_POINT:
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(len(self.t_s), np.nan))

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def t_run_s(self) -> NDArray[np.float64]:
        """The ticks' times on the run's continuous time base, which operating hours count on."""
        return self.t_s + self.run_shift_s

    def tick(self, i: int) -> Tick:
        """Row ``i`` as a :class:`Tick`."""
        return Tick(
            t_s=float(self.t_s[i]),
            gate=Gate(int(self.gate[i])),
            measured=float(self.measured[i]),
            predicted=float(self.predicted[i]),
            whitebox=float(self.whitebox[i]),
            ratio_raw_pct=float(self.ratio_raw_pct[i]),
            ratio_filt_pct=float(self.ratio_filt_pct[i]),
            extra_leak_lpm=float(self.extra_leak_lpm[i]),
            filt_valid=bool(self.filt_valid[i]),
            level=Level(int(self.level[i])),
            reason=Reason(int(self.reason[i])),
            time_below_s=float(self.time_below_s[i]),
            run_shift_s=float(self.run_shift_s[i]),
            **{name: float(getattr(self, name)[i]) for name in OPERATING_POINT},
            baseline_state=int(self.baseline_state[i]),
            **{name: float(getattr(self, name)[i]) for name in BASELINE_PROGRESS},
            **{name: int(getattr(self, name)[i]) for name in PROGNOSIS_CODES},
            **{name: float(getattr(self, name)[i]) for name in PROGNOSIS_HOURS},
        )

    @classmethod
    def from_ticks(cls, ticks: Sequence[Tick]) -> TickColumns:
        def col(name: str, dtype: Any) -> NDArray[Any]:
            return np.fromiter((getattr(k, name) for k in ticks), dtype=dtype, count=len(ticks))

        return cls(
            t_s=col("t_s", np.float64),
            gate=col("gate", np.int8),
            measured=col("measured", np.float64),
            predicted=col("predicted", np.float64),
            whitebox=col("whitebox", np.float64),
            ratio_raw_pct=col("ratio_raw_pct", np.float64),
            ratio_filt_pct=col("ratio_filt_pct", np.float64),
            extra_leak_lpm=col("extra_leak_lpm", np.float64),
            filt_valid=col("filt_valid", np.bool_),
            level=col("level", np.int8),
            reason=col("reason", np.int8),
            time_below_s=col("time_below_s", np.float64),
            run_shift_s=col("run_shift_s", np.float64),
            **{name: col(name, np.float64) for name in OPERATING_POINT},
            baseline_state=col("baseline_state", np.int8),
            **{name: col(name, np.float64) for name in BASELINE_PROGRESS},
            **{name: col(name, np.int8) for name in PROGNOSIS_CODES},
            **{name: col(name, np.float64) for name in PROGNOSIS_HOURS},
        )

    @classmethod
    def concat(cls, chunks: Sequence[TickColumns]) -> TickColumns:
        if not chunks:
            return cls.from_ticks([])
        return cls(**{n: np.concatenate([getattr(c, n) for c in chunks]) for n in cls.__dataclass_fields__})


class TickListener(Protocol):
    """Where evaluated ticks go: one at a time from the per-frame path, as columns from the array
    path, in evaluation order."""

    def tick(self, tick: Tick) -> None: ...
    def ticks(self, chunk: TickColumns) -> None: ...
