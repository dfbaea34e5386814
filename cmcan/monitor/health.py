"""Input health per mapped message, as production CAN receivers check it: checksum, alive counter and
timeout. Pure state over the frames' own times; nothing here reads a clock.

Each mapped input message is one *stream*, whatever J1939 source address its frames carry (a
controller that claims another address keeps its counter sequence; two senders interleaving on one
message are rule 1b's). For each frame of the stream that has the message's length and is not late
(:mod:`cmcan.monitor.clock`), in arrival order:

1. Checksum, where the message has one: a frame whose checksum does not match is rejected
   (``checksum``) and changes nothing else.
1a. Not available: on a J1939 message, a frame with a mapped value that is "not available" (or a
   reserved indicator) is no sample (``not_available``): counted, neither accepted nor rejected,
   as if it had not come; it takes no part in the rules below (a node that sends the message filled
   with 0xFF is not a second sender, nor does it break the counter).
1b. Senders, for a J1939 message that more than one source address may send (``source_addresses``
   ``any`` or a list): a frame from address X is rejected (``other_sender``) when X sent the message
   before, within the timeout, and another address has sent it since X's previous frame, within the
   timeout too: two nodes send the message at once, interleaved, and neither is believed (the input
   is not a blend of two senders, it is a health problem: erratic, then a fault). A sender that is new,
   or back after its timeout, passes: a controller that claimed another address goes on at once.
2. Alive counter, where the message has one, modulo M = 2**bits: let p be the counter of the stream's
   previous frame that passed step 1 and dt the time since that frame. With no such frame, or dt above
   the message's timeout (the sender restarted, or the machine was off), the frame passes. Otherwise,
   with d = (c - p) mod M: d == 0 is a frozen counter (``counter_frozen``) and d > max_step a jump
   (``counter_jump``); both reject the frame; 1 <= d <= max_step passes (max_step 2 tolerates one lost
   frame). Either way p becomes c: after a jump the counter is followed from its new value, so the next
   frame in sequence passes again.
2a. Not available, on a J1939 message (J1939-71: all ones is "not available" for a parameter of 2
   bits or more; a sender that does not implement its counter or checksum fills it so):
   - a checksum that does not match and whose bits are all ones is no checksum: the rule is skipped
     (``checksum_not_available``, counted; a frame whose checksum matches is checked as usual);
   - a counter of 2 bits or more whose bits are all ones skips step 2 (``counter_not_available``,
     counted): it is neither frozen nor a jump, and neither p nor its time changes. The counter's
     values are then 0 .. M-2, so it counts modulo M-1 (a sender wrapping from M-2 to 0, or through
     the all-ones value, makes one step).
   On a raw CAN message all ones is a value like any other (a 4-bit counter wraps through 15).
3. Values: on a J1939 message, a value carrying J1939-71's error indicator rejects the frame
   (``error_code``); a value outside its DBC range rejects it (``out_of_range``)
   (:mod:`cmcan.can.j1939.values`).
A frame that passes all of them is *accepted*: its values go into the role windows. Rejections and
frames not available are counted per stream and, on a J1939 message, per source address
(``by_source``); the counters and checksums not available (2a) per stream.

At an evaluation tick at time t, a message is
- *erratic* when its newest frame at or before t (of those that reached step 1) was rejected and is no
  older than the timeout. Any erratic message makes the point IMPLAUSIBLE_INPUT, whatever the other
  gate rules say (frames arrive but cannot be used: a fault after the fault delay, DM1 FMI 2);
- *timed out* when its newest frame is older than the timeout (``timeout_cycles`` times its DBC cycle
  time; no timeout where the DBC gives no cycle time). Its roles are stale once their newest accepted
  sample is older than the timeout (the role's maximum age is at most the timeout), which the gate says
  as STALE_INPUT (a fault after the fault delay, FMI 9) unless every input is silent (bus idle:
  NO_INPUT, no fault);
- *fresh* otherwise, so a message is fresh again from its first accepted frame on.
A tick at which some message is not timed out counts, per message, one ``timeout`` for a message that
timed out since the last such tick; ticks with every message timed out (the bus idle) change nothing.

Each rule has two forms side by side, over the same state: frame by frame (:meth:`Stream.check`,
:meth:`Stream.note`, :meth:`Health.tick`) and over a stretch of frames and ticks as arrays
(:meth:`Stream.integrity_columns`, :meth:`Health.check_columns`, :meth:`Health.tick_columns`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cmcan.can.checksums import TSC1_FOLD, byte_sums, crc8_ok, id_sum
from cmcan.can.codec import Layout, extract, extract_all

OK, CHECKSUM, COUNTER_FROZEN, COUNTER_JUMP, OUT_OF_RANGE, OTHER_SENDER, ERROR_CODE, NOT_AVAILABLE = range(8)
REASONS = (
    "ok",
    "checksum",
    "counter_frozen",
    "counter_jump",
    "out_of_range",
    "other_sender",
    "error_code",
    "not_available",
)
REJECTIONS = (CHECKSUM, COUNTER_FROZEN, COUNTER_JUMP, OUT_OF_RANGE, OTHER_SENDER, ERROR_CODE)
# what a stream counts; bad_length is the router's (a frame too short is matched, never checked)
COUNTED = (
    "checksum",
    "counter_frozen",
    "counter_jump",
    "out_of_range",
    "timeout",
    "other_sender",
    "error_code",
    "not_available",
    "counter_not_available",
    "checksum_not_available",
)
MAX_SOURCES = 256  # addresses remembered per stream (a J1939 source address is one byte)
_TSC1_FOLD = np.array(TSC1_FOLD, dtype=np.uint8)
# integrity_columns marks a frame whose checksum is not available (2a) by this bit of its counter
# column (the core's arrays hold a counter and a checksum verdict per frame; counters are far shorter)
CHECKSUM_NA_BIT = 1 << 48


@dataclass(frozen=True)
class HealthSpec:
    """What to check on one message: its counter (layout, modulo, largest step), its checksum (a
    ``check(can_id, data) -> bool``, made from ``algorithm`` and ``checksum_layout``, which stand for it
    in comparisons), its timeout in seconds (inf: none)."""

    counter: Layout | None = None
    max_step: int = 2
    checksum: Callable[[int, bytes], bool] | None = field(default=None, compare=False)
    timeout_s: float = math.inf
    nbytes: int = 8  # the frame as an integer, for the counter's extraction
    checksum_name: str = ""  # the checksum's signal and algorithm, for people
    algorithm: str = ""  # the checksum's algorithm (j1939_tsc1 is checked inline, the common J1939 case)
    checksum_layout: Layout | None = None
    j1939: bool = False  # matched as J1939: counted per source address
    senders: bool = False  # J1939, more than one source address possible: rule 1b

    @property
    def modulo(self) -> int:
        return 1 << self.counter.length if self.counter is not None else 0

    @property
    def checked(self) -> bool:
        """Whether frames of the message are checked before their values are read (steps 1-2)."""
        return self.counter is not None or self.checksum is not None or self.senders


def counter_reader(lay: Layout, nbytes: int) -> Callable[[bytes], int]:
    """The raw counter of one frame (a byte read where the counter sits in one byte)."""
    if not lay.big_endian and lay.shift // 8 == (lay.shift + lay.length - 1) // 8:
        at, shift, mask = lay.shift // 8, lay.shift % 8, lay.mask
        return lambda d: (d[at] >> shift) & mask if len(d) > at else 0

    def read(d: bytes) -> int:
        w = bytes(d[:nbytes]).ljust(nbytes, b"\0")
        return int(extract(int.from_bytes(w, "big" if lay.big_endian else "little"), lay))

    return read


def all_ones_reader(lay: Layout, nbytes: int) -> Callable[[bytes], bool]:
    """Whether a frame's signal at ``lay`` has all its bits set (J1939's "not available")."""
    read, mask = counter_reader(lay, nbytes), lay.mask
    return lambda d: read(d) & mask == mask


class Stream:
    """The health state of one message stream (see the module's rules)."""

    __slots__ = (
        "_at",
        "_cs_read",
        "_id",
        "_id_sum",
        "_mask",
        "_read",
        "_shift",
        "by_source",
        "checksum",
        "counts",
        "cs_na",
        "last_sa",
        "max_step",
        "modulo",
        "na",
        "newest_ok",
        "newest_t",
        "prev",
        "prev_t",
        "seen",
        "spec",
        "timed_out",
        "timeout_s",
        "tsc1",
    )

    def __init__(self, spec: HealthSpec) -> None:
        self.spec = spec
        self.checksum = spec.checksum
        # J1939-71's TSC1 checksum with its counter in byte 8: checked here without a call (the hot path)
        self.tsc1 = spec.algorithm == "j1939_tsc1"
        if self.tsc1:
            self.checksum = None
        self._id = -1
        self._id_sum = 0
        self._read = counter_reader(spec.counter, spec.nbytes) if spec.counter is not None else None
        # the common case, a counter within one byte of an Intel layout, read inline
        lay = spec.counter
        one_byte = lay is not None and not lay.big_endian and lay.shift // 8 == (lay.shift + lay.length - 1) // 8
        self._at = lay.shift // 8 if one_byte and lay is not None else -1
        self._shift = lay.shift % 8 if one_byte and lay is not None else 0
        self._mask = lay.mask if lay is not None else 0
        # rule 2a: on J1939, the all-ones counter (2 bits or more) is not available, the rest count modulo M-1
        self.na = self._mask if spec.j1939 and lay is not None and lay.length >= 2 else -1
        self.modulo = spec.modulo - 1 if self.na >= 0 else spec.modulo
        self.cs_na = spec.j1939 and spec.checksum_layout is not None and spec.checksum_layout.length >= 2
        cs = spec.checksum_layout
        self._cs_read = all_ones_reader(cs, spec.nbytes) if self.cs_na and cs is not None and not self.tsc1 else None
        self.max_step = spec.max_step
        self.timeout_s = spec.timeout_s
        self.counts = dict.fromkeys(COUNTED, 0)
        self.by_source: dict[int, dict[str, int]] = {}  # J1939: rejections and not available, per address
        self.last_sa: int | None = None  # rule 1b: the address of the frame before, and each one's last time
        self.seen: dict[int, float] = {}
        self.prev: int | None = None
        self.prev_t = -math.inf
        self.newest_t = -math.inf
        self.newest_ok = True
        self.timed_out = False

    @property
    def has_counter(self) -> bool:
        return self.tsc1 or self._read is not None

    def shift(self, delta_s: float) -> None:
        """The wall clock stepped by ``delta_s``: the stream's times move onto the new time base."""
        self.prev_t += delta_s
        self.newest_t += delta_s
        self.seen = {sa: t + delta_s for sa, t in self.seen.items()}

    # -- one frame ---------------------------------------------------------------------------------

    def check(self, t: float, can_id: int, data: bytes, absent: bool = False) -> int:
        """Steps 1 to 2a for a frame at ``t`` (``absent``: a value not available, rule 1a): OK,
        CHECKSUM, NOT_AVAILABLE, OTHER_SENDER, COUNTER_FROZEN or COUNTER_JUMP."""
        if self.tsc1:  # 8 bytes (the message's length, checked before): counter and checksum in byte 8
            if can_id != self._id:
                self._id, self._id_sum = can_id, id_sum(can_id)
            c = data[7]
            if c >> 4 != TSC1_FOLD[sum(data) - (c & 0xF0) + self._id_sum]:
                if c < 0xF0 or not self.cs_na:  # (the fold is at most 7: a nibble 0xF never matches)
                    return CHECKSUM
                self.counts["checksum_not_available"] += 1
            if absent:
                return NOT_AVAILABLE
            if self.spec.senders and self.other_sender(t, can_id & 0xFF):
                return OTHER_SENDER
            c &= 0x0F
        else:
            if self.checksum is not None and not self.checksum(can_id, data):
                if self._cs_read is None or not self._cs_read(data):
                    return CHECKSUM
                self.counts["checksum_not_available"] += 1
            if absent:
                return NOT_AVAILABLE
            if self.spec.senders and self.other_sender(t, can_id & 0xFF):
                return OTHER_SENDER
            at = self._at
            if at >= 0:
                c = (data[at] >> self._shift) & self._mask if len(data) > at else 0
            elif self._read is None:
                return OK
            else:
                c = self._read(data)
        return self.count_step(t, c)

    def count_step(self, t: float, c: int) -> int:
        """Step 2 (and 2a's counter) for the counter ``c`` of a frame at ``t`` that passed step 1."""
        if c == self.na:  # not available: the sender does not count; it is no reference either
            self.counts["counter_not_available"] += 1
            return OK
        p = self.prev
        verdict = OK
        if p is not None and t - self.prev_t <= self.timeout_s:
            d = (c - p) % self.modulo
            if d == 0:
                verdict = COUNTER_FROZEN
            elif d > self.max_step:
                verdict = COUNTER_JUMP
        self.prev = c
        self.prev_t = t
        return verdict

    def other_sender(self, t: float, sa: int) -> bool:
        """Rule 1b for a frame from address ``sa`` at ``t`` (that passed the checksum): True when
        another node sends the message at the same time (the frame is then rejected)."""
        seen = self.seen
        prev = seen.get(sa)
        seen[sa] = t
        if sa == self.last_sa:  # the frame before was this sender's: nobody else sent since
            return False
        self.last_sa = sa
        if prev is None or t - prev > self.timeout_s:  # new, or back after its timeout
            if len(seen) > MAX_SOURCES:
                self.seen = {sa: t}
            return False
        return any(a != sa and last >= prev and t - last <= self.timeout_s for a, last in seen.items())

    def note(self, t: float, verdict: int, can_id: int = -1) -> None:
        """The frame at ``t`` (identifier ``can_id`` where the source address counts) was accepted
        (OK), rejected for ``verdict``, or not a sample (NOT_AVAILABLE); counted."""
        if verdict == OK:
            if t >= self.newest_t:
                self.newest_t = t
                self.newest_ok = True
            return
        if verdict != NOT_AVAILABLE and t >= self.newest_t:
            self.newest_t = t
            self.newest_ok = False
        reason = REASONS[verdict]
        self.counts[reason] += 1
        if can_id >= 0 and self.spec.j1939:
            per = self.by_source.setdefault(can_id & 0xFF, {})
            per[reason] = per.get(reason, 0) + 1

    def erratic(self, t: float) -> bool:
        return not self.newest_ok and self.newest_t <= t and t - self.newest_t <= self.timeout_s

    def silent(self, t: float) -> bool:
        """No frame yet, or none within the timeout."""
        return self.newest_t == -math.inf or t - self.newest_t > self.timeout_s

    # -- many frames -------------------------------------------------------------------------------

    def integrity_columns(
        self, ids: NDArray[np.uint32], data: NDArray[np.uint8], length: int
    ) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """The counter (0 where none) and whether the checksum holds (True where none) of each frame
        of this message (identifiers ``ids``, payloads ``data``, the message ``length`` bytes long),
        pure functions of the frame, as :meth:`check` reads them. A checksum not available (rule 2a)
        holds here, its counter marked with :data:`CHECKSUM_NA_BIT` for :meth:`Health.check_columns`
        to count it."""
        n = len(ids)
        spec = self.spec
        if self.tsc1:  # 8 bytes: counter and checksum in byte 8, the sum over the message and the id
            d7 = data[:, 7]
            words = (
                data if data.shape[1] == 8 and data.flags.c_contiguous else np.ascontiguousarray(data[:, :8])
            ).view("<u8")[:, 0]
            s = byte_sums(words, 0x0FFF_FFFF_FFFF_FFFF)  # bytes 1-7 and the counter (the low half of byte 8)
            if n and bool((ids == ids[0]).all()):  # a sender that kept its address: one identifier sum
                s += np.uint64(id_sum(int(ids[0])))
            else:
                s += byte_sums(ids)
            ok = (d7 >> 4) == _TSC1_FOLD[s.view(np.int64)]  # a signed index gathers ~3x faster
            ctr = d7 & 0x0F
            if self.cs_na and (d7 >= 0xF0).any():
                return _checksum_not_available(ctr.astype(np.int64), ok, d7 >= 0xF0)
            return ctr, ok
        ctr = np.zeros(n, dtype=np.int64)
        cs_ok = np.ones(n, dtype=bool)
        if (
            spec.algorithm == "crc8_sae_j1850"
            and spec.checksum_layout is not None
            and (ok := crc8_ok(length, spec.checksum_layout, data)) is not None
        ):
            cs_ok = ok
        elif self.checksum is not None:  # any other checksum: frame by frame, as check does
            for i in range(n):
                cs_ok[i] = self.checksum(int(ids[i]), data[i, :length].tobytes())
        if spec.counter is not None:
            ctr[:] = extract_all(data[:, : spec.nbytes], [spec.counter], spec.nbytes)[0]
        lay = spec.checksum_layout
        if self._cs_read is not None and lay is not None and not cs_ok.all():
            raw = extract_all(data[:, : spec.nbytes], [lay], spec.nbytes)[0]
            return _checksum_not_available(ctr, cs_ok, np.asarray(raw & lay.mask == lay.mask, dtype=bool))
        return ctr, cs_ok


@dataclass(frozen=True)
class _Passing:
    """What :meth:`Health.check_columns` leaves one stream for :meth:`Health.commit_counters`."""

    passed: NDArray[np.int64]  # the frames that passed step 1 with their values (rule 1b's, up to until)
    t: NDArray[np.float64]  # their times
    ref: int | None  # the sender whose frames they are
    counting: NDArray[np.int64]  # those with a counter available (step 2)
    counters: NDArray[np.int64]  # and their counters and times
    counting_t: NDArray[np.float64]
    cs_na: NDArray[np.int64]  # the frames whose checksum was not available
    ctr_na: NDArray[np.int64]  # the frames whose counter was not available


class Health:
    """The health of every mapped message's stream, and the counts over all of them (``base``: the
    counts of streams a reload replaced)."""

    def __init__(self, specs: Sequence[HealthSpec]) -> None:
        self.streams = tuple(Stream(s) for s in specs)
        self.base = dict.fromkeys(COUNTED, 0)
        self._passing: list[_Passing | None] = []

    def counts(self) -> dict[str, int]:
        """Rejections and timeouts over all streams."""
        out = dict(self.base)
        for st in self.streams:
            for k, v in st.counts.items():
                out[k] += v
        return out

    def shift(self, delta_s: float) -> None:
        for st in self.streams:
            st.shift(delta_s)

    def tick(self, t: float) -> bool:
        """The verdict of a tick at ``t``: True when some stream is erratic; timeouts counted."""
        erratic = False
        alive = False
        for s in self.streams:
            if s.erratic(t):
                erratic = True
            if s.timeout_s < math.inf and not s.silent(t):
                alive = True
        if alive:
            for s in self.streams:
                out = s.newest_t > -math.inf and s.silent(t)
                if out and not s.timed_out:
                    s.counts["timeout"] += 1
                s.timed_out = out
        return erratic

    # -- a stretch ---------------------------------------------------------------------------------

    def check_columns(
        self,
        t: NDArray[np.float64],
        reach: Sequence[NDArray[np.int64]],
        ctr: NDArray[np.int64],
        cs_ok: NDArray[np.bool_],
        sa: NDArray[np.int64],
        absent: NDArray[np.bool_],
    ) -> tuple[NDArray[np.int8], int]:
        """Steps 1 to 2a for the frames that reach them (``reach[i]``: stream i's, in arrival order;
        ``ctr``, ``cs_ok`` from :meth:`Stream.integrity_columns`, ``sa`` their source addresses,
        ``absent`` the frames with a value not available): a failed checksum, else (a frame with its
        values) the counter against the previous frame that passed the checksum (within the
        timeout); the frames not available are left OK here (their values say it). Rule 1b's array
        form takes the frames of the stream's sender; the verdicts hold up to the first frame from
        another address than the frame before (returned, else the length), which rule 1b decides
        frame by frame. Keeps what :meth:`commit_counters` needs."""
        out = np.zeros(len(t), dtype=np.int8)
        until = len(t)
        self._passing = []
        flagged = bool(len(ctr)) and int(ctr.max()) >= CHECKSUM_NA_BIT
        for st, mine in zip(self.streams, reach, strict=True):
            if not st.spec.checked:
                self._passing.append(None)
                continue
            passed = cs_ok[mine]
            out[mine[~passed]] = CHECKSUM
            p = mine[passed & ~absent[mine]]
            c, cs_na = ctr[p], p[:0]
            if flagged:  # some checksum not available (rule 2a): counted at the commit, its mark off
                cs_na = mine[ctr[mine] >= CHECKSUM_NA_BIT]
                c = c & (CHECKSUM_NA_BIT - 1)
            ref = st.last_sa
            if st.spec.senders and len(p):  # frames from the address of the frame before pass
                if ref is None:  # the stream's first frame: nobody sent before it, it passes
                    ref = int(sa[p[0]])
                other = np.flatnonzero(sa[p] != ref)
                if len(other):
                    until = min(until, int(p[other[0]]))
            tp = t[p]
            q, cq, tq, ctr_na = p, c, tp, p[:0]
            if st.na >= 0 and not (counting := c != st.na).all():  # rule 2a: an all-ones counter skips step 2
                q, cq, tq, ctr_na = p[counting], c[counting], tp[counting], p[~counting]
            self._passing.append(_Passing(p, tp, ref, q, cq, tq, cs_na, ctr_na))
            if len(q) and st.has_counter:
                out[q] = _counter_verdicts(st, cq, tq)
        return out, until

    def commit_counters(self, stop: int) -> None:
        """Each stream's previous counter and its time, and its sender's last frame, as the first
        ``stop`` frames leave them; the counters and checksums not available among them counted."""
        for st, ps in zip(self.streams, self._passing, strict=True):
            if ps is None:
                continue
            n = int(np.searchsorted(ps.counting, stop))
            if n and st.has_counter:
                st.prev = int(ps.counters[n - 1])
                st.prev_t = float(ps.counting_t[n - 1])
            n = int(np.searchsorted(ps.passed, stop))
            if n and st.spec.senders:
                st.last_sa = ps.ref
                st.seen[ps.ref] = float(ps.t[n - 1])
            st.counts["checksum_not_available"] += int(np.searchsorted(ps.cs_na, stop))
            st.counts["counter_not_available"] += int(np.searchsorted(ps.ctr_na, stop))
        self._passing = []

    def tick_columns(
        self,
        t: NDArray[np.float64],
        reach: Sequence[NDArray[np.int64]],
        verdict: NDArray[np.int8],
        trig: NDArray[np.int64],
        t_k: NDArray[np.float64],
        sa: NDArray[np.int64],
    ) -> NDArray[np.bool_]:
        """:meth:`tick` at every tick of a stretch, with the frames' verdicts noted: each stream's
        newest frame and its verdict at each tick (the frames before ``trig``, the one that completes
        the tick), whether some stream is erratic there, the timeouts counted at the ticks where
        some stream is alive; the streams' state and counts left as frame-by-frame leaves them.
        ``reach``: each stream's frames that got to the checks (not late); ``verdict``: theirs."""
        erratic = np.zeros(len(t_k), dtype=bool)
        alive = np.zeros(len(t_k), dtype=bool)
        silent_after_frames = []
        ends = []
        for st, f in zip(self.streams, reach, strict=True):
            vf = verdict[f]
            _count(st, vf, sa[f])
            sample = vf != NOT_AVAILABLE  # a frame not available is as if it had not come
            if not sample.all():
                f, vf = f[sample], vf[sample]
            nt, ok_t, end = _newest_at_ticks(st, t[f], vf, f, trig)
            ends.append(end)
            with np.errstate(invalid="ignore"):
                age = t_k - nt
                erratic |= ~ok_t & (nt <= t_k) & (age <= st.timeout_s)
                silent = (nt == -np.inf) | (age > st.timeout_s)
            if st.timeout_s < math.inf:
                alive |= ~silent
            silent_after_frames.append((nt > -np.inf) & silent)
        live = np.flatnonzero(alive)
        for st, out, (nt_end, ok_end) in zip(self.streams, silent_after_frames, ends, strict=True):
            if len(live):
                o = out[live]
                prev = np.concatenate([[st.timed_out], o[:-1]])
                st.counts["timeout"] += int(np.count_nonzero(o & ~prev))
                st.timed_out = bool(o[-1])
            st.newest_t, st.newest_ok = nt_end, ok_end
        return erratic


def _checksum_not_available(
    ctr: NDArray[np.int64], cs_ok: NDArray[np.bool_], all_ones: NDArray[np.bool_]
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Rule 2a on columns: a checksum that fails with all its bits set holds, its frame marked."""
    na = all_ones & ~cs_ok
    return np.where(na, ctr | CHECKSUM_NA_BIT, ctr), cs_ok | na


def _counter_verdicts(st: Stream, c: NDArray[np.int64], tp: NDArray[np.float64]) -> NDArray[np.int8]:
    """Step 2 over a stream's frames that passed the checksum, from its state before them."""
    prev_c = np.concatenate([[st.prev if st.prev is not None else 0], c[:-1]])
    prev_t = np.concatenate([[st.prev_t], tp[:-1]])
    has_prev = np.ones(len(c), dtype=bool)
    has_prev[0] = st.prev is not None
    within = has_prev & (tp - prev_t <= st.timeout_s)
    d = (c - prev_c) % st.modulo
    return np.where(within & (d == 0), COUNTER_FROZEN, np.where(within & (d > st.max_step), COUNTER_JUMP, OK))


def _newest_at_ticks(
    st: Stream, tf: NDArray[np.float64], vf: NDArray[np.int8], f: NDArray[np.int64], trig: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_], tuple[float, bool]]:
    """A stream's newest frame time and whether it was accepted, at each tick (the frames before the
    tick's trigger), as :meth:`Stream.note` leaves them frame after frame (later frames win ties);
    and the state after the last frame."""
    n_ticks = len(trig)
    if not len(f):
        return np.full(n_ticks, st.newest_t), np.full(n_ticks, st.newest_ok), (st.newest_t, st.newest_ok)
    run = np.concatenate([[st.newest_t], tf])
    if tf[0] >= st.newest_t and (tf[1:] >= tf[:-1]).all():  # in order (the usual): each frame sets it
        ok_after = vf == OK
    else:
        run = np.maximum.accumulate(run)
        upd = tf >= run[:-1]
        last = np.maximum.accumulate(np.where(upd, np.arange(len(f)), -1))
        ok_after = np.where(last >= 0, vf[np.maximum(last, 0)] == OK, st.newest_ok)
    seen = np.searchsorted(f, trig)
    ok_t = np.where(seen > 0, ok_after[np.maximum(seen - 1, 0)], st.newest_ok)
    return run[seen], ok_t, (float(run[-1]), bool(ok_after[-1]))


def _count(st: Stream, vf: NDArray[np.int8], sa: NDArray[np.int64]) -> None:
    """A stream's rejected and not-available frames counted, per source address on J1939."""
    for code in (*REJECTIONS, NOT_AVAILABLE):
        hit = vf == code
        n = int(np.count_nonzero(hit))
        if not n:
            continue
        reason = REASONS[code]
        st.counts[reason] += n
        if st.spec.j1939:
            addresses, per = np.unique(sa[hit], return_counts=True)
            for a, k in zip(addresses.tolist(), per.tolist(), strict=True):
                d = st.by_source.setdefault(a, {})
                d[reason] = d.get(reason, 0) + k
