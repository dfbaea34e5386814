"""What a J1939 machine's inputs may carry that is not the drive's controller speaking, through both
engines: a second node sending an input message at the same time (a rogue node, with a valid counter
and checksum), a node sending it filled with "not available", values carrying the error indicator,
frames claiming cmcan's own address, a PDU1 message addressed to another node; and what replay says
of frames no input matched."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st

from cmcan.assemble import dbc_for
from cmcan.can import checksums, codec
from cmcan.can.j1939 import ids, values
from cmcan.monitor.health import ERROR_CODE, NOT_AVAILABLE
from cmcan.monitor.inputs import j1939_decoder
from cmcan.sim.frames import Frames
from tests.test_columnar import assert_same
from tests.test_columnar_buses import both
from tests.test_monitor_j1939 import j1939_cfg, machine_frames

SECONDS = 30.0
FROM_S = 8.0  # the other node starts sending then


@pytest.fixture(scope="module")
def healthy():
    cfg = j1939_cfg()
    frames, plan = machine_frames(cfg, SECONDS, leak_lpm=0.0)
    return cfg, frames, plan


def copies(cfg, frames: Frames, plan, message: str, source: int, edit) -> Frames:
    """Every frame of ``message`` from FROM_S on, once more 1 ms later from address ``source``, its
    payload changed by ``edit(raw values) -> raw values`` and its checksum made right for it."""
    db = dbc_for(cfg)
    msg = db.get_message_by_name(message)
    rows = np.flatnonzero(
        (ids.pgn(frames.arbitration_id) == ids.pgn(msg.frame_id))
        & (frames.timestamp_s >= frames.timestamp_s[0] + FROM_S)
    )
    data = frames.data[rows].copy()
    names = [s.name for s in msg.signals]
    raw = codec.decode_raw(msg, data, names)
    raw = edit(raw)
    lays = codec.message_layouts(msg, names)
    word = np.zeros(len(rows), dtype=object)
    for lay, name in zip(lays, names, strict=True):
        word = [codec.insert(int(w), int(r) & lay.mask, lay) for w, r in zip(word, raw[name], strict=True)]
    data = np.array([list(int(w).to_bytes(8, "little")) for w in word], dtype=np.uint8)
    fid = ids.with_source(frames.arbitration_id[rows], source)
    if message in plan.checksum:
        sig, algorithm = plan.checksum[message]
        data = checksums.seal(algorithm, 8, codec.layout(msg, sig), fid, data)
    extra = Frames(
        timestamp_s=frames.timestamp_s[rows] + 0.001,
        arbitration_id=fid,
        dlc=frames.dlc[rows],
        data=data,
        extended=np.ones(len(rows), dtype=bool),
    )
    merged = Frames(
        timestamp_s=np.concatenate([frames.timestamp_s, extra.timestamp_s]),
        arbitration_id=np.concatenate([frames.arbitration_id, extra.arbitration_id]),
        dlc=np.concatenate([frames.dlc, extra.dlc]),
        data=np.concatenate([frames.data, extra.data]),
        extended=np.concatenate([frames.is_extended(), extra.extended]),
    )
    return merged.select(np.argsort(merged.timestamp_s, kind="stable"))


def levels(mon) -> list[tuple[str, str]]:
    return [(h["to"], h["reason"]) for h in mon.totals.history]


def test_a_second_node_sending_an_input_at_the_same_time_is_a_health_problem_not_a_blend(healthy):
    """A node at 0x05 sends HST_MOTOR alongside the controller at 0x03, with a valid counter and
    checksum and the motor 6 % slower: neither is believed (no false ratio_low); the input is
    erratic, then a fault, the rejected frames counted under both addresses."""
    cfg, frames, plan = healthy

    def slower(raw):
        raw["motor_speed"] = (raw["motor_speed"] * 0.94).astype(np.int64)
        return raw

    rogue = copies(cfg, frames, plan, "HST_MOTOR", 0x05, slower).to_frames()
    a, b = both(cfg, rogue, 997)
    assert_same(a, b)
    mon = a[3]
    assert ("low", "ratio_low") not in levels(mon) and ("fault", "input_implausible") in levels(mon)
    inputs = mon.snapshot()["inputs"]["HST_MOTOR"]
    assert inputs["other_sender"] > 1000 and set(inputs["by_source"]) == {"0x03", "0x05"}
    assert all(v["other_sender"] > 400 for v in inputs["by_source"].values())
    # the same node sending alone (the controller gone quiet, or one that claimed another address) is fine
    alone = [
        f
        for f in rogue
        if ids.source_address(f.arbitration_id) != 0x03 or f.timestamp_s < frames.timestamp_s[0] + FROM_S
    ]
    c, _ = both(cfg, alone, 5000)
    assert c[3].counters["other_sender"] == 0


def test_a_node_sending_an_input_filled_with_not_available_is_no_sample_and_no_fault(healthy):
    """A second address sends HST_MOTOR with its values "not available" (0xFF..): its frames are no
    samples, counted per address, neither a second sender nor a fault; the controller's are used."""
    cfg, frames, plan = healthy

    def unavailable(raw):
        return {k: np.full(len(v), -1, dtype=np.int64) for k, v in raw.items()}  # all ones in every field

    na = copies(cfg, frames, plan, "HST_MOTOR", 0x06, unavailable).to_frames()
    a, b = both(cfg, na, 1999)
    assert_same(a, b)
    mon = a[3]
    base, _ = both(cfg, frames.to_frames(), 5000)
    assert levels(mon) == levels(base[3]) == []
    c = mon.counters
    assert c["not_available"] > 1000 and c["other_sender"] == c["out_of_range"] == 0
    assert c["accepted"] == base[3].counters["accepted"]
    assert mon.snapshot()["inputs"]["HST_MOTOR"]["by_source"] == {"0x06": {"not_available": c["not_available"]}}


def test_an_error_indicator_rejects_the_frame(healthy):
    """The controller says its motor speed is wrong (J1939's error indicator 0xFExx): not a sample
    but a rejected frame, the input implausible, then a fault."""
    cfg, frames, plan = healthy
    db = dbc_for(cfg)
    msg = db.get_message_by_name("HST_MOTOR")
    lay = codec.layout(msg, "motor_speed")
    t = values.thresholds(lay.length, lay.signed)
    assert t is not None
    rows = (ids.pgn(frames.arbitration_id) == ids.pgn(msg.frame_id)) & (
        frames.timestamp_s >= frames.timestamp_s[0] + FROM_S
    )
    data = frames.data.copy()
    cleared = [int.from_bytes(bytes(d), "little") & ~(lay.mask << lay.shift) for d in data[rows]]
    word = [codec.insert(w, t[1], lay) for w in cleared]  # the first error code in the field
    data[rows] = np.array([list(int(w).to_bytes(8, "little")) for w in word], dtype=np.uint8)
    sig, algorithm = plan.checksum["HST_MOTOR"]
    data[rows] = checksums.seal(algorithm, 8, codec.layout(msg, sig), frames.arbitration_id[rows], data[rows])
    bad = replace(frames, data=data).to_frames()
    a, b = both(cfg, bad, 3001)
    assert_same(a, b)
    mon = a[3]
    assert mon.counters["error_code"] == int(rows.sum()) and levels(mon) == [("fault", "input_implausible")]


def test_frames_claiming_cmcans_own_address_are_never_inputs(healthy):
    cfg, frames, plan = healthy
    own = cfg.j1939.source_address
    spoofed = copies(cfg, frames, plan, "HST_MOTOR", own, lambda raw: raw).to_frames()
    a, b = both(cfg, spoofed, 2500)
    assert_same(a, b)
    c = a[3].counters
    assert c["own_address"] == sum(ids.source_address(f.arbitration_id) == own for f in spoofed) > 1000
    assert c["other_sender"] == 0 and levels(a[3]) == []


def test_unknown_identifiers_are_named_by_count(healthy):
    """What a log has that no input matched: the busiest identifiers, with PGN and address."""
    cfg, frames, _ = healthy
    other = [f._replace(arbitration_id=ids.make_id(6, 0xFEF1, 0x00)) for f in frames.to_frames()[:500]]
    a, b = both(cfg, frames.to_frames() + [o._replace(timestamp_s=o.timestamp_s + 0.0005) for o in other], 4000)
    unknown = a[3].snapshot()["unknown_ids"]
    assert unknown == b[3].snapshot()["unknown_ids"]
    assert unknown[0] == {"channel": "can0", "id": "0x18FEF100", "frames": 500, "pgn": 0xFEF1, "source": "0x00"}


def test_a_pdu1_message_is_matched_whatever_its_destination_unless_told(healthy):
    """TSC1-like PDU1 inputs: by default any destination is the message; a configured list narrows it."""
    from cmcan.monitor.inputs import InputMessage

    pgn = 0x0000  # TSC1: PDU1, destination in the identifier
    m = InputMessage(
        frame_id=ids.make_id(3, pgn, 0x03, dest=0xFE), length=8, layouts=(), size=8, roles=(), extended=True, pgn=pgn
    )
    assert m.matches(ids.make_id(3, pgn, 0x03, dest=0x00), True) and m.matches(
        ids.make_id(3, pgn, 0x0B, dest=0xFE), True
    )
    narrow = replace(m, destinations=frozenset({0xFE}))
    assert narrow.matches(ids.make_id(3, pgn, 0x03, dest=0xFE), True)
    assert not narrow.matches(ids.make_id(3, pgn, 0x03, dest=0x00), True)


@given(st.integers(1, 64), st.booleans(), st.data())
def test_the_reserved_codes_one_by_one_and_as_arrays(length, signed, data):
    """J1939-71's indicators by value and over arrays alike, and the decoder's verdict order."""
    t = values.thresholds(length, signed)
    if t is None:
        event("no reserved codes")
        assert signed or length < 2
        return
    top = (1 << length) - 1
    raws = data.draw(
        st.lists(st.one_of(st.integers(0, top), st.integers(max(0, t[0] - 2), top)), min_size=1, max_size=30)
    )
    one = [values.classify(r, t) for r in raws]
    many = values.classify_columns(np.array(raws, dtype=object if length >= 63 else np.int64), t).tolist()
    assert one == many
    for k in set(one):
        event(("valid", "not available", "error")[k])
    assert values.classify(top, t) == values.NOT_AVAILABLE and values.classify(t[1], t) == values.ERROR


def _byte(k: int) -> codec.Layout:
    return codec.Layout(f"v{k}", 8 * k, 8, False, False, 1.0, 0.0, 0.0, 255.0)


def test_the_decoder_takes_the_first_verdict_in_its_order():
    t8 = values.thresholds(8, False)
    dec = j1939_decoder((_byte(0), _byte(1)), 2, ((0, 250), (0, 100)), (t8, t8))
    assert dec(bytes([10, 20])) == (10, 20)
    assert dec(bytes([0xFF, 20])) == NOT_AVAILABLE
    assert dec(bytes([0xFF, 200])) is None  # out of range wins over not available
    assert dec(bytes([0xFE, 200])) == ERROR_CODE  # the error indicator wins over both
    assert dec(bytes([10])) == (10, 0)  # a short frame read as zero-filled


@st.composite
def j1939_frames(draw):
    """A message of 1-4 values of any width, order and sign, its bounds, and frames some of whose
    values sit in the reserved codes."""
    size = draw(st.integers(1, 8))
    lays, bounds, reserved = [], [], []
    for k in range(draw(st.integers(1, 4))):
        length = draw(st.integers(1, 8 * size))
        signed = draw(st.booleans())
        lay = codec.Layout(
            f"v{k}", draw(st.integers(0, 8 * size - length)), length, signed, draw(st.booleans()), 1.0, 0.0, 0.0, 0.0
        )
        lo_r = -(1 << (length - 1)) if signed else 0
        hi_r = (1 << (length - 1)) - 1 if signed else lay.mask
        lays.append(lay)
        if draw(st.integers(0, 3)):  # mostly the whole range: the reserved codes decide
            bounds.append((lo_r, hi_r))
        else:
            lo = draw(st.integers(lo_r, hi_r))
            bounds.append((lo, draw(st.integers(lo - 1, hi_r))))
        reserved.append(values.thresholds(length, signed))
    near_top = st.binary(min_size=size, max_size=size).map(lambda b: bytes(x | 0xF0 for x in b))
    data = draw(st.lists(st.one_of(st.binary(min_size=0, max_size=8), near_top), min_size=1, max_size=20))
    return tuple(lays), size, tuple(bounds), tuple(reserved), data


@given(j1939_frames())
def test_the_decoder_equals_reading_then_classifying(case):
    """The per-frame decoder inlines the bits' reading and the codes' classes; the same verdict as
    :func:`codec.raw_decoder` read first and :func:`values.classify` applied in the documented order."""
    lays, size, bounds, reserved, frames = case
    fast, read = j1939_decoder(lays, size, bounds, reserved), codec.raw_decoder(lays, size)
    for data in frames:
        raws = read(data)
        kinds = [values.classify(r, t) if t is not None else values.VALID for r, t in zip(raws, reserved, strict=True)]
        outside = any(
            k == values.VALID and not lo <= r <= hi for r, k, (lo, hi) in zip(raws, kinds, bounds, strict=True)
        )
        if values.ERROR in kinds:
            want = ERROR_CODE
        elif outside:
            want = None
        elif values.NOT_AVAILABLE in kinds:
            want = NOT_AVAILABLE
        else:
            want = raws
        assert fast(data) == want
        event(
            {ERROR_CODE: "error", NOT_AVAILABLE: "not available"}.get(want, "values")
            if want is not None
            else "out of range"
        )


def test_the_kernel_filter_of_a_pdu1_input_lets_any_destination_through_unless_told():
    from cmcan.daemon.loop import can_filters
    from cmcan.monitor.inputs import InputMessage

    def passes(flt: dict, fid: int) -> bool:
        return fid & flt["can_mask"] == flt["can_id"] & flt["can_mask"]

    m = InputMessage(
        frame_id=ids.make_id(3, 0, 0x03, dest=0xFE), length=8, layouts=(), size=8, roles=(), extended=True, pgn=0
    )
    (f,) = can_filters([m], "")
    assert all(passes(f, ids.make_id(p, 0, sa, dest=d)) for p in (0, 3, 7) for sa in (0, 3) for d in (0, 0x27, 0xFE))
    assert not passes(f, ids.make_id(3, 0x0100, 0x03, dest=0xFE))  # another PGN
    (g,) = can_filters([replace(m, destinations=frozenset({0x27}), sources=frozenset({3}))], "")
    assert passes(g, ids.make_id(6, 0, 3, dest=0x27)) and not passes(g, ids.make_id(6, 0, 3, dest=0xFE))
    assert not passes(g, ids.make_id(6, 0, 4, dest=0x27))


def test_a_message_sent_once_a_second_is_judged_with_a_window_that_fits_it(healthy):
    """Vehicle Fluids (the oil temperature) sent once a second, as J1939-71 has it: with its cycle time
    known (here ``messages.VF.cycle_ms``) the temperature gets a 2 s window and one sample suffices,
    so points are judged (both engines alike); without it, every point would stay warming_up."""
    cfg, frames, _ = healthy
    vf = ids.pgn(dbc_for(cfg).get_message_by_name("VF").frame_id)
    t0 = float(frames.timestamp_s[0])
    is_vf = ids.pgn(frames.arbitration_id) == vf
    keep = ~is_vf | (np.round((frames.timestamp_s - t0) * 10).astype(np.int64) % 10 == 0)
    slow = frames.select(np.flatnonzero(keep)).to_frames()
    assert 25 <= sum(ids.pgn(f.arbitration_id) == vf for f in slow) <= 31
    told = replace(cfg, messages={**cfg.messages, "VF": replace(cfg.message("VF"), cycle_ms=1000.0)})
    a, b = both(told, slow, 1500)
    assert_same(a, b)
    gates = {int(g) for g in a[0].gate}
    assert 0 in gates and a[3].counters["evaluated"] > 100  # judged
    stuck, _ = both(cfg, slow, 5000)  # the DBC's 100 ms: five samples a second wanted
    assert stuck[3].counters["evaluated"] == 0
