"""J1939-21 connection mode (RTS/CTS) as cmcan sends a directed answer, DM3/DM11 only from whom the
configuration trusts, and a fresh alive counter in answers to requests for CM messages: the pure
state machines, the node, and the core in both replay engines."""

from __future__ import annotations

from dataclasses import replace

import pytest
from hypothesis import event, find, given, settings
from hypothesis import strategies as st

from cmcan import config as cfgmod
from cmcan.can.frame import Frame
from cmcan.can.j1939 import dm1, ids, transport
from cmcan.can.j1939 import requests as rq
from cmcan.monitor.node import ClearTrust, Node, NodeParams
from cmcan.monitor.totals import Totals
from cmcan.monitor.warnings import Level, Thresholds, WarningMachine
from cmcan.schema import SchemaError
from tests.test_columnar import assert_same
from tests.test_j1939_node import SA, TOOL, both, claim_frame, dm_payloads, merged, req, tp_cm, trusting

PGN = rq.PGN_DM2
PAYLOAD = bytes(range(40))  # 6 packets
N = 6


# -- the originator as a state machine -------------------------------------------------------------------

STEP = st.one_of(
    st.tuples(st.just("cts"), st.integers(0, 4), st.integers(0, N + 1)),
    st.tuples(st.just("eoma"), st.just(0), st.just(0)),
    st.tuples(st.just("abort"), st.integers(1, 9), st.just(0)),
    st.tuples(st.just("other_pgn"), st.integers(1, 4), st.just(1)),
    st.tuples(st.just("wait"), st.just(0), st.just(0)),
)
STEPS = st.lists(st.tuples(st.sampled_from([0.01, 0.3, 0.6, 1.0, 1.2, 1.3]), STEP), max_size=25)


def run(steps: list) -> tuple[transport.Sender, list[tuple[float, str, Frame]]]:
    """The sender through ``steps`` (a gap, then what the receiver does); every frame it sends, with
    what it answered."""
    s = transport.Sender(PGN, PAYLOAD, SA, TOOL, "can0")
    t = 0.0
    log = [(t, "start", f) for f in s.start(t)]
    for dt, (kind, a, b) in steps:
        t += dt
        log += [(t, kind, f) for f in receiver_does(s, t, kind, a, b)]
    return s, log


def receiver_does(s: transport.Sender, t: float, kind: str, a: int, b: int) -> list[Frame]:
    """One step of the receiver (STEP) at ``t``: the sender's answer."""
    if kind == "cts":
        return s.on_cm(t, transport.cts_data(a, b, PGN))
    if kind == "eoma":
        return s.on_cm(t, transport.eoma_data(len(PAYLOAD), PGN))
    if kind == "abort":
        return s.on_cm(t, transport.abort_data(a, PGN))
    if kind == "other_pgn":
        return s.on_cm(t, transport.cts_data(a, b, PGN + 1))
    return s.expire(t)


@given(STEPS)
@settings(max_examples=400, deadline=None)
def test_the_sender_follows_j1939_21_whatever_the_receiver_does(steps):
    """Every frame goes from cmcan to the requester; packets only in answer to a CTS, exactly the
    window it asks for (cut at the last packet); a hold, a CTS for another message, an EndOfMsgAck
    before the end send nothing; a deadline missed (T3 after the RTS or a window, T4 after a hold)
    aborts with "timeout" at the next moment the sender hears of; nothing after the end."""
    s = transport.Sender(PGN, PAYLOAD, SA, TOOL, "can0")
    t, closed, deadline = 0.0, False, transport.T3_S
    sent_all = False
    assert [f.data for f in s.start(t)] == [transport.rts_data(PGN, len(PAYLOAD))]
    for dt, (kind, a, b) in steps:
        t += dt
        state_before = s.state
        out = receiver_does(s, t, kind, a, b)
        for f in out:
            assert f.timestamp_s == t and ids.source_address(f.arbitration_id) == SA
            assert ids.destination(f.arbitration_id) == TOOL and ids.priority(f.arbitration_id) == 7
        if closed:
            assert out == [] and not s.open
            continue
        if t >= deadline:  # too late, whatever came
            assert [f.data for f in out] == [transport.abort_data(transport.ABORT_TIMEOUT, PGN)]
            assert s.outcome == "timeout"
            event("timeout")
            closed = True
            continue
        if kind == "cts" and a == 0:
            event("hold")
            assert out == [] and s.state == transport.HOLD
            deadline = t + transport.T4_S
        elif kind == "cts" and not 1 <= b <= N:
            event("bad next packet")
            assert [f.data[:2] for f in out] == [bytes((transport.CM_ABORT, transport.ABORT_BAD_SEQUENCE))]
            closed = True
        elif kind == "cts" and s.state == transport.ABORTED:
            event("too many retransmits")
            assert [f.data[:2] for f in out] == [bytes((transport.CM_ABORT, transport.ABORT_RETRANSMITS))]
            assert s.retransmits > transport.MAX_RETRANSMITS
            closed = True
        elif kind == "cts":
            want = transport.packets(PAYLOAD)[b - 1 : min(N, b + a - 1)]
            assert [f.data for f in out] == want and all(ids.pdu_format(f.arbitration_id) == 0xEB for f in out)
            sent_all = sent_all or b + a - 1 >= N
            event("window" if b + a - 1 < N else "last window")
            deadline = t + transport.T3_S
        elif kind == "abort":
            assert out == [] and s.outcome == f"aborted by receiver (reason {a})"
            event("aborted by the receiver")
            closed = True
        elif kind == "eoma" and state_before == transport.WAIT_EOMA:
            assert out == [] and s.outcome == "sent" and sent_all
            event("sent")
            closed = True
        else:
            assert out == [] and s.open
        assert s.open == (not closed)


@pytest.mark.parametrize(
    "outcome",
    ["sent", "timeout", "aborted by receiver", "cmcan aborted (reason 5)", "cmcan aborted (reason 7)", "hold"],
)
def test_the_generated_receivers_reach_every_interesting_case(outcome):
    """The strategy above reaches each way a connection goes (the property test is not vacuous)."""

    def reached(steps):
        s, _ = run(steps)
        return s.holds > 0 if outcome == "hold" else (s.outcome or "").startswith(outcome)

    found = find(STEPS, reached, settings=settings(max_examples=5000, database=None, derandomize=True))
    assert reached(found)


def test_a_windowed_transfer_with_a_hold_and_a_retransmission():
    """The receiver takes 2 packets per CTS, holds once, asks for packet 3 again: the whole message."""
    s, log = run(
        [
            (0.05, ("cts", 2, 1)),
            (0.05, ("cts", 0, 0)),
            (0.9, ("cts", 2, 3)),
            (0.05, ("cts", 1, 3)),
            (0.05, ("cts", 4, 5)),
            (0.05, ("eoma", 0, 0)),
        ]
    )
    seqs = [f.data[0] for _, _, f in log if ids.pdu_format(f.arbitration_id) == 0xEB]
    assert seqs == [1, 2, 3, 4, 3, 5, 6] and s.outcome == "sent" and (s.holds, s.retransmits) == (1, 1)


def test_a_hold_longer_than_t4_and_silence_after_the_rts_time_out():
    s, log = run([(0.1, ("cts", 0, 0)), (1.2, ("wait", 0, 0))])
    assert s.outcome == "timeout" and log[-1][2].data[:2] == bytes((255, 3))
    s, _ = run([(1.2, ("wait", 0, 0))])
    assert s.open  # within T3
    s, _ = run([(1.3, ("wait", 0, 0))])
    assert s.outcome == "timeout"


def test_the_receiver_for_tests_reassembles_in_windows():
    payload = bytes(range(100))
    s = transport.Sender(PGN, payload, SA, TOOL)
    r = transport.ConnectionReceiver(window=3)
    pending = s.start(0.0)
    done, t = None, 0.0
    while pending:
        f = pending.pop(0)
        back, got = r.feed(f.arbitration_id, f.data)
        done = got or done
        for data in back:
            t += 0.01
            pending += s.on_cm(t, data)
    assert done == (SA, PGN, payload) and s.outcome == "sent" and s.windows == 5


# -- the node: trusted clears, RTS/CTS answers, a fresh counter -------------------------------------------


def node(trust: ClearTrust | None = None) -> Node:
    n = Node(NodeParams(SA, "can0", None, frozenset(), 0.3, trust or ClearTrust()))
    n.start(0.0)
    return n


class FakeDm:
    """What the node takes of the DM1 producer: its parameters, active DTCs and counts."""

    def __init__(self, counts: dict[str, int]) -> None:
        from cmcan.monitor.diagnostics import Dm1Params

        self.p = Dm1Params(520192, 520193, 96.0, 104.0, 0.5, 10, SA, channel="can0")
        self.active: list[str] = []
        self.totals = Totals(dtc_occurrences=counts)

    def answer(self, pgn: int, t: float) -> list[Frame]:
        return [Frame(t, "can0", ids.make_id(6, pgn, SA), True, False, False, False, b"bam")]


def acks(frames: list[Frame]) -> list[tuple[int, int, int]]:
    return [(a.control, a.pgn, a.address) for a in (rq.decode_ack(f.data) for f in frames)]


@pytest.mark.parametrize("kind", [rq.PGN_DM3, rq.PGN_DM11])
def test_clears_only_from_a_trusted_address_or_name(kind):
    dm = FakeDm({})
    n = node()  # the default: nobody
    out, clear = n.handle(req(1.0, TOOL, SA, kind), dm)
    assert clear is None and acks(out) == [(rq.ACCESS_DENIED, kind, TOOL)]
    out, clear = n.handle(req(2.0, TOOL, 255, kind), dm)
    assert clear is None and out == []  # to all: silence
    assert n.counts["clears_refused"] == 2
    n = node(ClearTrust((TOOL,)))
    out, clear = n.handle(req(1.0, TOOL, SA, kind), dm)
    assert clear is not None and clear.by_address == TOOL and acks(out) == [(rq.ACK, kind, TOOL)]
    out, clear = n.handle(req(1.0, 0x80, SA, kind), dm)  # another address: not trusted
    assert clear is None and acks(out) == [(rq.ACCESS_DENIED, kind, 0x80)]
    # a NAME is trusted where it claimed its address; where it went, the old address is not
    n = node(ClearTrust((), (0xA00C81045A20021B,)))
    n.handle(claim_frame(0.5, 0x81, 0xA00C81045A20021B), dm)
    assert n.handle(req(1.0, 0x81, SA, kind), dm)[1] is not None
    n.handle(claim_frame(1.5, 0x82, 0xA00C81045A20021B), dm)
    assert n.handle(req(2.0, 0x81, SA, kind), dm)[1] is None
    assert n.handle(req(2.0, 0x82, 255, kind), dm)[1] is not None
    assert n.counts[f"clears_{'dm3' if kind == rq.PGN_DM3 else 'dm11'}"] == 2 and n.counts["clears_refused"] == 1


@given(st.integers(0, 255), st.sampled_from([SA, 255]), st.sampled_from([rq.PGN_DM3, rq.PGN_DM11]))
def test_never_from_the_null_address_or_cmcans_own_whatever_the_configuration(sa, dest, kind):
    n = node(ClearTrust(tuple(range(254))))
    n.names[sa] = 1
    _, clear = n.handle(req(1.0, sa, dest, kind), FakeDm({}))
    assert (clear is not None) == (sa <= 253 and sa != SA)


def test_the_configuration_names_who_may_clear_and_never_cmcan_itself(tmp_path):
    path = cfgmod.Path(__file__).resolve().parents[1] / "config" / "j1939-example.yaml"
    raw = cfgmod.load_yaml(path)
    raw["dbc"] = str(path.parents[1] / "dbc" / "j1939-example.dbc")
    assert cfgmod.from_dict(raw, "x.yaml", tmp_path).j1939.clears == ClearTrust()
    raw["j1939"]["clears"] = {"trusted_addresses": [0xF9], "trusted_names": [0xA00C81045A20021B]}
    cfg = cfgmod.from_dict(raw, "x.yaml", tmp_path)
    assert cfg.j1939.clears == ClearTrust((0xF9,), (0xA00C81045A20021B,))
    raw["j1939"]["clears"] = {"trusted_addresses": [0x8C]}
    with pytest.raises(SchemaError, match=r"j1939\.clears\.trusted_addresses: includes cmcan's own address"):
        cfgmod.from_dict(raw, "x.yaml", tmp_path)
    raw["j1939"]["clears"] = {"trusted_addresses": [254]}
    with pytest.raises(SchemaError, match=r"trusted_addresses\[0\]"):
        cfgmod.from_dict(raw, "x.yaml", tmp_path)


def test_a_directed_dm2_longer_than_a_frame_goes_by_rts_cts_and_one_to_all_by_bam():
    dm = FakeDm({"520193:9": 3, "520193:2": 1, "520192:17": 2})
    n = node()
    out, _ = n.handle(req(1.0, TOOL, 255, PGN), dm)
    assert [f.data for f in out] == [b"bam"]  # the producer's BAM to all
    out, _ = n.handle(req(2.0, TOOL, SA, PGN), dm)
    assert len(out) == 1 and out[0].data[0] == transport.CM_RTS and ids.destination(out[0].arbitration_id) == TOOL
    assert n.deadline_s == 2.0 + transport.T3_S
    # a second request while the connection is open: cannot respond
    assert acks(n.handle(req(2.5, TOOL, SA, PGN), dm)[0]) == [(rq.CANNOT_RESPOND, PGN, TOOL)]
    # a CTS to another node is not cmcan's; the tool's CTS gets the packets, its EndOfMsgAck ends it
    assert n.handle(tp_cm(2.6, TOOL, 0x10, transport.cts_data(255, 1, PGN)), dm)[0] == []
    out, _ = n.handle(tp_cm(2.7, TOOL, SA, transport.cts_data(255, 1, PGN)), dm)
    assert [f.data[0] for f in out] == [1, 2] and out[0].timestamp_s == 2.7  # 14 bytes: 2 packets
    n.handle(tp_cm(2.8, TOOL, SA, transport.eoma_data(14, PGN)), dm)
    assert n.counts["connections_sent"] == 1 and not n.connections
    # silence after an RTS: the abort at the first moment the node hears of after T3
    n.handle(req(5.0, TOOL, SA, PGN), dm)
    assert n.expire(6.0) == [] and [f.data[:2] for f in n.expire(6.3)] == [bytes((255, 3))]
    assert n.counts["connections_timed_out"] == 1 and n.describe()["connections_open"] == 0
    # an RTS to cmcan (it takes no messages): refused
    (ab,) = n.handle(tp_cm(7.0, TOOL, SA, transport.rts_data(65000, 20)), dm)[0]
    assert ab.data[:2] == bytes((255, transport.ABORT_RESOURCES)) and transport.cm_pgn(ab.data) == 65000


def test_a_request_from_the_null_address_is_answered_to_all():
    dm = FakeDm({"520193:9": 3, "520193:2": 1})
    out, _ = node().handle(req(1.0, ids.NULL_ADDRESS, SA, PGN), dm)
    assert [f.data for f in out] == [b"bam"]


# -- DM11 and the warning ---------------------------------------------------------------------------------


def test_dm11_keeps_a_condition_the_filtered_ratio_still_shows_and_the_debounce_going():
    th = Thresholds(debounce_s=2.0)
    m = WarningMachine(th, condition=Level.LOW)
    m.clear(95.0)  # still below 98 %: stays raised
    assert m.level == Level.LOW
    m.clear(98.2)  # in the hysteresis: the latched warning goes
    assert m.level == Level.OK
    m = WarningMachine(th)
    m.below_s = 1.5  # a debounce under way goes on
    m.clear(95.0)
    assert m.below_s == 1.5 and m.level == Level.OK
    m = WarningMachine(th, condition=Level.HIGH)
    m.clear(None)  # nothing shows it: ok
    assert m.level == Level.OK


# -- the core, both engines -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def leak40():
    from tests.test_monitor_j1939 import j1939_cfg, machine_frames

    cfg = j1939_cfg()
    f, _ = machine_frames(cfg, 40.0)
    return cfg, f.to_frames()


def test_dm11_once_a_minute_from_anyone_leaves_the_warning_on(leak40):
    """The attack of the issue: DM11 from 254, from cmcan's own address and from a node nobody
    trusts, over and over, while the leak is there: the warning stays low and the amber lamp on."""
    cfg, frames = leak40
    t0 = frames[0].timestamp_s
    extra = [req(t0 + t, sa, 255, rq.PGN_DM11) for t in (20.0, 25.0, 30.0, 35.0) for sa in (254, SA, 0x80)]
    a, b = both(trusting(cfg, TOOL), merged(frames, extra), 333)
    assert_same(a, b)
    mon = a[3]
    assert mon.totals.dtc_clears == [] and mon.node.counts["clears_refused"] == 12
    assert [(h["from"], h["to"]) for h in mon.totals.history][-1] == ("ok", "low")
    lamps = [dm1.decode(p)[0].amber_warning for t, p in dm_payloads(a[1], dm1.PGN_DM1) if t > t0 + 20]
    assert lamps and all(x == dm1.Lamp.ON for x in lamps)


def test_a_trusted_dm11_while_the_leak_is_there_raises_it_again_at_once(leak40):
    cfg, frames = leak40
    t0 = frames[0].timestamp_s
    extra = [req(t0 + 25.0, TOOL, SA, rq.PGN_DM11)]
    a, b = both(trusting(cfg, TOOL), merged(frames, extra), 777)
    assert_same(a, b)
    mon = a[3]
    assert [c["kind"] for c in mon.totals.dtc_clears] == ["dm11"]
    after = [dm1.decode(p) for t, p in dm_payloads(a[1], dm1.PGN_DM1) if t0 + 25.0 <= t < t0 + 26.5]
    assert after and all(lamps.amber_warning == dm1.Lamp.ON and d and d[0].occurrence == 1 for lamps, d in after)
    tl = a[0]
    levels = {int(x) for t, x in zip(tl.t_s.tolist(), tl.level.tolist(), strict=True) if t > t0 + 25.0}
    assert levels == {Level.LOW}


@given(
    st.lists(
        st.tuples(
            st.floats(0.0, 40.0),
            st.sampled_from([TOOL, 0x80, 254]),
            st.sampled_from(["dm2", "dm1", "cts", "hold", "eoma", "abort", "dm11", "ratio"]),
            st.integers(0, 4),
        ),
        min_size=1,
        max_size=14,
    ),
    st.integers(50, 3000),
)
@settings(max_examples=10, deadline=None)
def test_any_mix_of_connections_and_clears_replays_the_same_in_both_engines(leak40, mix, chunk):
    cfg, frames = leak40
    t0 = frames[0].timestamp_s
    totals = Totals(dtc_occurrences={"520193:9": 3, "520193:2": 1})
    extra = []
    for dt, sa, what, n in mix:
        t = t0 + dt
        if what in ("dm1", "dm2", "dm11", "ratio"):
            pgn = {"dm1": dm1.PGN_DM1, "dm2": PGN, "dm11": rq.PGN_DM11, "ratio": 65312}[what]
            extra.append(req(t, sa, SA, pgn))
        elif what == "cts" or what == "hold":
            extra.append(tp_cm(t, sa, SA, transport.cts_data(0 if what == "hold" else n + 1, n + 1, PGN)))
        elif what == "eoma":
            extra.append(tp_cm(t, sa, SA, transport.eoma_data(10, PGN)))
        else:
            extra.append(tp_cm(t, sa, SA, transport.abort_data(n, PGN)))
        event(what)
    a, b = both(trusting(cfg, TOOL), merged(frames, extra), chunk, totals)
    assert_same(a, b)


def test_the_node_describes_its_trust_and_counts():
    n = node(ClearTrust((TOOL,), (5,)))
    d = n.describe()
    assert d["trusted_addresses"] == ["0xF9"] and d["trusted_names"] == ["0x0000000000000005"]
    assert {"clears_dm3", "clears_dm11", "clears_refused", "connections_sent", "connections_timed_out"} <= set(d)
    assert replace(ClearTrust([1], [2])) == ClearTrust((1,), (2,))


def test_a_reload_that_changes_who_may_clear_keeps_the_claim(leak40):
    from cmcan.assemble import assemble

    cfg, frames = leak40
    old = assemble(cfg).monitor
    old.feed(frames[0])
    new = assemble(trusting(cfg, TOOL)).monitor
    new.take_over(old)
    assert new.node is old.node and new.node.p.trust == ClearTrust((TOOL,)) and new.node.started
