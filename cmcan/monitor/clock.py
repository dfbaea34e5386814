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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from cmcan.monitor.windows import TIME_EPS_S

STEP_BACK_S = 0.5


@dataclass
class Step:
    """What a frame time means for the clock: ticks to evaluate first (in order), whether the clock
    stepped back (the state is to be moved onto the frame's time base first: ``back_by_s``), and
    whether the frame is late (not to be used)."""

    ticks: list[int] = field(default_factory=list)
    back_by_s: float = 0.0
    late: bool = False


class TickClock:
    __slots__ = ("_due_t", "_late_t", "last_frame_t", "max_gap_s", "next_k", "period")

    def __init__(self, rate_hz: float, max_gap_s: float) -> None:
        self.period = 1.0 / rate_hz
        self.max_gap_s = max_gap_s
        self.last_frame_t = -math.inf
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
        """The frame time ``t`` of an input frame (called when :meth:`in_step` is False)."""
        if not math.isfinite(t):
            return Step(late=True)
        if self.next_k is None:
            return Step()
        if t < self._late_t:
            if t < self.last_frame_t - STEP_BACK_S:
                return Step(back_by_s=self.last_frame_t - t)
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
        """Move onto a time base ``ticks`` periods later (negative: earlier): the newest frame's time
        and the next tick move with it, so not a tick is lost or evaluated twice."""
        if self.next_k is None:
            return
        self.last_frame_t += ticks * self.period
        self._set_next(self.next_k + ticks)

    def resume(self, next_k: int, last_frame_t: float) -> None:
        """Continue from a state computed elsewhere (the columnar replay's write-back)."""
        self._set_next(next_k)
        self.last_frame_t = last_frame_t

    def reset(self) -> None:
        self._set_next(None)
        self.last_frame_t = -math.inf

    def advance(self, t: float) -> list[int]:
        """Time passes without frames (the daemon's idle timer): the ticks up to ``t``."""
        if self.next_k is None or not math.isfinite(t):
            return []
        return self._ticks_before(t, idle=True)

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
            if idle:
                if k_last >= self.next_k:  # keep broadcasting while the bus is silent: the newest tick
                    ks.append(k_last)
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
