"""J1939 diagnostics of the drive: the DM1 message driven by the warning state (SAE J1939-73).

Active DTCs at each evaluation tick, from the warning machine's condition and fault:
- condition low: (``spn``, FMI 17, below normal, least severe), or FMI 18 (moderately severe) while
  the filtered ratio is below ``low_severe_pct``; condition high: FMI 15, or FMI 16 above
  ``high_severe_pct``. The severity follows the filtered ratio of evaluated ticks with the thresholds'
  hysteresis (severe from below ``low_severe_pct``, least severe again from ``low_severe_pct +
  hysteresis``; mirrored on the high side) and is kept while nothing is evaluated;
- fault: (``input_spn``, FMI 9, abnormal update rate) for stale inputs, FMI 2 (data erratic) for
  implausible or erratic ones, FMI 12 for a model error.
The amber warning lamp is on while the condition is low or high (a fault alone lights no lamp: the
monitor cannot judge the drive then, which is a service matter). A DTC's occurrence count goes up by
one each time it becomes active (up to 126) and lives in the totals, so it survives restarts; the
DTCs active at the last save are not counted again when they are still active after a restart.

DM1 goes out every ``every_ticks`` ticks (1 s) and at once when the lamp or the active DTCs change;
with one DTC or none in one frame (the all-zero DTC when none is active), with more over BAM
(:mod:`cmcan.can.j1939.transport`): TP.CM at the tick's time, each TP.DT ``bam_gap_s`` later.

Answers to requests for DM1 and DM2 (:meth:`Dm1Producer.answer`) come after the node's own DM1: a
node has one BAM at a time (J1939-21), and cmcan's periodic DM1 is not to wait for anybody's
request. An answer of one frame goes at once (a single frame needs no session). An answer by BAM
starts at once when no BAM is on the wire and it ends before the next periodic DM1; otherwise it
waits (at most ``answers_waiting_max``; more are dropped and counted in ``dropped``) and starts at
the first tick where it can, after any DM1 due. An answer too long to fit between two DM1s at all
starts at the first tick after a DM1. A DM1 by BAM due while a BAM is on the wire goes at the first
tick after its last packet, ahead of the answers waiting.

One tick at a time (:meth:`Dm1Producer.step`), or a stretch of ticks (:meth:`Dm1Producer.run_columns`),
which steps only the ticks where a step could do something.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cmcan.can.frame import Frame, FrameColumns
from cmcan.can.j1939 import dm1, ids, transport
from cmcan.can.j1939.dm1 import Dtc, Fmi, Lamp, Lamps
from cmcan.monitor.totals import Totals
from cmcan.monitor.warnings import Level, Reason


@dataclass(frozen=True)
class Dm1Params:
    spn: int  # the drive's condition (CM ratio)
    input_spn: int  # the monitor's inputs
    low_severe_pct: float
    high_severe_pct: float
    hysteresis_pct: float  # the warning thresholds', for the severity's
    every_ticks: int
    source: int  # cmcan's source address
    priority: int = dm1.DM1_PRIORITY
    bam_gap_s: float = 0.1
    channel: str = ""
    answers_waiting_max: int = 4  # answers by BAM waiting for the session (AnswerLimits.waiting_max)


_FAULT_FMI = {
    Reason.INPUT_STALE: Fmi.ABNORMAL_UPDATE_RATE,
    Reason.INPUT_IMPLAUSIBLE: Fmi.DATA_ERRATIC,
    Reason.MODEL_ERROR: Fmi.BAD_DEVICE,
}


class Dm1Producer:
    __slots__ = (
        "_dm1_until",
        "_every",
        "_hi_off",
        "_hi_on",
        "_last",
        "_lo_off",
        "_lo_on",
        "_payload",
        "_tick_s",
        "active",
        "busy_until",
        "changed",
        "dropped",
        "frame_id",
        "high_severe",
        "low_severe",
        "p",
        "totals",
        "waiting",
    )

    def __init__(self, p: Dm1Params, totals: Totals) -> None:
        self.p = p
        self.totals = totals
        self.frame_id = ids.make_id(p.priority, dm1.PGN_DM1, p.source)
        self.active: list[str] = list(totals.dtc_active)
        self.low_severe = f"{p.spn}:{int(Fmi.BELOW_NORMAL_MODERATE)}" in self.active
        self.high_severe = f"{p.spn}:{int(Fmi.ABOVE_NORMAL_MODERATE)}" in self.active
        self.busy_until = -1e300
        self.changed = False
        self._last: tuple[int, int, bool, bool] | None = None  # the inputs of the last DTC list
        self._payload: tuple[tuple[int, ...], bytes] | None = None  # the last DM1 payload and what made it
        # read at every tick (the daemon's hot path): the severity's thresholds with their hysteresis
        self._lo_on, self._lo_off = p.low_severe_pct, p.low_severe_pct + p.hysteresis_pct
        self._hi_on, self._hi_off = p.high_severe_pct, p.high_severe_pct - p.hysteresis_pct
        self._every = p.every_ticks
        self.waiting: deque[int] = deque()  # the PGNs of answers by BAM waiting for the session
        self.dropped = 0  # answers dropped: more waiting than answers_waiting_max
        self._dm1_until = -1e300  # the last packet of the last BAM of DM1 (a DM1 frame goes after it)
        self._tick_s = 0.0  # the tick's period (from the first tick: t = k x period), 0 before

    def dtcs(self, condition: Level, fault: Reason) -> list[tuple[int, int]]:
        """(SPN, FMI) of the active DTCs, condition first."""
        p = self.p
        out = []
        if condition == Level.LOW:
            out.append((p.spn, Fmi.BELOW_NORMAL_MODERATE if self.low_severe else Fmi.BELOW_NORMAL_LEAST))
        elif condition == Level.HIGH:
            out.append((p.spn, Fmi.ABOVE_NORMAL_MODERATE if self.high_severe else Fmi.ABOVE_NORMAL_LEAST))
        if fault != Reason.NONE:
            out.append((p.input_spn, _FAULT_FMI.get(fault, Fmi.BAD_DEVICE)))
        return [(s, int(f)) for s, f in out]

    def step(self, k: int, t: float, condition: Level, fault: Reason, ratio_pct: float | None) -> list[Frame]:
        """One tick: update the active DTCs and counts; the DM1 frames due (times >= ``t``)."""
        if not self._tick_s and k:
            self._tick_s = t / k
        if ratio_pct is not None:  # the severity (kept while nothing is evaluated), inline: every tick
            if ratio_pct < self._lo_on:
                self.low_severe = True
            elif ratio_pct >= self._lo_off:
                self.low_severe = False
            if ratio_pct > self._hi_on:
                self.high_severe = True
            elif ratio_pct <= self._hi_off:
                self.high_severe = False
        # condition and fault as given (Level and Reason, or their ints: the columnar engine's)
        state = (condition, fault, self.low_severe, self.high_severe)
        if state == self._last and not self.changed:
            if k % self._every:  # nothing changed, nothing to send: the common tick
                return self._answer_waiting(t) if self.waiting else []
            # due, nothing changed since the last DM1 (any change of DTCs, lamp or counts sets
            # ``changed`` until it is sent): the same single frame again
            pl = self._payload
            if self._single_ready(pl, t):
                dm = [Frame(t, self.p.channel, self.frame_id, True, False, False, False, pl[1])]  # type: ignore[index]
                return dm + self._answer_waiting(t) if self.waiting else dm
        self._last = state
        now = self.dtcs(condition, fault)
        keys = [f"{s}:{f}" for s, f in now]
        counts = self.totals.dtc_occurrences
        if keys != self.active:
            for key in keys:
                if key not in self.active:
                    counts[key] = min(dm1.OC_MAX, counts.get(key, 0) + 1)
            self.active = keys
            self.totals.dtc_active = list(keys)
            self.changed = True
        due = k % self.p.every_ticks == 0 or self.changed
        if not due:
            return self._answer_waiting(t) if self.waiting else []
        payload = self._dm1_payload(condition, now)
        single = len(payload) <= 8
        # a single frame needs no session (an answer's BAM does not hold it back), but does not overtake
        # a DM1 still on the wire; one BAM at a time: a DM1 by BAM goes next, ahead of the answers waiting
        if t <= (self._dm1_until if single else self.busy_until):
            self.changed = True
            return []
        self.changed = False
        if single:
            dm = [Frame(t, self.p.channel, self.frame_id, True, False, False, False, payload)]
        else:
            dm = transport.bam_frames(t, self.p.bam_gap_s, dm1.PGN_DM1, payload, self.p.source, self.p.channel)
            self.busy_until = self._dm1_until = dm[-1].timestamp_s
        return dm + self._answer_waiting(t) if self.waiting else dm

    def _dm1_payload(self, condition: Level, now: list[tuple[int, int]]) -> bytes:
        """DM1's payload for the active DTCs ``now`` (the one of the last DM1 when nothing changed)."""
        counts = self.totals.dtc_occurrences
        amber = condition in (Level.LOW, Level.HIGH)
        made_of = (amber, *(x for s, f in now for x in (s, f, counts.get(f"{s}:{f}", 0))))
        if self._payload is not None and self._payload[0] == made_of:  # the same DM1 as a second ago
            return self._payload[1]
        lamps = Lamps(amber_warning=Lamp.ON if amber else Lamp.OFF)
        payload = dm1.encode(lamps, [Dtc(s, f, counts.get(f"{s}:{f}", 0)) for s, f in now])
        self._payload = (made_of, payload)
        return payload

    # -- answers to requests and clears (DM1, DM2, DM3, DM11) ----------------------------------------

    def answer(self, pgn: int, t: float) -> list[Frame]:
        """The frames answering a request at ``t`` for DM1 (the active DTCs as DM1 would send them now)
        or DM2 (the previously active ones: an occurrence count, not active now), the lamps as they are
        now. Longer than 8 bytes by BAM: at once where the session is free and the BAM ends before the
        next DM1, else none now: the answer waits for a tick where it can go (see the module), or is
        dropped (counted) when ``answers_waiting_max`` wait already."""
        if not self.waiting and t > self.busy_until:
            frames = self._answer_now(pgn, t)
            if frames is not None:
                return frames
        elif len(dm_payload(self.p, self.active, self.totals.dtc_occurrences, pgn)) <= 8:
            return self._answer_now(pgn, t) or []
        if len(self.waiting) < self.p.answers_waiting_max:
            self.waiting.append(pgn)
        else:
            self.dropped += 1
        return []

    def _answer_now(self, pgn: int, t: float) -> list[Frame] | None:
        """The answer for ``pgn`` at ``t`` where it can go now (None: a BAM that would still be on the
        wire at the next periodic DM1, while a DM1 by BAM could be due then)."""
        p = self.p
        payload = dm_payload(p, self.active, self.totals.dtc_occurrences, pgn)
        if len(payload) <= 8:
            return [Frame(t, p.channel, ids.make_id(p.priority, pgn, p.source), True, False, False, False, payload)]
        t_end = t + (len(payload) + 6) // 7 * p.bam_gap_s  # the last packet's time
        if self._tick_s and not self._fits(t, t_end):
            return None
        frames = transport.bam_frames(t, p.bam_gap_s, pgn, payload, p.source, p.channel)
        self.busy_until = frames[-1].timestamp_s
        if pgn == dm1.PGN_DM1:
            self._dm1_until = self.busy_until
        return frames

    def _fits(self, t: float, t_end: float) -> bool:
        """Whether a BAM from ``t`` to ``t_end`` leaves the next periodic DM1 alone: it ends before
        that DM1's tick, or DM1 is a single frame now, or no BAM could (longer than DM1's period: it
        goes right after a DM1, the earliest it can)."""
        pl = self._payload
        if pl is not None and len(pl[1]) <= 8 and not self.changed:
            return True
        every, tick = self._every, self._tick_s
        k_next = (math.floor(t / tick + 1e-6) // every + 1) * every  # the next DM1 tick after t
        return t_end < k_next * tick or t_end - t + self.p.bam_gap_s >= every * tick

    def _answer_waiting(self, t: float) -> list[Frame]:
        """At a tick ``t`` with no DM1 to go: the answers waiting that can go now (one BAM at most)."""
        out: list[Frame] = []
        while self.waiting and not self.changed and t > self.busy_until:
            frames = self._answer_now(self.waiting[0], t)
            if frames is None:
                break
            self.waiting.popleft()
            out += frames
        return out

    def clear_previous(self) -> list[str]:
        """DM3: forget the previously active DTCs (their occurrence counts); the keys forgotten."""
        counts = self.totals.dtc_occurrences
        gone = sorted((k for k in counts if k not in self.active), key=dtc_order)
        for k in gone:
            del counts[k]
        return gone

    def clear_active(self) -> list[str]:
        """DM11: forget the active DTCs and their counts; a condition still present makes its DTC
        active again (occurrence count 1) when the monitor finds it again. The keys forgotten."""
        gone = list(self.active)
        for k in gone:
            self.totals.dtc_occurrences.pop(k, None)
        self.active = []
        self.totals.dtc_active = []
        self.low_severe = self.high_severe = False
        self._last = None
        self._payload = None
        self.changed = True  # the cleared DM1 goes out at the next tick
        return gone

    # -- a stretch of ticks ------------------------------------------------------------------------

    def run_columns(
        self,
        ks: NDArray[np.int64],
        t_k: NDArray[np.float64],
        cond: NDArray[np.int8],
        fault: NDArray[np.int8],
        ratio: NDArray[np.float64],
        queue: Callable[[list[Frame], float, list[Frame]], None],
    ) -> FrameColumns | None:
        """:meth:`step` over a stretch of ticks (``ratio``: NaN where a tick gives none): the frames due
        at their ticks, in order (None when there are none); ``queue(frames, t, out)`` takes a step's
        frames (those due later wait there, as frame by frame).

        A tick is stepped where the step could do something: a tick due by the period, a change of
        condition or fault, a change still waiting to go out (``changed``), or anywhere while the
        severity could move (a ratio beyond a severe threshold, or a severe flag set). Any other tick
        would find its state unchanged and nothing due. And a run of due ticks with nothing changed
        since a step that left one cached single frame resends that frame, which is what the step
        would do at each of them."""
        must, event = self._ticks_to_step(ks, cond, fault, ratio)
        now: list[Frame] = []
        now_at: list[int] = []  # the tick of each frame in ``now``
        resend: list[tuple[NDArray[np.int64], bytes]] = []  # ticks that resend a cached frame, and it
        must_i, events = np.flatnonzero(must), np.flatnonzero(event)
        n = len(ks)

        def stepped(i: int) -> int:  # the last tick stepped
            while True:
                r, t = float(ratio[i]), float(t_k[i])
                dm = self.step(int(ks[i]), t, int(cond[i]), int(fault[i]), None if r != r else r)  # type: ignore[arg-type]
                if dm:
                    queue(dm, t, now)
                    now_at.extend([i] * (len(now) - len(now_at)))
                if not (self.changed or self.waiting) or i + 1 >= n:
                    return i
                i += 1  # a change or an answer waits to go out: every tick until it has

        q = 0
        while q < len(must_i):
            i = int(must_i[q])
            pl = self._payload
            if not event[i] and self._resends(pl, int(cond[i]), int(fault[i]), float(t_k[i])):
                # the due ticks up to the next event resend the cached frame (times only grow: all of
                # them are past any transport in progress)
                end = events[np.searchsorted(events, i)] if len(events) and events[-1] > i else n
                q_end = int(np.searchsorted(must_i, end))
                resend.append((must_i[q:q_end], pl[1]))  # type: ignore[index]
                q = q_end
                continue
            q = int(np.searchsorted(must_i, stepped(i), side="right"))
        return self._frames_of(t_k, now, now_at, resend)

    def _ticks_to_step(
        self, ks: NDArray[np.int64], cond: NDArray[np.int8], fault: NDArray[np.int8], ratio: NDArray[np.float64]
    ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """The ticks a step could do something at, and among them those that change something."""
        p = self.p
        with np.errstate(invalid="ignore"):
            severe = (ratio < self._lo_on) | (ratio > self._hi_on)  # where step could set a severe flag
        if self.low_severe or self.high_severe or self.waiting or severe.any():
            every = np.ones(len(ks), dtype=bool)
            return every, every
        event = np.zeros(len(ks), dtype=bool)  # the severity flags stay: only these ticks change anything
        # the first tick against the state the producer was left in (by the stretch before)
        event[0] = self.changed or self._last != (int(cond[0]), int(fault[0]), self.low_severe, self.high_severe)
        event[1:] = (cond[1:] != cond[:-1]) | (fault[1:] != fault[:-1])
        return event | (ks % p.every_ticks == 0), event

    def _single_ready(self, pl: tuple[tuple[int, ...], bytes] | None, t: float) -> bool:
        """A cached DM1 that fits one frame and no DM1 by BAM on the wire at ``t`` (an answer's BAM of
        DM2 does not hold it back): what a due tick with nothing changed resends (:meth:`step`, and the
        runs of :meth:`run_columns`)."""
        return pl is not None and len(pl[1]) <= 8 and t > self._dm1_until

    def _resends(self, pl: tuple[tuple[int, ...], bytes] | None, cond: int, fault: int, t: float) -> bool:
        """Whether a due tick with nothing changed would resend the cached single frame."""
        return (
            not self.changed
            and not self.waiting
            and self._last == (cond, fault, self.low_severe, self.high_severe)
            and self._single_ready(pl, t)
        )

    def _frames_of(
        self,
        t_k: NDArray[np.float64],
        now: list[Frame],
        now_at: list[int],
        resend: list[tuple[NDArray[np.int64], bytes]],
    ) -> FrameColumns | None:
        """The stepped ticks' frames and the resent ones as columns, in tick order (a tick's own
        frames in their order)."""
        if not now and not resend:
            return None
        parts, at = [], []
        if now:
            parts.append(FrameColumns.from_frames(now))
            at.append(np.array(now_at, dtype=np.int64))
        if resend:
            r = np.concatenate([run for run, _ in resend])
            data = np.zeros((len(r), 8), dtype=np.uint8)
            dlc = np.zeros(len(r), dtype=np.int16)
            at_run = 0
            for run, payload in resend:  # the frame cached when the run began
                data[at_run : at_run + len(run), : len(payload)] = np.frombuffer(payload, dtype=np.uint8)
                dlc[at_run : at_run + len(run)] = len(payload)
                at_run += len(run)
            no = np.zeros(len(r), dtype=bool)
            parts.append(
                FrameColumns(
                    timestamp_s=t_k[r],
                    channel=np.zeros(len(r), dtype=np.int16),
                    channel_names=(self.p.channel,),
                    arbitration_id=np.full(len(r), self.frame_id, dtype=np.uint32),
                    extended=np.ones(len(r), dtype=bool),
                    remote=no,
                    error=no,
                    fd=no,
                    dlc=dlc,
                    data=data,
                )
            )
            at.append(r)
        cols = FrameColumns.concat(parts) if len(parts) > 1 else parts[0]
        if len(parts) > 1:
            cols = cols.take(np.argsort(np.concatenate(at), kind="stable"))
        return cols


def dtc_order(key: str) -> tuple[int, int]:
    """A DTC key ("SPN:FMI") as numbers, for sorting."""
    spn, fmi = key.split(":")
    return int(spn), int(fmi)


def dm_payload(p: Dm1Params, active: list[str], counts: dict[str, int], pgn: int) -> bytes:
    """DM1's payload (``pgn`` 65226: the active DTCs) or DM2's (65227: the previously active ones, by
    SPN and FMI), each DTC with its occurrence count; the amber lamp on while a condition DTC is active."""
    if pgn == dm1.PGN_DM1:
        keys = list(active)
    else:
        keys = sorted((k for k, n in counts.items() if n and k not in active), key=dtc_order)
    amber = any(dtc_order(k)[0] == p.spn for k in active)
    dtcs = [Dtc(*dtc_order(k), counts.get(k, 0)) for k in keys]
    return dm1.encode(Lamps(amber_warning=Lamp.ON if amber else Lamp.OFF), dtcs)
