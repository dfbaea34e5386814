"""Input health per message stream (monitor/health.py): the rules of its docstring, checked on random
frame sequences against a reference written from those rules, with the interesting cases reached."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.codec import Layout
from cmcan.monitor import health
from cmcan.monitor.health import HealthSpec, Stream

COUNTER = Layout("ctr", 56, 4, False, False, 1.0, 0.0, 0.0, 15.0)  # byte 8, bits 1-4
TIMEOUT = 0.1


def frame(counter: int, checksum_ok: bool) -> bytes:
    # byte 1 carries whether the (test's) checksum holds
    return bytes([1 if checksum_ok else 0, 0, 0, 0, 0, 0, 0, counter & 0x0F])


def spec(max_step: int) -> HealthSpec:
    return HealthSpec(counter=COUNTER, max_step=max_step, checksum=lambda _id, d: d[0] == 1, timeout_s=TIMEOUT)


def reference(events, max_step):
    """The module docstring's steps 1-2, restated."""
    prev, prev_t, out = None, -math.inf, []
    for t, c, ok in events:
        if not ok:
            out.append(health.CHECKSUM)
            continue
        v = health.OK
        if prev is not None and t - prev_t <= TIMEOUT:
            d = (c - prev) % 16
            v = health.COUNTER_FROZEN if d == 0 else health.COUNTER_JUMP if d > max_step else health.OK
        prev, prev_t = c, t
        out.append(v)
    return out


# A sender mostly counting on, sometimes repeating, skipping or jumping, pausing, or corrupt.
steps = st.lists(
    st.tuples(
        st.sampled_from([0.01] * 6 + [0.005, 0.05, 0.2]),  # time since the previous frame
        st.sampled_from([1] * 8 + [0, 2, 3, 7, 15]),  # counter step
        st.sampled_from([True] * 9 + [False]),  # checksum holds
    ),
    min_size=1,
    max_size=60,
)
SEEN: set[str] = set()


@given(steps, st.integers(1, 3))
@settings(max_examples=300, deadline=None)
def check_stream_against_the_rules(seq, max_step):
    s = Stream(spec(max_step))
    t, c, events = 100.0, 3, []
    for dt, step, ok in seq:
        t += dt
        c = (c + step) % 16
        events.append((t, c, ok))
    want = reference(events, max_step)
    for (t, c, ok), w in zip(events, want, strict=True):
        got = s.check(t, 0x123, frame(c, ok))
        assert got == w
        s.note(t, got)
        SEEN.add(health.REASONS[got])
        # right after the frame: erratic exactly when it was rejected
        assert s.erratic(t) == (got != health.OK)
        assert not s.silent(t) and s.silent(t + TIMEOUT + 1e-6)
        assert not s.erratic(t + TIMEOUT + 1e-6)  # an old rejection is a timeout, not erratic
        if w == health.OK and events.index((t, c, ok)) > 0:
            prev = events[events.index((t, c, ok)) - 1]
            if prev[0] < t - TIMEOUT:
                SEEN.add("restart after a timeout")


def test_stream_follows_its_rules_and_reaches_every_case():
    SEEN.clear()
    check_stream_against_the_rules()
    assert {"ok", "checksum", "counter_frozen", "counter_jump", "restart after a timeout"} <= SEEN, SEEN


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
