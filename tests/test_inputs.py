"""Matching frames to input messages (monitor/inputs.py): channels, 11- and 29-bit, J1939 PGN and
source addresses; a pure function of the frame's fields."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from cmcan.can.j1939 import ids
from cmcan.monitor.inputs import Channels, InputMessage, Matcher, overlap


def msg(name: str, frame_id: int, extended=False, pgn=None, sources=None, channel="", dests=frozenset()):
    return InputMessage(frame_id, 8, (), 8, (), name, channel, extended, pgn, sources, dests)


PUMP = 0x0CFF1003  # proprietary B PGN 0xFF10 from 0x03


def test_channel_names_resolve_by_the_stated_rules():
    one = Channels(("vcan0",), (False,))
    assert one.resolve("vcan0") == 0 and one.resolve("can0") == 0 and one.resolve("") == 0
    two = Channels(("can0", "can1"), (False, True))
    assert two.resolve("can1") == 1 and two.resolve("can7") is None and two.resolve("") is None
    aliased = Channels(("vcan0", "vcan1"), (False, False), {"can0": "vcan0", "can1": "vcan1"})
    assert aliased.resolve("can1") == 1 and aliased.resolve("vcan0") == 0 and aliased.resolve("can2") is None
    # with an alias given, a single-channel configuration takes only what the aliases name
    strict = Channels(("vcan0",), (False,), {"can1": "vcan0"})
    assert strict.resolve("can1") == 0 and strict.resolve("can0") is None and strict.resolve("vcan0") == 0


@given(st.integers(0, 7), st.integers(0, 255), st.sampled_from([None, frozenset({3}), frozenset({3, 4})]))
def test_j1939_matches_on_pgn_and_sources_whatever_the_priority(prio, sa, sources):
    m = msg("HST_PUMP", PUMP, True, 0xFF10, sources)
    can_id = ids.make_id(prio, 0xFF10, sa)
    assert m.matches(can_id, True) == (sources is None or sa in sources)
    assert not m.matches(can_id, False)  # a standard frame is never a 29-bit message
    assert not m.matches(ids.make_id(prio, 0xFF11, sa), True)


@given(st.integers(0, 255), st.integers(0, 255))
def test_pdu1_messages_match_their_destination(sa, da):
    m = msg("PROP_A", ids.make_id(6, 0xEF00, 0x03, 0x8C), True, 0xEF00, None, dests=frozenset({0x8C}))
    assert m.matches(ids.make_id(6, 0xEF00, sa, da), True) == (da == 0x8C)


@given(st.integers(0, 0x7FF), st.integers(0, ids.MAX_ID), st.booleans())
def test_plain_messages_match_exactly(std_id, ext_id, extended):
    a, b = msg("A", std_id), msg("B", ext_id, True)
    assert a.matches(std_id, False) and not a.matches(std_id, True)
    assert b.matches(ext_id, True) and not b.matches(ext_id ^ 1, True)


def test_matcher_keeps_channels_apart():
    chans = Channels(("can0", "can1"), (False, False))
    a = msg("A", 0x100, channel="can0")
    b = msg("B", 0x100, channel="can1")
    m = Matcher([a, b], chans)
    assert m.match(0, 0x100, False) is a and m.match(1, 0x100, False) is b and m.match(1, 0x101, False) is None


def test_overlap_finds_ambiguous_mappings():
    any_src = msg("A", PUMP, True, 0xFF10, None)
    only3 = msg("B", PUMP, True, 0xFF10, frozenset({3}))
    only4 = msg("C", PUMP | 1, True, 0xFF10, frozenset({4}))
    assert overlap(any_src, only3) and not overlap(only3, only4)
    assert overlap(msg("D", PUMP, True), any_src)  # an exact 29-bit id that the PGN rule also takes
    assert not overlap(msg("E", 0x100), msg("F", 0x100, True))
