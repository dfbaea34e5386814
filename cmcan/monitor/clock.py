"""The evaluation tick clock on frame time: which ticks a frame completes, and which frames are late.

Ticks fall on multiples of the evaluation period in the frames' own time. A tick is evaluated when
the first frame after it arrives (so a replayed log gives exactly what the daemon sent); a frame
older than a tick already evaluated is late and unused. After a gap in the data longer than
``max_gap_s`` (the machine was off, or a burst-sampled log) the ticks inside the gap are skipped.

Frame time comes from the wall clock (SocketCAN stamps frames with it), and the wall clock steps:
NTP or a GPS fix sets it back or forward. A frame more than ``STEP_BACK_S`` older than the newest
one cannot be a late delivery (a bus delivers in order; a logger merging buses is off by
milliseconds): the clock stepped back, and the monitor moves its state onto the new time base
instead of waiting, silent, until time catches up. A step forward looks like a gap here; the daemon,
which can compare frame time with the boot-time clock, tells the monitor of it (``Monitor.shift_time``).

The clock takes frames one by one (:meth:`TickClock.step`, :meth:`TickClock.started`) or plans a
stretch of them at once (:meth:`TickClock.plan`, :meth:`TickClock.regular_until`,
:meth:`TickClock.commit`): the same decisions from running maxima, up to the first frame the
stretch cannot take (a gap, a step back, an unreadable time), which then goes one by one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.windows import TIME_EPS_S, running_max

STEP_BACK_S = 0.5


@dataclass
class Step:
    """What a frame time means for the clock: ticks to evaluate first (in order), whether the clock
    stepped back (the state is to be moved onto the frame's time base first: ``back_by_s``), and
    whether the frame is late (not to be used)."""

    ticks: list[int] = field(default_factory=list)
    back_by_s: float = 0.0
    late: bool = False


@dataclass
class ClockPlan:
    """The clock's decisions for a stretch of input frames at times ``t`` (arrival order), from its
    state when planned: ``g`` the first tick a frame would complete (-inf for a time that is not a
    number), ``k_prev`` the clock's next tick before each frame, ``late`` the frames older than a
    tick already evaluated."""

    t: NDArray[np.float64]
    g: NDArray[np.float64]
    k_prev: NDArray[np.float64]
    late: NDArray[np.bool_]


class TickClock:
    __slots__ = ("_due_t", "_late_t", "counts", "last_frame_t", "max_gap_s", "next_k", "period")

    def __init__(self, rate_hz: float, max_gap_s: float) -> None:
        self.period = 1.0 / rate_hz
        self.max_gap_s = max_gap_s
        self.last_frame_t = -math.inf
        self.counts = {"late": 0, "clock_steps": 0}
        self._set_next(None)

    def _set_next(self, k: int | None) -> None:
        self.next_k = k
        if k is None:
            self._due_t, self._late_t = math.inf, -math.inf
        else:
            self._due_t = k * self.period + TIME_EPS_S
            self._late_t = (k - 1) * self.period - TIME_EPS_S

    def in_step(self, t: float) -> bool:
        """True when ``t`` neither completes a tick nor is late: the common case, checked first."""
        return self._late_t <= t <= self._due_t

    def step(self, t: float) -> Step:
        """The frame time ``t`` of an input frame (called when :meth:`in_step` is False); a late frame
        is counted."""
        if not math.isfinite(t):
            self.counts["late"] += 1
            return Step(late=True)
        if self.next_k is None:
            return Step()
        if t < self._late_t:
            if t < self.last_frame_t - STEP_BACK_S:
                return Step(back_by_s=self.last_frame_t - t)
            self.counts["late"] += 1
            return Step(late=True)
        return Step(self._ticks_before(t))

    def started(self, t: float) -> None:
        """An input frame at ``t`` was accepted: the first one starts the clock; remember the newest."""
        if self.next_k is None:
            self._set_next(math.floor(t / self.period) + 1)
        if t > self.last_frame_t:
            self.last_frame_t = t

    def whole_ticks(self, delta_s: float) -> int:
        """A step of ``delta_s`` in whole evaluation periods (the state moves by these)."""
        return round(delta_s / self.period)

    def shift(self, ticks: int) -> None:
        """A step of the wall clock (counted): move onto a time base ``ticks`` periods later
        (negative: earlier); the newest frame's time and the next tick move with it, so not a tick
        is lost or evaluated twice."""
        self.counts["clock_steps"] += 1
        if self.next_k is None:
            return
        self.last_frame_t += ticks * self.period
        self._set_next(self.next_k + ticks)

    def advance(self, t: float) -> list[int]:
        """Time passes without frames (the daemon's idle timer): the ticks up to ``t``, which counts as
        the newest time seen (frames after it that are earlier by more than ``STEP_BACK_S`` are a step
        of the clock back). Before the first frame, time starts at ``t`` (the daemon's wall clock: the
        time its bus stamps frames with), so a silent bus still gets its ticks."""
        if not math.isfinite(t):
            return []
        if self.next_k is None:
            self._set_next(math.floor(t / self.period) + 1)
            self.last_frame_t = t
            return []
        ks = self._ticks_before(t, idle=True)
        self.last_frame_t = max(self.last_frame_t, t)  # the newest time seen: a step back is measured from it
        return ks

    def passing(self, t: float) -> list[int]:
        """A frame that is no input passes at ``t`` (a J1939 node's request or claim, answered at its
        time): the ticks before it, as an input frame at ``t`` completes them, so what cmcan sends
        stays in order of time. It neither starts the clock nor is counted late nor moves the time
        base; after a gap in the inputs only the ticks up to the last input frame (those the next input
        frame would evaluate in any case)."""
        if self.next_k is None or not math.isfinite(t) or t <= self._due_t:
            return []
        if t - self.last_frame_t > self.max_gap_s:
            return self.flush()
        ks = []
        k = self.next_k
        while k * self.period < t - TIME_EPS_S:
            ks.append(k)
            k += 1
        self._set_next(k)
        return ks

    def flush(self) -> list[int]:
        """The ticks up to the last frame (the end of a replayed log)."""
        if self.next_k is None:
            return []
        ks = []
        k = self.next_k
        while k * self.period <= self.last_frame_t + TIME_EPS_S:
            ks.append(k)
            k += 1
        self._set_next(k)
        return ks

    def _ticks_before(self, t: float, idle: bool = False) -> list[int]:
        assert self.next_k is not None
        if t - self.last_frame_t > self.max_gap_s:
            ks = self.flush()  # finish the span that ended with the last frame
            k_last = math.ceil(t / self.period) - 1  # the last tick strictly before t
            if idle:  # keep broadcasting while the bus is silent: the ticks of the last second at most
                if k_last >= self.next_k:
                    ks.extend(range(max(self.next_k, k_last - round(1.0 / self.period) + 1), k_last + 1))
                    self._set_next(k_last + 1)
            else:
                self._set_next(math.floor(t / self.period) + 1)
            return ks
        ks = []
        k = self.next_k
        while k * self.period < t - TIME_EPS_S:
            ks.append(k)
            k += 1
        self._set_next(k)
        return ks

    # -- a stretch of frames at once ---------------------------------------------------------------

    def plan(self, t: NDArray[np.float64]) -> ClockPlan:
        """What :meth:`step` would decide for input frames at ``t`` one after the other, as arrays
        (the clock started: ``next_k`` is set)."""
        assert self.next_k is not None
        P, eps = self.period, TIME_EPS_S
        finite = np.isfinite(t)
        # g: the smallest k with k P >= t - eps, robust to the rounding of t / P
        u = t - eps
        g = np.ceil(u / P)
        for _ in range(2):
            g = np.where(g * P < u, g + 1, g)
            g = np.where((g - 1) * P >= u, g - 1, g)
        g = np.where(finite, g, -np.inf)
        k_prev = running_max(np.concatenate([[float(self.next_k)], g]))[:-1]
        return ClockPlan(t, g, k_prev, t < (k_prev - 1) * P - eps)

    def regular_until(self, plan: ClockPlan, accepted: NDArray[np.bool_], limit: int) -> tuple[int, float]:
        """How many frames of the plan the stretch takes: up to the first that :meth:`step` would
        take otherwise than the plan says (a time that is not a number, a step of the clock back, a
        gap, a rounding edge), at most ``limit``. ``accepted``: the frames accepted as input (they
        move the newest frame's time). Returns that count and the newest accepted frame's time up to
        there."""
        t, g, k_prev, late = plan.t, plan.g, plan.k_prev, plan.late
        advances = t > k_prev * self.period + TIME_EPS_S
        lf = np.maximum.accumulate(np.concatenate([[self.last_frame_t], np.where(accepted, t, -np.inf)]))
        lf_prev = lf[:-1]
        gap = advances & (t - lf_prev > self.max_gap_s)
        step_back = late & (t < lf_prev - STEP_BACK_S)  # the wall clock stepped back: re-based frame by frame
        odd_step = ~late & ~advances & (g > k_prev)  # a frame in step must not move the clock
        irregular = ~np.isfinite(t) | step_back | gap | odd_step
        stop = min(int(np.argmax(irregular)) if irregular.any() else len(t), limit)
        return stop, float(lf[stop])

    def ticks_of(self, plan: ClockPlan, stop: int) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
        """The ticks the first ``stop`` frames of the plan complete, for each tick the index of the
        frame that completes it (the frames before it are the tick's), and the next tick after them."""
        k_after = np.where(plan.late[:stop], plan.k_prev[:stop], np.maximum(plan.k_prev[:stop], plan.g[:stop]))
        k_end = int(k_after[-1])
        ticks = np.arange(int(self.next_k), k_end, dtype=np.int64)  # type: ignore[arg-type]
        return ticks, np.searchsorted(k_after.astype(np.int64), ticks, side="right"), k_end

    def commit(self, plan: ClockPlan, stop: int, next_k: int, last_frame_t: float) -> None:
        """The first ``stop`` frames of the plan taken (their late ones counted): the clock goes on
        from the next tick ``next_k`` and the newest accepted frame's time."""
        self.counts["late"] += int(np.count_nonzero(plan.late[:stop]))
        self._set_next(next_k)
        self.last_frame_t = last_frame_t
