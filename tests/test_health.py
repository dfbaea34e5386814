"""Input health per message stream (monitor/health.py): the rules of its docstring, checked on random
frame sequences against a reference written from those rules, with the interesting cases reached."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.can import checksums
from cmcan.can.codec import Layout
from cmcan.monitor import health
from cmcan.monitor.health import HealthSpec, Stream

COUNTER = Layout("ctr", 56, 4, False, False, 1.0, 0.0, 0.0, 15.0)  # byte 8, bits 1-4
CHECKSUM = Layout("cs", 48, 8, False, False, 1.0, 0.0, 0.0, 255.0)  # byte 7 (the test's checksum's value)
TSC1_CHECKSUM = Layout("cs", 60, 4, False, False, 1.0, 0.0, 0.0, 15.0)  # byte 8, bits 5-8
TIMEOUT = 0.1


def frame(counter: int, checksum_ok: bool, checksum_ones: bool = False) -> bytes:
    # byte 1 carries whether the (test's) checksum holds, byte 7 the checksum's value (all ones or 0)
    return bytes([1 if checksum_ok else 0, 0, 0, 0, 0, 0, 0xFF if checksum_ones else 0, counter & 0x0F])


def spec(max_step: int, j1939: bool = False, senders: bool = False) -> HealthSpec:
    return HealthSpec(
        counter=COUNTER,
        max_step=max_step,
        checksum=lambda _id, d: d[0] == 1,
        timeout_s=TIMEOUT,
        checksum_layout=CHECKSUM,
        j1939=j1939,
        senders=senders,
    )


def tsc1_spec(max_step: int, j1939: bool, senders: bool = False) -> HealthSpec:
    return HealthSpec(
        counter=COUNTER,
        max_step=max_step,
        checksum=checksums.verifier("j1939_tsc1", 8, TSC1_CHECKSUM),
        timeout_s=TIMEOUT,
        algorithm="j1939_tsc1",
        checksum_layout=TSC1_CHECKSUM,
        j1939=j1939,
        senders=senders,
    )


def tsc1_frame(can_id: int, counter: int, checksum_ok: bool, checksum_ones: bool, fill: int) -> bytes:
    """A TSC1 frame: its checksum right, wrong, or all ones (not available)."""
    d = np.array([[fill] * 7 + [counter]], dtype=np.uint8)
    sealed = checksums.seal("j1939_tsc1", 8, TSC1_CHECKSUM, np.array([can_id]), d)[0]
    if checksum_ones:
        sealed[7] |= 0xF0
    elif not checksum_ok:
        sealed[7] ^= 0x10  # another checksum (the fold is 0-7: bit 5 flipped, never all ones)
    return sealed.tobytes()


def reference(events, max_step, j1939=False):
    """The module docstring's steps 1-2a, restated; with the not-available counts."""
    prev, prev_t, out = None, -math.inf, []
    notes = {"counter_not_available": 0, "checksum_not_available": 0}
    modulo = 15 if j1939 else 16
    for t, c, ok, ones in events:
        if not ok:
            if not (j1939 and ones):
                out.append(health.CHECKSUM)
                continue
            notes["checksum_not_available"] += 1
        if j1939 and c == 15:
            notes["counter_not_available"] += 1
            out.append(health.OK)
            continue
        v = health.OK
        if prev is not None and t - prev_t <= TIMEOUT:
            d = (c - prev) % modulo
            v = health.COUNTER_FROZEN if d == 0 else health.COUNTER_JUMP if d > max_step else health.OK
        prev, prev_t = c, t
        out.append(v)
    return out, notes


CHECKSUM_CASES = [(True, False)] * 7 + [(True, True), (False, False), (False, True)]
# A sender mostly counting on, sometimes repeating, skipping or jumping, pausing, or corrupt; a
# J1939 one now and then with its counter or checksum all ones (not available).
steps = st.lists(
    st.tuples(
        st.sampled_from([0.01] * 6 + [0.005, 0.05, 0.2]),  # time since the previous frame
        st.sampled_from([1] * 8 + [0, 2, 3, 7, 15]),  # counter step
        st.sampled_from(CHECKSUM_CASES),  # checksum holds, checksum all ones
    ),
    min_size=1,
    max_size=60,
)
SEEN: set[str] = set()


@given(steps, st.integers(1, 3), st.booleans(), st.sampled_from([16, 15]))
@settings(max_examples=400, deadline=None, derandomize=True, database=None)  # the reach check cannot flake
def check_stream_against_the_rules(seq, max_step, j1939, wraps_at):
    """``wraps_at`` 15: a sender counting 0-14, as one that keeps all ones for "not available"."""
    s = Stream(spec(max_step, j1939))
    t, c, events = 100.0, 3, []
    for dt, step, (ok, ones) in seq:
        t += dt
        c = (c + step) % wraps_at
        events.append((t, c, ok, ones))
    want, notes = reference(events, max_step, j1939)
    for i, ((t, c, ok, ones), w) in enumerate(zip(events, want, strict=True)):
        got = s.check(t, 0x123, frame(c, ok, ones))
        assert got == w
        s.note(t, got)
        SEEN.add(health.REASONS[got])
        # right after the frame: erratic exactly when it was rejected
        assert s.erratic(t) == (got != health.OK)
        assert not s.silent(t) and s.silent(t + TIMEOUT + 1e-6)
        assert not s.erratic(t + TIMEOUT + 1e-6)  # an old rejection is a timeout, not erratic
        if w == health.OK and i > 0 and events[i - 1][0] < t - TIMEOUT:
            SEEN.add("restart after a timeout")
        if c == 15 and ok:
            SEEN.add("J1939 counter all ones" if j1939 else "raw CAN counter all ones checked")
        if j1939 and not ok and ones:
            SEEN.add("J1939 checksum all ones")
        if j1939 and w == health.OK and i > 1 and (events[i - 2][1], events[i - 1][1], c) == (14, 15, 0):
            SEEN.add("J1939 counter wraps through all ones")  # a sender counting 0-15
        if j1939 and w == health.OK and i > 0 and (events[i - 1][1], c) == (14, 0):
            SEEN.add("J1939 counter wraps from 14 to 0")  # one counting 0-14
    assert {k: s.counts[k] for k in notes} == notes


def test_stream_follows_its_rules_and_reaches_every_case():
    SEEN.clear()
    check_stream_against_the_rules()
    assert {
        "ok",
        "checksum",
        "counter_frozen",
        "counter_jump",
        "restart after a timeout",
        "J1939 counter all ones",
        "raw CAN counter all ones checked",
        "J1939 checksum all ones",
        "J1939 counter wraps through all ones",
        "J1939 counter wraps from 14 to 0",
    } <= SEEN, SEEN


def test_a_j1939_sender_that_does_not_count_is_no_frozen_counter():
    """908 of a real truck's 923 TSC1 frames carry the counter and checksum all ones (byte 8 0xFF):
    J1939's "not available". The frames pass and are counted; the same bytes on raw CAN are frozen."""
    s = Stream(tsc1_spec(2, j1939=True))
    raw = Stream(tsc1_spec(2, j1939=False))
    data = bytes([0x01, 0x20, 0x03, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF])
    got = [s.check(i * 0.01, 0x0C000003, data) for i in range(5)]
    assert got == [health.OK] * 5
    assert s.counts["counter_not_available"] == s.counts["checksum_not_available"] == 5
    assert s.prev is None  # no reference: the sender's first real counter passes
    assert [raw.check(i * 0.01, 0x0C000003, data) for i in range(2)] == [health.CHECKSUM] * 2


def test_a_j1939_counter_that_stops_counting_is_judged_from_its_last_real_value():
    s = Stream(spec(1, j1939=True))
    cs = [(0.0, 13), (0.01, 14), (0.02, 15), (0.03, 0), (0.04, 15), (0.05, 15), (0.06, 0), (0.07, 1)]
    verdicts = [s.check(t, 0, frame(c, True)) for t, c in cs]
    # 14 -> 15 (skipped) -> 0 is one step modulo 15; 0 -> 15, 15 -> 0 is the counter frozen at 0
    assert verdicts == [health.OK] * 6 + [health.COUNTER_FROZEN, health.OK]
    assert s.counts["counter_not_available"] == 3


def test_raw_can_counters_wrap_through_all_ones():
    s = Stream(spec(1))
    assert [s.check(i * 0.01, 0, frame(c, True)) for i, c in enumerate((14, 15, 0, 15))] == [
        health.OK,
        health.OK,
        health.OK,
        health.COUNTER_JUMP,
    ]


def test_after_a_jump_the_next_frame_in_sequence_passes():
    s = Stream(spec(2))
    verdicts = [s.check(t, 0, frame(c, True)) for t, c in ((0.0, 1), (0.01, 2), (0.02, 9), (0.03, 10), (0.04, 10))]
    assert verdicts == [health.OK, health.OK, health.COUNTER_JUMP, health.OK, health.COUNTER_FROZEN]


def test_a_wrong_checksum_leaves_the_counter_alone():
    s = Stream(spec(1))
    assert s.check(0.0, 0, frame(4, True)) == health.OK
    assert s.check(0.01, 0, frame(9, False)) == health.CHECKSUM
    assert s.check(0.02, 0, frame(5, True)) == health.OK  # 4 -> 5: the corrupt frame did not count


def test_timeouts_are_counted_only_while_another_message_is_alive():
    h = health.Health([spec(2), spec(2)])
    a, b = h.streams
    for st_ in (a, b):
        st_.note(0.0, health.OK)
    assert not h.tick(0.05)
    b.note(0.2, health.OK)  # a went quiet, b goes on
    h.tick(0.25)
    assert a.counts["timeout"] == 1 and b.counts["timeout"] == 0
    h.tick(0.35)  # still out: not counted twice
    assert a.counts["timeout"] == 1
    h.tick(5.0)  # everything silent: the bus is idle, nothing changes
    a.note(5.01, health.OK)
    b.note(5.01, health.OK)
    h.tick(5.05)
    assert a.counts["timeout"] == 1 and b.counts["timeout"] == 0
    assert h.counts()["timeout"] == 1  # the total over the streams


def test_an_erratic_stream_makes_the_tick_erratic():
    h = health.Health([spec(2), spec(2)])
    a, b = h.streams
    a.note(0.0, health.OK)
    b.note(0.0, health.COUNTER_FROZEN)
    assert h.tick(0.05)
    assert not h.tick(0.2)  # b's rejected frame is older than its timeout now
    assert b.counts["counter_frozen"] == 1


# -- both forms: frame by frame and columns ------------------------------------------------------

SEEN_COLUMNS: set[str] = set()
ADDRESSES = (0x03, 0x05)


def forms_frames(kind: str, seq) -> tuple[HealthSpec, list[tuple[float, int, bytes, bool]]]:
    """The spec and frames (time, identifier, payload, value not available) of a random sender."""
    j1939 = kind in ("j1939", "tsc1")
    sp = (tsc1_spec if kind.startswith("tsc1") else spec)(2, j1939, senders=j1939)
    t, c, out = 100.0, 3, []
    for dt, step, (ok, ones), absent, other in seq:
        t += dt
        c = (c + step) % 16
        can_id = 0x0C000000 | ADDRESSES[other]
        data = tsc1_frame(can_id, c, ok, ones, int(t * 100) & 0xFF) if kind.startswith("tsc1") else frame(c, ok, ones)
        out.append((t, can_id, data, absent and j1939))
    return sp, out


def by_frames(sp: HealthSpec, frames) -> tuple[list[int], Stream]:
    s = health.Health([sp]).streams[0]
    verdicts = []
    for t, can_id, data, absent in frames:
        v = s.check(t, can_id, data, absent)
        s.note(t, v, can_id)
        verdicts.append(v)
    return verdicts, s


def by_columns(sp: HealthSpec, frames, cuts) -> tuple[list[int], Stream]:
    """As the core's columnar engine drives it: stretches committed up to a cut or rule 1b's limit,
    a frame rule 1b stops at taken frame by frame."""
    h = health.Health([sp])
    s = h.streams[0]
    t = np.array([f[0] for f in frames])
    ids = np.array([f[1] for f in frames], dtype=np.uint32)
    data = np.array([list(f[2]) for f in frames], dtype=np.uint8)
    absent = np.array([f[3] for f in frames])
    sa = (ids & 0xFF).astype(np.int64)
    ctr, cs_ok = s.integrity_columns(ids, data, 8)
    verdicts: list[int] = []
    pos, cuts = 0, iter(cuts)
    while pos < len(frames):
        reach = [np.arange(len(frames) - pos)]
        checks, until = h.check_columns(t[pos:], reach, ctr[pos:], cs_ok[pos:], sa[pos:], absent[pos:])
        stop = min(until, next(cuts, len(frames)))
        if stop == 0:  # the per-frame path for one frame
            SEEN_COLUMNS.add("frame by frame")
            v = s.check(t[pos], int(ids[pos]), data[pos].tobytes(), bool(absent[pos]))
            s.note(float(t[pos]), v, int(ids[pos]))
            verdicts.append(v)
            pos += 1
            continue
        h.commit_counters(stop)
        verdict = np.where(checks != health.OK, checks, np.where(absent[pos:], health.NOT_AVAILABLE, health.OK))
        empty = np.zeros(0, dtype=np.int64)
        h.tick_columns(t[pos : pos + stop], [reach[0][:stop]], verdict[:stop], empty, empty * 1.0, sa[pos:])
        verdicts += verdict[:stop].astype(int).tolist()
        pos += stop
    return verdicts, s


@given(
    st.sampled_from(["raw", "j1939", "tsc1", "tsc1_raw"]),
    st.lists(
        st.tuples(
            st.sampled_from([0.01] * 6 + [0.005, 0.05, 0.2]),
            st.sampled_from([1] * 8 + [0, 2, 3, 7, 15]),
            st.sampled_from(CHECKSUM_CASES),
            st.sampled_from([False] * 9 + [True]),  # a value not available
            st.sampled_from([0] * 15 + [1]),  # now and then another sender
        ),
        min_size=1,
        max_size=50,
    ),
    st.lists(st.integers(0, 20), max_size=4),
)
@settings(max_examples=300, deadline=None, derandomize=True, database=None)  # the reach check cannot flake
def check_both_forms_agree(kind, seq, cuts):
    sp, frames = forms_frames(kind, seq)
    want, a = by_frames(sp, frames)
    got, b = by_columns(sp, frames, cuts)
    assert got == want
    assert a.counts == b.counts and a.by_source == b.by_source
    assert (a.prev, a.prev_t, a.newest_t, a.newest_ok) == (b.prev, b.prev_t, b.newest_t, b.newest_ok)
    assert (a.last_sa, a.seen) == (b.last_sa, b.seen)
    for k in ("counter_not_available", "checksum_not_available", "counter_frozen", "counter_jump", "checksum"):
        if a.counts[k]:
            SEEN_COLUMNS.add(f"{kind} {k}")
    if a.counts["other_sender"]:
        SEEN_COLUMNS.add("other_sender")


def test_the_frame_and_column_forms_agree_and_reach_the_not_available_cases():
    SEEN_COLUMNS.clear()
    check_both_forms_agree()
    assert {
        "frame by frame",
        "other_sender",
        "raw checksum",
        "raw counter_frozen",
        "j1939 counter_not_available",
        "j1939 checksum_not_available",
        "j1939 counter_jump",
        "tsc1 counter_not_available",
        "tsc1 checksum_not_available",
        "tsc1 checksum",
        "tsc1_raw checksum",
        "tsc1_raw counter_frozen",
    } <= SEEN_COLUMNS, SEEN_COLUMNS
    assert not any(k.startswith("raw") and "not_available" in k for k in SEEN_COLUMNS)
