"""cmcan as a J1939 node (J1939-81 address claim, J1939-21 requests, J1939-73 DM2/DM3/DM11): the pure
state machines, the core stage in both replay engines over logs with other nodes' claims and requests,
and an independent decoder (pretty_j1939) reading what cmcan sends."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from dataclasses import replace

import pytest
import yaml
from hypothesis import event, given, settings
from hypothesis import strategies as st

from cmcan import config as cfgmod
from cmcan.assemble import assemble
from cmcan.can.frame import Frame, FrameColumns
from cmcan.can.j1939 import claim as ac
from cmcan.can.j1939 import dm1, ids, transport
from cmcan.can.j1939 import requests as rq
from cmcan.can.j1939.name import Name
from cmcan.monitor.node import ClearTrust
from cmcan.monitor.totals import StateError, Totals
from cmcan.replay import FrameCollector, TimelineCollector, replay, replay_columns
from cmcan.schema import SchemaError
from tests.conftest import ROOT
from tests.test_columnar import assert_same
from tests.test_j1939 import pretty
from tests.test_monitor_j1939 import j1939_cfg, machine_frames

SA = 0x8C
TOOL = 0xF9  # a service tool (J1939 reserves 249 for the first off-board diagnostic tool)
OURS = Name(identity_number=1001, manufacturer_code=2000, function=130, industry_group=3)


def name_of(**kw) -> Name:
    return replace(OURS, **kw)


def req(t: float, sa: int, dest: int, pgn: int, channel: str = "can0") -> Frame:
    fid = ids.make_id(rq.REQUEST_PRIORITY, rq.PGN_REQUEST, sa, dest)
    return Frame(t, channel, fid, True, False, False, False, rq.request_data(pgn))


def tp_cm(t: float, sa: int, dest: int, data: bytes, channel: str = "can0") -> Frame:
    fid = ids.make_id(transport.TP_PRIORITY, transport.PGN_TP_CM, sa, dest)
    return Frame(t, channel, fid, True, False, False, False, data)


def trusting(cfg, *addresses: int, names: tuple[int, ...] = ()):
    """``cfg`` with DM3/DM11 trusted from these source addresses (and NAMEs)."""
    return replace(cfg, j1939=replace(cfg.j1939, clears=ClearTrust(addresses, names)))


def claim_frame(t: float, sa: int, name: Name | int, channel: str = "can0") -> Frame:
    value = name if isinstance(name, int) else name.value
    fid = ids.make_id(6, rq.PGN_ADDRESS_CLAIMED, sa, ids.GLOBAL_ADDRESS)
    return Frame(t, channel, fid, True, False, False, False, value.to_bytes(8, "little"))


# -- the NAME -------------------------------------------------------------------------------------------


@given(
    st.integers(0, (1 << 21) - 1),
    st.integers(0, 2047),
    st.integers(0, 255),
    st.integers(0, 7),
    st.booleans(),
    st.integers(0, 7),
    st.integers(0, 31),
    st.integers(0, 127),
    st.integers(0, 15),
)
def test_a_name_round_trips_through_its_64_bits(ident, mfr, func, ig, arb, ecu, fi, vs, vsi):
    n = Name(ident, mfr, func, ig, arb, ecu, fi, vs, vsi)
    assert Name.from_bytes(n.to_bytes()) == n and Name.from_value(n.value) == n
    assert (n.value >> 63) == int(arb) and n.value & 0x1FFFFF == ident  # the fields where J1939-81 puts them


def test_a_name_field_out_of_range_is_refused():
    with pytest.raises(ValueError, match="identity_number"):
        Name(1 << 21, 0, 0)


# -- the claim's state machine --------------------------------------------------------------------------


def machine(arbitrary: bool = False, addresses: tuple[int, ...] = ()) -> ac.AddressClaim:
    return ac.AddressClaim(ac.ClaimParams(name_of(arbitrary_address_capable=arbitrary), SA, addresses, "can0"))


def test_a_claim_stands_250_ms_after_it_and_a_higher_name_is_answered_by_claiming_again():
    m = machine()
    (f,) = m.start(10.0)
    assert (
        ids.source_address(f.arbitration_id) == SA
        and f.data == OURS.to_bytes()
        and ids.destination(f.arbitration_id) == 255
    )
    assert not m.may_send(10.2) and m.may_send(10.25) and m.state == ac.CLAIMED
    again = m.on_claim(11.0, SA, OURS.value + 1)  # a higher NAME on our address: we win
    assert [ids.source_address(x.arbitration_id) for x in again] == [SA] and m.may_send(11.0)


def test_a_lower_name_takes_the_address_cannot_claim_and_silence():
    m = machine()
    m.start(0.0)
    out = m.on_claim(1.0, SA, OURS.value - 1)
    assert [ids.source_address(x.arbitration_id) for x in out] == [ids.NULL_ADDRESS] and out[0].data == OURS.to_bytes()
    assert m.state == ac.LOST and not m.may_send(5.0)
    # a Request for Address Claimed to all: Cannot Claim after the NAME's pseudo-random delay (0..153 ms)
    (cc,) = m.on_request(2.0, ids.GLOBAL_ADDRESS)
    assert ids.source_address(cc.arbitration_id) == ids.NULL_ADDRESS and 2.0 <= cc.timestamp_s <= 2.153
    assert m.events[-1].state == ac.LOST and m.events[-1].by_name == OURS.value - 1
    # the link comes back: claim again (the winner still there takes it again from us)
    assert m.start(9.0, "link back")[0].timestamp_s == 9.0 and m.state == ac.CLAIMING


def test_arbitrary_address_capable_moves_to_a_free_address_and_goes_on():
    m = machine(True, (0x8D, 0x8E, 0x8F))
    m.on_claim(0.0, 0x8D, 5)  # someone with a low NAME holds 0x8D
    m.start(1.0)
    out = m.on_claim(2.0, SA, OURS.value - 1)
    assert [ids.source_address(x.arbitration_id) for x in out] == [0x8E] and m.address == 0x8E
    assert not m.may_send(2.2) and m.may_send(2.25)
    # none left: the last one goes too
    m.on_claim(3.0, 0x8F, 1)
    out = m.on_claim(4.0, 0x8E, 2)
    assert ids.source_address(out[0].arbitration_id) == ids.NULL_ADDRESS and m.state == ac.LOST


def test_the_250_ms_run_from_when_the_claim_was_on_the_bus():
    """A daemon behind its bus sends the claim it made for frame time 2.0 at 2.08: nothing else
    before 2.33 (J1939-81 counts from the claim on the wire). Other frames, another address's claim
    or a claim that already stands move nothing."""
    m = machine(True, (0x8D, 0x8E))
    m.start(1.0)
    (moved,) = m.on_claim(2.0, SA, OURS.value - 1)
    m.on_air(2.01, claim_frame(2.01, 0x8E, OURS))  # not the address claimed
    m.on_air(2.02, Frame(2.02, "can0", moved.arbitration_id, True, False, False, False, bytes(8)))  # not our NAME
    assert m.settle_at == 2.25
    m.on_air(2.08, moved)
    assert not m.may_send(2.3) and m.may_send(2.33)
    m.on_air(3.0, moved)  # it stands: a repeat of the claim (an answer to a request) moves nothing
    assert m.may_send(3.0)


@given(
    st.lists(
        st.tuples(st.floats(0, 0.5), st.integers(0x8A, 0x90), st.integers(0, 1 << 64 - 1), st.booleans()), max_size=30
    ),
    st.booleans(),
)
@settings(max_examples=200, deadline=None)
def test_the_claim_keeps_its_rules_whatever_the_bus_says(steps, arbitrary):
    """Whatever claims and requests come: cmcan only ever sends Address Claimed from the address it
    holds or Cannot Claim from 254; it holds an address only while no lower NAME claimed it after
    cmcan's last claim; a node that is not arbitrary address capable never moves."""
    m = machine(arbitrary, (0x8D, 0x8E))
    t = 0.0
    m.start(t)
    last_lower: dict[int, float] = {}
    for dt, sa, name, is_request in steps:
        t += dt
        held = m.address
        out = m.on_request(t, ids.GLOBAL_ADDRESS) if is_request else m.on_claim(t, sa, name)
        for f in out:
            src = ids.source_address(f.arbitration_id)
            assert src in (m.address, ids.NULL_ADDRESS) and f.data == m.p.name.to_bytes()
        if not is_request and name < m.name_value:
            last_lower[sa] = t
            if sa == held:
                event("lost to a lower NAME")
                assert m.address != held
        if m.address is not None and m.address != SA:
            event("moved")
            assert arbitrary
        if m.state == ac.LOST:
            event("lost")


# -- requests --------------------------------------------------------------------------------------


def test_request_and_acknowledgment_bytes():
    assert rq.request_data(65227) == bytes((0xCB, 0xFE, 0x00)) and rq.requested_pgn(b"\xcb\xfe\x00") == 65227
    assert rq.requested_pgn(b"\x01\x02") is None
    a = rq.decode_ack(rq.ack_data(rq.NACK, 65262, TOOL))
    assert (a.control, a.address, a.pgn, a.group_function) == (rq.NACK, TOOL, 65262, 0xFF)


def test_a_requester_gets_one_answer_per_pgn_per_interval():
    lim = rq.RequestLimit(0.3)
    assert lim.allow(0.0, TOOL, 1) and not lim.allow(0.1, TOOL, 1) and lim.allow(0.1, TOOL, 2)
    assert lim.allow(0.31, TOOL, 1) and lim.refused == 1


# -- the node in the core, over logs with other nodes' claims and requests, both engines ---------------


def both(cfg, frames, chunk, totals=None):
    out = {}
    for engine in ("streaming", "columnar"):
        mon = assemble(cfg, totals=Totals.from_dict(totals.to_dict()) if totals else None).monitor
        tl, fr = TimelineCollector(), FrameCollector()
        if engine == "streaming":
            s = replay(mon, frames, [tl, fr])
        else:
            chunks = [FrameColumns.from_frames(frames[i : i + chunk]) for i in range(0, len(frames), chunk)]
            s = replay_columns(mon, chunks, [tl, fr])
        out[engine] = (tl.timeline, fr.frames_out, s, mon)
    return out["streaming"], out["columnar"]


def merged(frames: list[Frame], extra: list[Frame]) -> list[Frame]:
    return sorted(frames + extra, key=lambda f: f.timestamp_s)


@pytest.fixture(scope="module")
def leak40():
    cfg = j1939_cfg()
    f, _ = machine_frames(cfg, 40.0)
    return cfg, f.to_frames()


def from_cmcan(out: list[Frame], pgn: int, source: int = SA) -> list[Frame]:
    return [
        f
        for f in out
        if f.extended and ids.pgn(f.arbitration_id) == pgn and ids.source_address(f.arbitration_id) == source
    ]


def dm_payloads(out: list[Frame], pgn: int) -> list[tuple[float, bytes]]:
    """Each message of ``pgn`` cmcan sent: in one frame, by BAM, or by RTS/CTS (to whomever)."""
    r, c = transport.BamReceiver(), transport.ConnectionReceiver()
    got = []
    for f in out:
        if ids.source_address(f.arbitration_id) != SA:
            continue
        to_one = ids.destination(f.arbitration_id) != ids.GLOBAL_ADDRESS
        if ids.pgn(f.arbitration_id) == pgn:
            got.append((f.timestamp_s, f.data))
            continue
        done = c.feed(f.arbitration_id, f.data)[1] if to_one else r.feed(f.arbitration_id, f.data)
        if done is not None and done[1] == pgn:
            got.append((f.timestamp_s, done[2]))
    return got


@pytest.fixture(scope="module")
def service(leak40):
    """A service tool at 0xF9 (it claims its address; the configuration trusts it to clear) asks cmcan
    for what a workshop asks; cmcan started with two previously active DTCs in its state; a leak from
    12 s raises the low warning. DM2 of two DTCs goes by RTS/CTS to the tool, which takes it at once."""
    cfg, frames = leak40
    cfg = trusting(cfg, TOOL)
    t0 = frames[0].timestamp_s
    tool = Name(identity_number=7, manufacturer_code=11, function=129, industry_group=0)
    extra = [
        claim_frame(t0 + 0.5, TOOL, tool),
        req(t0 + 1.0, TOOL, ids.GLOBAL_ADDRESS, rq.PGN_ADDRESS_CLAIMED),
        req(t0 + 2.0, TOOL, SA, dm1.PGN_DM1),
        req(t0 + 2.5, TOOL, SA, 65262),  # engine temperature: not cmcan's
        req(t0 + 2.6, TOOL, ids.GLOBAL_ADDRESS, 65263),  # to all, not cmcan's: nothing
        req(t0 + 3.03, TOOL, SA, 65312),  # CM_RATIO
        req(t0 + 3.08, TOOL, SA, 65312),  # again within 300 ms: not answered
        req(t0 + 3.2, TOOL, 0x00, dm1.PGN_DM1),  # to the engine: not for cmcan
        req(t0 + 4.0, TOOL, SA, rq.PGN_DM2),
        tp_cm(t0 + 4.02, TOOL, SA, transport.cts_data(255, 1, rq.PGN_DM2)),
        tp_cm(t0 + 4.04, TOOL, SA, transport.eoma_data(10, rq.PGN_DM2)),
        req(t0 + 5.0, TOOL, SA, rq.PGN_DM3),
        req(t0 + 6.0, TOOL, SA, rq.PGN_DM2),
        req(t0 + 22.0, TOOL, SA, rq.PGN_DM11),
    ]
    totals = Totals(dtc_occurrences={"520193:9": 3, "520193:2": 1})
    return cfg, merged(frames, extra), totals, t0


@pytest.mark.parametrize("chunk", [257, 100_000])
def test_a_service_tool_gets_its_answers_in_both_engines(service, chunk):
    cfg, frames, totals, t0 = service
    a, b = both(cfg, frames, chunk, totals)
    assert_same(a, b)
    out, mon = a[1], a[3]
    # the claim first, then nothing else from 0x8C within 250 ms
    assert out[0].arbitration_id == ids.make_id(6, rq.PGN_ADDRESS_CLAIMED, SA) and out[0].timestamp_s == t0
    assert all(f.timestamp_s >= t0 + 0.25 for f in out[1:])
    claims = from_cmcan(out, rq.PGN_ADDRESS_CLAIMED)
    assert [f.timestamp_s - t0 for f in claims] == [0.0, 1.0]  # at the start, and for the request
    acks = [(f.timestamp_s - t0, rq.decode_ack(f.data)) for f in from_cmcan(out, rq.PGN_ACK)]
    assert all(ids.destination(f.arbitration_id) == 255 for f in from_cmcan(out, rq.PGN_ACK))
    assert [(round(t, 3), a.control, a.pgn, a.address) for t, a in acks] == [
        (2.5, rq.NACK, 65262, TOOL),
        (5.0, rq.ACK, rq.PGN_DM3, TOOL),
        (22.0, rq.ACK, rq.PGN_DM11, TOOL),
    ]
    ratio = from_cmcan(out, 65312)
    answer = [f for f in ratio if abs(f.timestamp_s - (t0 + 3.03)) < 1e-9]
    # the answer: the last CM_RATIO with the alive counter's next value (bits 56-59), which moves on
    before = [f for f in ratio if f.timestamp_s < t0 + 3.03][-1].data
    after = next(f for f in ratio if f.timestamp_s > t0 + 3.03).data
    assert len(answer) == 1 and answer[0].data[:7] == before[:7] and answer[0].data[7] >> 4 == before[7] >> 4
    alive = [d[7] & 0xF for d in (before, answer[0].data, after)]
    assert alive == [alive[0], (alive[0] + 1) % 16, (alive[0] + 2) % 16]
    assert not [f for f in ratio if abs(f.timestamp_s - (t0 + 3.08)) < 1e-9]
    # DM2 before DM3: both previously active DTCs with their counts (two DTCs: RTS/CTS to the tool,
    # nothing to all); after: none
    dm2 = dm_payloads(out, rq.PGN_DM2)
    assert [round(t - t0, 2) for t, _ in dm2] == [4.02, 6.0]  # (the message whole with its last packet)
    tp = [f for f in out if ids.pdu_format(f.arbitration_id) in (0xEB, 0xEC) and f.timestamp_s < t0 + 5]
    assert {ids.destination(f.arbitration_id) for f in tp} == {TOOL} and tp[0].data[0] == transport.CM_RTS
    assert mon.node.counts["connections_sent"] == 1 and not mon.node.connections
    assert [(d.spn, d.fmi, d.occurrence) for d in dm1.decode(dm2[0][1])[1]] == [(520193, 2, 1), (520193, 9, 3)]
    assert dm1.decode(dm2[1][1])[1] == []
    # DM11 at 22 s while low: the DTC's count goes, the DTC is active again at once (count 1: the
    # leak is still there), the amber lamp stays on, the warning never says ok
    dm1s = [(t - t0, dm1.decode(p)) for t, p in dm_payloads(out, dm1.PGN_DM1)]
    before = [d for t, (_, d) in dm1s if 20 < t < 22]
    after = [(lamps, d) for t, (lamps, d) in dm1s if 22 <= t < 23]
    assert before and before[-1] and before[-1][0].fmi in (17, 18) and before[-1][0].occurrence >= 1
    assert after and after[0][1] and after[0][1][0].fmi in (17, 18) and after[0][1][0].occurrence == 1
    assert all(lamps.amber_warning == dm1.Lamp.ON for lamps, _ in after)
    clears = mon.totals.dtc_clears
    assert [(c["kind"], c["by_address"], c["by_name"]) for c in clears] == [
        ("dm3", TOOL, f"0x{Name(7, 11, 129).value:016X}"),
        ("dm11", TOOL, f"0x{Name(7, 11, 129).value:016X}"),
    ]
    assert clears[0]["cleared"] == ["520193:2", "520193:9"] and clears[1]["t_s"] == t0 + 22.0
    levels = [(h["from"], h["to"]) for h in mon.totals.history]
    assert ("low", "ok") not in levels and levels[-1] == ("ok", "low")
    assert (mon.node.counts["clears_dm3"], mon.node.counts["clears_dm11"], mon.node.counts["clears_refused"]) == (
        1,
        1,
        0,
    )
    assert mon.counters["node_frames"] == 14


def test_a_lower_name_on_cmcans_address_silences_it(leak40):
    cfg, frames = leak40
    t0 = frames[0].timestamp_s
    rival = Name(identity_number=1, manufacturer_code=1, function=130, industry_group=3)  # lower than cmcan's
    extra = [claim_frame(t0 + 10.0, SA, rival), req(t0 + 11.0, TOOL, ids.GLOBAL_ADDRESS, rq.PGN_ADDRESS_CLAIMED)]
    a, b = both(cfg, merged(frames, extra), 500)
    assert_same(a, b)
    out = a[1]
    assert max(f.timestamp_s for f in out if ids.source_address(f.arbitration_id) == SA) < t0 + 10.0
    cannot = [f for f in out if ids.source_address(f.arbitration_id) == ids.NULL_ADDRESS]
    assert round(cannot[0].timestamp_s - t0, 3) == 10.0 and len(cannot) == 2
    assert t0 + 11.0 <= cannot[1].timestamp_s <= t0 + 11.153
    assert a[3].node.state == ac.LOST


def test_arbitrary_address_capable_moves_and_sends_from_its_new_address(leak40):
    cfg, frames = leak40
    j = cfg.j1939
    cfg = replace(cfg, j1939=replace(j, name=replace(j.name, arbitrary_address_capable=True), addresses=(0x8D, 0x8E)))
    t0 = frames[0].timestamp_s
    rival = Name(identity_number=1, manufacturer_code=1, function=130, industry_group=3)
    extra = [claim_frame(t0 + 0.1, 0x8D, 3), claim_frame(t0 + 10.0, SA, rival)]
    a, b = both(cfg, merged(frames, extra), 700)
    assert_same(a, b)
    out = a[1]
    srcs = {ids.source_address(f.arbitration_id) for f in out if f.timestamp_s > t0 + 10.3}
    assert srcs == {0x8E}
    assert not [
        f
        for f in out
        if t0 + 10.0 <= f.timestamp_s < t0 + 10.25 and ids.pgn(f.arbitration_id) != rq.PGN_ADDRESS_CLAIMED
    ]
    assert a[3].node.address == 0x8E and a[3].node.state == ac.CLAIMED


@given(
    st.lists(
        st.tuples(
            st.floats(0.0, 40.0),
            st.sampled_from([0x80, TOOL, SA, 0x00]),
            st.sampled_from([SA, 255, 0x00]),
            st.sampled_from(
                [rq.PGN_ADDRESS_CLAIMED, dm1.PGN_DM1, rq.PGN_DM2, rq.PGN_DM3, rq.PGN_DM11, 65312, 65262, -1]
            ),
        ),
        min_size=1,
        max_size=12,
    ),
    st.integers(50, 3000),
)
@settings(max_examples=12, deadline=None)
def test_any_mix_of_claims_and_requests_replays_the_same_in_both_engines(leak40, mix, chunk):
    cfg, frames = leak40
    t0 = frames[0].timestamp_s
    extra = []
    for dt, sa, dest, pgn in mix:
        if pgn == -1:
            extra.append(claim_frame(t0 + dt, dest if dest != 255 else sa, sa * 7919 + 1))
            event("a claim")
        else:
            extra.append(req(t0 + dt, sa, dest, pgn))
            event(f"request for {pgn}")
    a, b = both(cfg, merged(frames, extra), chunk)
    assert_same(a, b)


# -- an independent decoder reads what cmcan sends --------------------------------------------------


def test_pretty_j1939_reads_cmcans_name_and_dm2(service, tmp_path):
    """pretty_j1939 decodes Address Claimed (the NAME's fields) and DM2 (over BAM) as cmcan meant them.
    It shows nothing of an Acknowledgment (it takes PGN 59392 for transport): the VM's test has the
    kernel's J1939 stack receive cmcan's ACK and NACK instead."""
    cfg, frames, totals, t0 = service
    mon = assemble(cfg, totals=Totals.from_dict(totals.to_dict())).monitor
    fr = FrameCollector()
    replay(mon, frames[: next(i for i, f in enumerate(frames) if f.timestamp_s > t0 + 4.5)], [fr])
    mine = [
        f
        for f in fr.frames_out
        if ids.pgn(f.arbitration_id) in (rq.PGN_ADDRESS_CLAIMED, rq.PGN_ACK, rq.PGN_DM2, 0xEC00, 0xEB00)
    ]
    got = pretty(mine, tmp_path)
    acl = [m for m in got if str(m.get("PGN", "")).startswith("Address Claimed")]
    assert acl, got
    n = cfg.j1939.name
    assert acl[0]["Identity Number"] == n.identity_number
    assert acl[0]["Manufacturer Code"].startswith(f"{n.manufacturer_code} ")
    assert acl[0]["Function ID"].startswith(f"{n.function} ") and acl[0]["Industry Group"].startswith(
        f"{n.industry_group} "
    )
    assert acl[0]["Arbitrary Address Capable"] == 0 and acl[0]["SA"].endswith("(140)")
    dm2 = [m for m in got if m.get("PGN") == "DM2(65227)"]
    assert len(dm2) == 1
    assert sorted(m for k, m in dm2[0].items() if k.startswith("DTC ")) == [
        "SPN 520193 (Unknown), FMI 2, OC 1",
        "SPN 520193 (Unknown), FMI 9, OC 3",
    ]


# -- configuration and state --------------------------------------------------------------------------


def test_check_refuses_an_arbitrary_name_without_addresses_and_addresses_without_one(tmp_path):
    raw_yaml = (cfgmod.Path(__file__).resolve().parents[1] / "config" / "j1939-example.yaml").read_text()
    import yaml

    raw = yaml.safe_load(raw_yaml)
    raw["dbc"] = str(cfgmod.Path(__file__).resolve().parents[1] / "dbc" / "j1939-example.dbc")
    raw["j1939"]["name"]["arbitrary_address_capable"] = True
    with pytest.raises(SchemaError, match=r"j1939\.addresses: missing"):
        cfgmod.from_dict(raw, "x.yaml", tmp_path)
    raw["j1939"]["name"]["arbitrary_address_capable"] = False
    raw["j1939"]["addresses"] = [0x8D]
    with pytest.raises(SchemaError, match="arbitrary_address_capable: is false"):
        cfgmod.from_dict(raw, "x.yaml", tmp_path)
    raw["j1939"]["addresses"] = []
    raw["j1939"]["name"]["identity_number"] = 1 << 21
    with pytest.raises(SchemaError, match="identity_number"):
        cfgmod.from_dict(raw, "x.yaml", tmp_path)


def test_the_clears_survive_a_restart_and_a_bad_record_is_refused():
    t = Totals()
    t.record_clear("dm11", 5.0, 5.0, TOOL, None, ["520192:17"])
    back = Totals.from_dict(t.to_dict())
    assert back.dtc_clears == t.dtc_clears
    d = t.to_dict()
    d["dtc_clears"][0]["kind"] = "dm99"
    with pytest.raises(StateError, match="dtc_clears"):
        Totals.from_dict(d)


# -- several drives on one gateway ---------------------------------------------------------------------


def drive_config(tmp_path, name: str, address: int, identity: int, instance: int, state: str):
    import yaml

    root = cfgmod.Path(__file__).resolve().parents[1]
    raw = yaml.safe_load((root / "config" / "j1939-example.yaml").read_text())
    raw["dbc"] = str(root / "dbc" / "j1939-example.dbc")
    raw["state"]["directory"] = str(tmp_path / state)
    raw["j1939"]["source_address"] = address
    raw["j1939"]["name"].update(identity_number=identity, function_instance=instance)
    p = tmp_path / name
    p.write_text(yaml.safe_dump(raw))
    return p


def test_check_refuses_two_drives_that_would_send_the_same_identifiers_or_claim_one_address(tmp_path):
    from tests.conftest import run_cli

    left = drive_config(tmp_path, "left.yaml", 0x8C, 1001, 0, "left")
    right = drive_config(tmp_path, "right.yaml", 0x8C, 1001, 0, "right")
    r = run_cli("check", "--config", str(left), "--config", str(right))
    assert r.returncode == 78, r.stderr
    assert "both claim J1939 address 0x8C on can0" in r.stderr and "both send identifier 0x18FF208C" in r.stderr
    assert "the same J1939 NAME" in r.stderr
    drive_config(tmp_path, "right.yaml", 0x8D, 1002, 1, "right")
    r = run_cli("check", "--config", str(tmp_path), "--json")  # a directory of drive configurations
    assert r.returncode == 0, r.stdout + r.stderr
    import json

    got = json.loads(r.stdout)
    assert [d["sends"][0] for d in got["drives"]] == ["0x18FF208C", "0x18FF208D"]


def test_the_channel_probe_says_who_holds_cmcans_address():
    from cmcan.daemon.claimprobe import judge

    mine = OURS.value
    assert judge(mine, SA, {SA: mine}, set())["state"] == "claimed"
    assert judge(mine, SA, {0x10: 5}, {mine})["state"] == "lost"
    assert judge(mine, SA, {0x10: 5}, set())["state"] == "free"
    taken = judge(mine, SA, {SA: mine - 1}, set(), (0x8D,))
    assert taken["state"] == "taken" and "move within j1939.addresses" in taken["text"]
    assert judge(mine, SA, {SA: mine + 1}, set())["state"] == "contested"


def test_clears_and_claim_changes_become_uplink_events():
    from cmcan.uplink.records import claim_entry, clear_entry

    t = Totals()
    t.record_clear("dm3", 7.0, 7.0, TOOL, OURS.value, ["520193:9"])
    e = clear_entry(t.dtc_clears[0])
    assert (e.kind, e.t_s, e.body["type"], e.body["by_address"], e.body["cleared"]) == (
        "event",
        7.0,
        "dtc_clear",
        TOOL,
        ["520193:9"],
    )
    m = machine()
    m.start(1.0)
    m.on_claim(2.0, SA, OURS.value - 1)
    bodies = [claim_entry(x, m.name_value).body for x in m.events]
    assert [(b["state"], b["address"]) for b in bodies] == [("claiming", SA), ("lost", None)]
    assert bodies[-1]["by_name"] == f"0x{OURS.value - 1:016X}"


def test_the_daemon_claims_on_a_silent_bus_and_writes_its_node_file(tmp_path):
    """The real ``cmcan run`` of the J1939 example machine on a bus nobody else sends on: it claims at
    its first idle step, says so in the journal and the node file. Before: its first idle step, with
    no claim made yet, ended the daemon with an internal error."""
    raw = yaml.safe_load((ROOT / "config" / "j1939-example.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "j1939-example.dbc")
    raw["bus"].update(interface="virtual", channel="silent-j1939")
    raw["state"]["directory"] = str(tmp_path)
    cfg = tmp_path / "j.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    proc = subprocess.Popen(
        [sys.executable, "-m", "cmcan", "-v", "run", "--config", str(cfg)],
        cwd=ROOT, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    node_file = tmp_path / "j1939-node.json"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None and '"claimed"' not in read_if_there(node_file):
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "internal error" not in err and "address 0x8C claimed" in err, err
    node = json.loads(node_file.read_text())
    assert node["state"] == "claimed" and node["address"] == SA, node


def read_if_there(path) -> str:
    try:
        return path.read_text()
    except FileNotFoundError:
        return ""
