"""The warning state machine: ok, low (ratio below threshold), high (ratio above), fault (inputs).

Two layers, each debounced in *evaluated* time (the sum of evaluation periods that counted):
- the condition, from the filtered CM ratio: ok -> low after ``debounce_s`` below ``low_pct``,
  ok -> high after ``debounce_s`` above ``high_pct``; back to ok only after ``debounce_s`` inside the
  band narrowed by ``hysteresis_pct``; low <-> high directly after the debounce on the other side;
- extrapolated points (evaluated outside the model's training envelope, ``Gate.EXTRAPOLATED``) count
  like any evaluated point toward raising a low or high warning, so a fault that pushes the operating
  point out of the envelope is still warned about; but they cannot clear a warning: the return to ok
  needs ``debounce_s`` of points inside the envelope (an extrapolated point inside the band leaves
  that count where it is, one outside the band resets it, as any point does);
- the fault, from the gate: inputs stale or implausible, or a model that gives no plausible
  prediction, for ``fault_after_s`` of tick time raise it (reason: the cause at the tick it rises), as
  many seconds of good input clear it. While faulted the published level is fault; the condition
  underneath is kept and comes back when the fault clears.
Time is the evaluation ticks' own (frame time); nothing here reads a clock.

A warning counts when the condition becomes low or high (:func:`warning_raised`), a fault when one
rises (:func:`fault_raised`). The machine steps one tick at a time (:meth:`WarningMachine.step`) or
runs a stretch of ticks (:meth:`WarningMachine.run_columns`), which skips runs of quiet ticks in the
ok state in one step (:meth:`WarningMachine.skip`) and steps the others.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.gating import EVALUATED, Gate, is_evaluated


class Level(IntEnum):
    OK = 0
    LOW = 1
    HIGH = 2
    FAULT = 3


class Reason(IntEnum):
    NONE = 0
    RATIO_LOW = 1
    RATIO_HIGH = 2
    INPUT_STALE = 3
    INPUT_IMPLAUSIBLE = 4
    MODEL_ERROR = 5


@dataclass(frozen=True)
class Thresholds:
    low_pct: float = 98.0
    high_pct: float = 102.0
    hysteresis_pct: float = 0.5
    debounce_s: float = 60.0
    fault_after_s: float = 5.0


@dataclass(frozen=True)
class Transition:
    t_s: float
    level_from: Level
    level_to: Level
    reason: Reason
    ratio_pct: float | None


# Durations add up tick by tick in floating point: ten 0.1 s ticks are 0.9999999999999999 s.
_EPS = 1e-6


def band(ratio_pct: Any, th: Thresholds) -> tuple[Any, Any, Any]:
    """Where a filtered ratio lies (a float, or per value of an array): below the low threshold,
    above the high one, inside the band narrowed by the hysteresis (where a warning may clear). The
    one definition :meth:`WarningMachine.step` and its runs over quiet ticks share; NaN is none."""
    below = ratio_pct < th.low_pct
    above = ratio_pct > th.high_pct
    inside = (th.low_pct + th.hysteresis_pct <= ratio_pct) & (ratio_pct <= th.high_pct - th.hysteresis_pct)
    return below, above, inside


def warning_raised(before: Level, after: Level) -> bool:
    """A step that changed the condition to low or high raised a warning."""
    return after != before and after in (Level.LOW, Level.HIGH)


def fault_raised(before: Reason, after: Reason) -> bool:
    return before == Reason.NONE and after != Reason.NONE


@dataclass
class WarningColumns:
    """The machine after each tick of a stretch: its condition and reason, fault, the evaluated time
    below the threshold, the warnings raised so far (``warning_count``), and the counts at the end."""

    condition: NDArray[np.int8]
    condition_reason: NDArray[np.int8]
    fault: NDArray[np.int8]
    time_below_s: NDArray[np.float64]
    warning_count: NDArray[np.int64]
    warnings: int
    faults: int

    @property
    def level(self) -> NDArray[np.int8]:
        return np.where(self.fault != 0, np.int8(Level.FAULT), self.condition).astype(np.int8)

    @property
    def reason(self) -> NDArray[np.int8]:
        return np.where(self.fault != 0, self.fault, self.condition_reason).astype(np.int8)


_FAULT_GATES = {
    Gate.STALE_INPUT: Reason.INPUT_STALE,
    Gate.IMPLAUSIBLE_INPUT: Reason.INPUT_IMPLAUSIBLE,
    Gate.MODEL_ERROR: Reason.MODEL_ERROR,
}
_FAULT_GATE_CODES = np.array(sorted(int(g) for g in _FAULT_GATES), dtype=np.int64)


@dataclass
class WarningMachine:
    th: Thresholds
    condition: Level = Level.OK
    condition_reason: Reason = Reason.NONE
    fault_reason: Reason = Reason.NONE
    # debounce accumulators (seconds)
    below_s: float = 0.0
    above_s: float = 0.0
    inside_s: float = 0.0
    bad_input_s: float = 0.0
    good_input_s: float = 0.0
    time_below_s: float = 0.0  # evaluated time below low_pct in the current low episode

    @property
    def level(self) -> Level:
        return Level.FAULT if self.fault_reason != Reason.NONE else self.condition

    @property
    def reason(self) -> Reason:
        return self.fault_reason if self.fault_reason != Reason.NONE else self.condition_reason

    def step(self, t_s: float, dt_s: float, gate: Gate, ratio_filt_pct: float | None) -> list[Transition]:
        """Advance by one evaluation tick. ``ratio_filt_pct`` is given when this tick evaluated a
        steady point (in or outside the envelope) and the filter is valid; it is None otherwise.
        Returns the level changes."""
        before = self.level
        self._fault(gate, dt_s)
        if ratio_filt_pct is not None and gate in EVALUATED:
            self._condition(ratio_filt_pct, dt_s, trusted=gate == Gate.EVALUATING)
        after = self.level
        if after == before:
            return []
        return [Transition(t_s, before, after, self.reason, ratio_filt_pct)]

    def _fault(self, gate: Gate, dt_s: float) -> None:
        reason = _FAULT_GATES.get(gate)
        if reason is not None:
            self.bad_input_s += dt_s
            self.good_input_s = 0.0
            if self.fault_reason == Reason.NONE and self.bad_input_s >= self.th.fault_after_s - _EPS:
                self.fault_reason = reason
        elif gate == Gate.NO_INPUT:
            # Bus idle: neither evidence of a fault nor of recovery.
            pass
        else:
            self.good_input_s += dt_s
            self.bad_input_s = 0.0
            if self.fault_reason != Reason.NONE and self.good_input_s >= self.th.fault_after_s - _EPS:
                self.fault_reason = Reason.NONE

    def _condition(self, r: float, dt_s: float, trusted: bool = True) -> None:
        th = self.th
        below, above, inside = band(r, th)
        self.below_s = self.below_s + dt_s if below else 0.0
        self.above_s = self.above_s + dt_s if above else 0.0
        # Clearing needs trusted evidence: an extrapolated point adds nothing to it (nor breaks it).
        if not inside:
            self.inside_s = 0.0
        elif trusted:
            self.inside_s += dt_s
        if below:
            self.time_below_s += dt_s
        elif self.condition != Level.LOW:
            self.time_below_s = 0.0

        if self.condition != Level.LOW and self.below_s >= th.debounce_s - _EPS:
            self._set(Level.LOW, Reason.RATIO_LOW)
        elif self.condition != Level.HIGH and self.above_s >= th.debounce_s - _EPS:
            self._set(Level.HIGH, Reason.RATIO_HIGH)
        elif self.condition != Level.OK and self.inside_s >= th.debounce_s - _EPS:
            self._set(Level.OK, Reason.NONE)
            self.time_below_s = 0.0

    def clear(self, ratio_filt_pct: float | None) -> None:
        """A DM11 (active DTCs cleared): a low or high condition the filtered ratio no longer shows goes
        back to ok; one it still shows stays raised (it is there: raised again at once, not after a new
        debounce). The debounce accumulators and the fault go on as they were."""
        if ratio_filt_pct is not None:
            below, above, _ = band(ratio_filt_pct, self.th)
            if (self.condition == Level.LOW and below) or (self.condition == Level.HIGH and above):
                return
        if self.condition != Level.OK:
            self.condition, self.condition_reason = Level.OK, Reason.NONE
            self.inside_s = 0.0
            if ratio_filt_pct is None or not band(ratio_filt_pct, self.th)[0]:
                self.time_below_s = 0.0

    def _set(self, level: Level, reason: Reason) -> None:
        self.condition = level
        self.condition_reason = reason
        self.below_s = self.above_s = self.inside_s = 0.0

    # -- many ticks at once (the columnar replay) ---------------------------------------------------

    def quiet(self, gates: NDArray[np.integer], ratios: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Per tick: could it leave the ok, unfaulted state? False when it could. A quiet tick has
        input neither stale nor implausible and no ratio outside ``[low_pct, high_pct]``; ``ratios``
        is NaN where a tick has none (not evaluated, filter not yet valid)."""
        rated = _rated(gates, ratios)
        with np.errstate(invalid="ignore"):
            below, above, _ = band(ratios, self.th)
        return ~np.isin(gates, _FAULT_GATE_CODES) & ~(rated & (below | above))

    def can_skip(self) -> bool:
        """Whether :meth:`skip` applies now: ok, no fault, and a debounce that takes time."""
        return self.condition == Level.OK and self.fault_reason == Reason.NONE and self.th.debounce_s - _EPS > 0.0

    def skip(self, gates: NDArray[np.integer], ratios: NDArray[np.float64], dt_s: float) -> NDArray[np.float64]:
        """Advance over quiet ticks (see :meth:`quiet`) from the state :meth:`can_skip` accepts: the
        accumulators end as ``step`` tick after tick leaves them, with the same float additions in
        the same order, and no level changes. Returns ``time_below_s`` after each tick."""
        th = self.th
        n = len(gates)
        below_after = np.full(n, self.time_below_s)
        live = int(np.count_nonzero(gates != Gate.NO_INPUT))
        if live:
            self.good_input_s = add_repeat(self.good_input_s, dt_s, live)
            self.bad_input_s = 0.0
        rated = _rated(gates, ratios)
        first = int(np.argmax(rated)) if n else 0
        if n and rated[first]:
            below_after[first:] = 0.0
            self.below_s = self.above_s = self.time_below_s = 0.0
            with np.errstate(invalid="ignore"):
                inside = rated & band(ratios, th)[2]
            adds = inside & (gates == Gate.EVALUATING)
            breaks = np.flatnonzero(rated & ~inside)
            if len(breaks):
                self.inside_s = 0.0
                adds = adds[breaks[-1] + 1 :]
            self.inside_s = add_repeat(self.inside_s, dt_s, int(np.count_nonzero(adds)))
        return below_after

    def run_columns(
        self,
        t_k: NDArray[np.float64],
        gates: NDArray[np.int8],
        ratios: NDArray[np.float64],
        dt_s: float,
        counts: tuple[int, int],
        record: Callable[[Transition], None],
    ) -> WarningColumns:
        """:meth:`step` at every tick of a stretch (``ratios``: NaN where a tick gives none), each
        level change handed to ``record``; ``counts``: the warnings and faults raised before."""
        n = len(t_k)
        cond, creason, fault = (np.zeros(n, dtype=np.int8) for _ in range(3))
        below = np.zeros(n, dtype=np.float64)
        wcount = np.zeros(n, dtype=np.int64)
        quiet = self.quiet(gates, ratios)
        loud = np.append(np.flatnonzero(~quiet), n)
        quiet_l, t_list, g_list, arg = quiet.tolist(), t_k.tolist(), gates.tolist(), ratios.tolist()
        wc, fc = counts
        i = 0
        while i < n:
            if quiet_l[i] and self.can_skip():  # a run of quiet ticks in the ok state: one step
                j = int(loud[np.searchsorted(loud, i)])
                below[i:j] = self.skip(gates[i:j], ratios[i:j], dt_s)
                creason[i:j] = self.condition_reason
                wcount[i:j] = wc
                i = j
                continue
            a = arg[i]
            cb, fb = self.condition, self.fault_reason
            for tr in self.step(t_list[i], dt_s, g_list[i], None if a != a else a):
                record(tr)
            wc += warning_raised(cb, self.condition)
            fc += fault_raised(fb, self.fault_reason)
            cond[i], creason[i], fault[i] = self.condition, self.condition_reason, self.fault_reason
            below[i] = self.time_below_s
            wcount[i] = wc
            i += 1
        return WarningColumns(cond, creason, fault, below, wcount, wc, fc)


def _rated(gates: NDArray[np.integer], ratios: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Ticks whose ratio the condition sees: evaluated, with a (finite) filtered ratio."""
    return is_evaluated(gates) & ~np.isnan(ratios)


def add_repeat(start: float, step: float, times: int) -> float:
    """``start`` plus ``step``, ``times`` times, one addition after the other (as ``step`` adds)."""
    if times <= 0:
        return start
    acc = np.empty(times + 1)
    acc[0] = start
    acc[1:] = step
    return float(np.cumsum(acc)[-1])
