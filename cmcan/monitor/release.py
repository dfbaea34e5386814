"""The order output frames leave the monitor in.

Every output frame carries its time: a tick's time, or later for the packets of a J1939 transport
session (:mod:`cmcan.can.j1939.transport`), which wait in the queue. Frames go out in order of time,
equal times in the order they were made: the frames of the ticks evaluated and the waiting packets
that fell due by a given time (:meth:`OutputQueue.release`); a stretch of ticks' frames merged with
the packets due meanwhile the same way (:meth:`OutputQueue.merge_columns`).
"""

from __future__ import annotations

import heapq
import math

import numpy as np

from cmcan.can.frame import Frame, FrameColumns


class OutputQueue:
    def __init__(self) -> None:
        self.later: list[tuple[float, int, Frame]] = []  # (time, order made, frame), a heap
        self.seq = 0

    @property
    def next_due_t(self) -> float:
        """The time of the next waiting frame (inf when none)."""
        return self.later[0][0] if self.later else math.inf

    def queue(self, frames: list[Frame], t: float, out: list[Frame]) -> None:
        """Output frames of the tick at ``t``: those due now go to ``out``, the later ones wait."""
        for f in frames:
            if f.timestamp_s > t:
                heapq.heappush(self.later, (f.timestamp_s, self.seq, f))
                self.seq += 1
            else:
                out.append(f)

    def release(self, out: list[Frame], t: float) -> list[Frame]:
        """``out`` (frames of ticks, in time order) merged with the waiting frames due by ``t``."""
        later = self.later
        if not later or later[0][0] > t:
            return out
        merged: list[Frame] = []
        for f in out:
            while later and later[0][0] <= f.timestamp_s:
                merged.append(heapq.heappop(later)[2])
            merged.append(f)
        while later and later[0][0] <= t:
            merged.append(heapq.heappop(later)[2])
        return merged

    def merge_columns(self, ticks: FrameColumns, now: FrameColumns | None, t_end: float) -> FrameColumns:
        """A stretch's tick frames (in time order) with the frames of the same ticks made after them
        (``now``, DM1: each after its tick's CM frames) and the waiting frames due by ``t_end`` (before
        a tick's frames of the same time), as :meth:`release` orders them tick after tick."""
        due = self.release([], t_end)
        if now is None and not due:
            return ticks
        later = FrameColumns.from_frames(due)
        extra = FrameColumns.concat([now, later]) if now is not None else later
        n_now = len(now) if now is not None else 0
        ts, t_x = ticks.timestamp_s, extra.timestamp_s
        is_later = np.arange(len(extra)) >= n_now
        at = np.where(is_later, np.searchsorted(ts, t_x, side="left"), np.searchsorted(ts, t_x, side="right"))
        # at one place: by time, a waiting packet before a DM1 frame, each kind in its own order
        order = np.lexsort((np.arange(len(extra)), ~is_later, t_x, at))
        extra = extra.take(order)
        pos = at[order] + np.arange(len(extra))  # rows in the result
        mine = np.ones(len(ticks) + len(extra), dtype=bool)
        mine[pos] = False
        return FrameColumns.concat([ticks, extra]).take(np.argsort(np.concatenate([np.flatnonzero(mine), pos])))
