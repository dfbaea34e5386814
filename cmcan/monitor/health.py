"""Input health per mapped message, as production CAN receivers check it: checksum, alive counter and
timeout. Pure state over the frames' own times; nothing here reads a clock.

Each mapped input message is one *stream*, whatever J1939 source address its frames carry (a
controller that claims another address keeps its counter sequence; two senders interleaving on one
message show up as a jumping counter). For each frame of the stream that has the message's length and
is not late (:mod:`cmcan.monitor.clock`), in arrival order:

1. Checksum, where the message has one: a frame whose checksum does not match is rejected
   (``checksum``) and changes nothing else.
2. Alive counter, where the message has one, modulo M = 2**bits: let p be the counter of the stream's
   previous frame that passed step 1 and dt the time since that frame. With no such frame, or dt above
   the message's timeout (the sender restarted, or the machine was off), the frame passes. Otherwise,
   with d = (c - p) mod M: d == 0 is a frozen counter (``counter_frozen``) and d > max_step a jump
   (``counter_jump``); both reject the frame; 1 <= d <= max_step passes (max_step 2 tolerates one lost
   frame). Either way p becomes c: after a jump the counter is followed from its new value, so the next
   frame in sequence passes again.
3. Range: a value outside its DBC range rejects the frame (``out_of_range``).
A frame that passes all three is *accepted*: its values go into the role windows.

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
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from cmcan.checksums import TSC1_FOLD, id_sum
from cmcan.codec import Layout, extract

OK, CHECKSUM, COUNTER_FROZEN, COUNTER_JUMP, OUT_OF_RANGE = 0, 1, 2, 3, 4
REASONS = ("ok", "checksum", "counter_frozen", "counter_jump", "out_of_range")
COUNTED = ("bad_length", "checksum", "counter_frozen", "counter_jump", "out_of_range", "timeout")


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

    @property
    def modulo(self) -> int:
        return 1 << self.counter.length if self.counter is not None else 0


def counter_reader(lay: Layout, nbytes: int) -> Callable[[bytes], int]:
    """The raw counter of one frame (a byte read where the counter sits in one byte)."""
    if not lay.big_endian and lay.shift // 8 == (lay.shift + lay.length - 1) // 8:
        at, shift, mask = lay.shift // 8, lay.shift % 8, lay.mask
        return lambda d: (d[at] >> shift) & mask if len(d) > at else 0

    def read(d: bytes) -> int:
        w = bytes(d[:nbytes]).ljust(nbytes, b"\0")
        return int(extract(int.from_bytes(w, "big" if lay.big_endian else "little"), lay))

    return read


class Stream:
    """The health state of one message stream (see the module's rules)."""

    __slots__ = (
        "_at",
        "_id",
        "_id_sum",
        "_mask",
        "_read",
        "_shift",
        "checksum",
        "counts",
        "max_step",
        "modulo",
        "newest_ok",
        "newest_t",
        "prev",
        "prev_t",
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
        self.modulo = spec.modulo
        self.max_step = spec.max_step
        self.timeout_s = spec.timeout_s
        self.counts = dict.fromkeys(COUNTED, 0)
        self.reset()

    def reset(self) -> None:
        self.prev: int | None = None
        self.prev_t = -math.inf
        self.newest_t = -math.inf
        self.newest_ok = True
        self.timed_out = False

    def shift(self, delta_s: float) -> None:
        """The wall clock stepped by ``delta_s``: the stream's times move onto the new time base."""
        self.prev_t += delta_s
        self.newest_t += delta_s

    def check(self, t: float, can_id: int, data: bytes) -> int:
        """Steps 1 and 2 for a frame at ``t``: OK, CHECKSUM, COUNTER_FROZEN or COUNTER_JUMP."""
        if self.tsc1:  # 8 bytes (the message's length, checked before): counter and checksum in byte 8
            if can_id != self._id:
                self._id, self._id_sum = can_id, id_sum(can_id)
            c = data[7]
            if c >> 4 != TSC1_FOLD[sum(data) - (c & 0xF0) + self._id_sum]:
                return CHECKSUM
            c &= 0x0F
        else:
            if self.checksum is not None and not self.checksum(can_id, data):
                return CHECKSUM
            at = self._at
            if at >= 0:
                c = (data[at] >> self._shift) & self._mask if len(data) > at else 0
            elif self._read is None:
                return OK
            else:
                c = self._read(data)
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

    def note(self, t: float, verdict: int) -> None:
        """The frame at ``t`` was accepted (OK) or rejected for ``verdict``."""
        if t >= self.newest_t:
            self.newest_t = t
            self.newest_ok = verdict == OK
        if verdict != OK:
            self.counts[REASONS[verdict]] += 1

    def erratic(self, t: float) -> bool:
        return not self.newest_ok and self.newest_t <= t and t - self.newest_t <= self.timeout_s

    def silent(self, t: float) -> bool:
        """No frame yet, or none within the timeout."""
        return self.newest_t == -math.inf or t - self.newest_t > self.timeout_s


def tick(streams: list[Stream], t: float, counters: dict[str, int]) -> bool:
    """The health verdict of a tick at ``t``: True when some stream is erratic. Counts timeouts, per
    stream and in the monitor's ``counters``."""
    erratic = False
    alive = False
    for s in streams:
        if s.erratic(t):
            erratic = True
        if s.timeout_s < math.inf and not s.silent(t):
            alive = True
    if alive:
        for s in streams:
            out = s.newest_t > -math.inf and s.silent(t)
            if out and not s.timed_out:
                s.counts["timeout"] += 1
                counters["timeout"] += 1
            s.timed_out = out
    return erratic
