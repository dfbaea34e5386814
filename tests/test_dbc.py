"""The DBC contract: strict loading, documented signals, named nodes, round trips."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.can import codec
from cmcan.roles import DEFAULT_INPUTS

INPUT_IDS = {0x100, 0x101, 0x102, 0x103}


def all_signals(db):
    return [(m, s) for m in db.messages for s in m.signals]


def test_loads_strictly_with_expected_messages(db):
    names = {m.name for m in db.messages}
    assert {
        "PUMP_STATUS",
        "LOOP_PRESSURE",
        "MOTOR_STATUS",
        "OIL_STATUS",
        "CM_RATIO",
        "CM_SPEED",
        "CM_FLOW",
        "CM_WARNING",
        "CM_BASELINE",
        "CM_PROGNOSIS",
    } == names
    assert all(not m.is_extended_frame and m.frame_id <= 0x7FF for m in db.messages)
    assert {m.frame_id for m in db.messages if "DRIVE_CTRL" in m.senders} == INPUT_IDS


def test_every_signal_has_unit_range_scaling_comment(db):
    for m, s in all_signals(db):
        assert s.unit, f"{m.name}.{s.name} has no unit"
        assert s.minimum is not None and s.maximum is not None, f"{m.name}.{s.name} has no range"
        assert s.scale > 0
        assert s.comment, f"{m.name}.{s.name} has no comment"
        assert s.receivers, f"{m.name}.{s.name} has no receivers"
    for m in db.messages:
        assert m.comment and m.senders and m.cycle_time


def test_senders_and_receivers_are_declared_nodes(db):
    nodes = {n.name for n in db.nodes}
    assert nodes == {"DRIVE_CTRL", "CMCAN", "DISPLAY", "TELEMATICS"}
    for m, s in all_signals(db):
        assert set(m.senders) <= nodes and set(s.receivers) <= nodes


def test_outputs_carry_what_the_contract_names(db):
    ratio = {s.name: s for s in db.get_message_by_name("CM_RATIO").signals}
    assert ratio["cm_ratio_raw_pct"].scale == 0.01 and ratio["cm_ratio_filt_pct"].scale == 0.01
    assert ratio["extra_leakage_lpm"].unit == "l/min"
    warn = db.get_message_by_name("CM_WARNING")
    choices = warn.get_signal_by_name("warning_level").choices
    assert {str(v) for v in choices.values()} == {"ok", "low", "high", "fault"}


def test_cm_gate_table_is_the_gate_enum(db):
    from cmcan.monitor.gating import Gate

    choices = db.get_message_by_name("CM_RATIO").get_signal_by_name("cm_gate").choices
    assert {int(k): str(v) for k, v in choices.items()} == {int(g): g.name.lower() for g in Gate}


def test_each_quantity_has_its_output_message(db):
    from cmcan.roles import OUTPUT_SIGNALS, QUANTITY_OUTPUT

    for key in QUANTITY_OUTPUT.values():
        msg = db.get_message_by_name({"cm_speed": "CM_SPEED", "cm_flow": "CM_FLOW"}[key])
        assert set(OUTPUT_SIGNALS[key]) <= {s.name for s in msg.signals}


def test_input_mapping_points_at_real_signals(db):
    for msg, sig in DEFAULT_INPUTS.values():
        db.get_message_by_name(msg).get_signal_by_name(sig)


def signal_values(m, s):
    lo, hi = s.minimum, s.maximum
    return st.floats(min_value=lo, max_value=hi, allow_nan=False, allow_infinity=False)


@pytest.mark.parametrize(
    "name",
    ["PUMP_STATUS", "LOOP_PRESSURE", "MOTOR_STATUS", "OIL_STATUS", "CM_RATIO", "CM_SPEED", "CM_FLOW", "CM_WARNING"],
)
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_every_signal_round_trips_within_its_resolution(db, name, data):
    m = db.get_message_by_name(name)
    values = {s.name: data.draw(signal_values(m, s), label=s.name) for s in m.signals}
    frame = m.encode(values, strict=True)
    back = m.decode(frame, decode_choices=False)
    for s in m.signals:
        assert abs(back[s.name] - values[s.name]) <= s.scale / 2 + 1e-9 * max(1.0, abs(values[s.name]))


@pytest.mark.parametrize(
    "name",
    ["PUMP_STATUS", "LOOP_PRESSURE", "MOTOR_STATUS", "OIL_STATUS", "CM_RATIO", "CM_SPEED", "CM_FLOW", "CM_WARNING"],
)
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_vectorized_codec_equals_cantools(db, name, data):
    m = db.get_message_by_name(name)
    n = data.draw(st.integers(1, 6))
    cols = {s.name: np.array([data.draw(signal_values(m, s)) for _ in range(n)]) for s in m.signals}
    frames = codec.encode(m, cols)
    for i in range(n):
        row = {k: float(codec.quantize(m, k, v[i : i + 1])[0]) for k, v in cols.items()}
        assert bytes(frames[i]) == m.encode(row, strict=False)
    decoded = codec.decode(m, frames)
    for i in range(n):
        ref = m.decode(bytes(frames[i]), decode_choices=False)
        for k in cols:
            assert decoded[k][i] == pytest.approx(ref[k], abs=1e-9)


@settings(max_examples=100, deadline=None)
@given(payload=st.binary(min_size=8, max_size=8))
def test_vectorized_decode_of_arbitrary_payloads_equals_cantools(db, payload):
    for m in db.messages:
        ours = codec.decode(m, np.frombuffer(payload, dtype=np.uint8).reshape(1, 8))
        ref = m.decode(payload, decode_choices=False)
        for k, v in ref.items():
            assert ours[k][0] == pytest.approx(v, abs=1e-9)


def test_out_of_range_values_saturate_instead_of_failing(db):
    m = db.get_message_by_name("PUMP_STATUS")
    frames = codec.encode(m, {"pump_speed_rpm": np.array([-5.0, 1e9]), "pump_disp_cc": np.array([0.0, 0.0])})
    back = codec.decode(m, frames)
    assert list(back["pump_speed_rpm"]) == [0.0, 8000.0]


@pytest.mark.parametrize(
    "name",
    ["PUMP_STATUS", "LOOP_PRESSURE", "MOTOR_STATUS", "OIL_STATUS", "CM_RATIO", "CM_SPEED", "CM_FLOW", "CM_WARNING"],
)
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_per_frame_encoder_and_decoder_equal_cantools(db, name, data):
    m = db.get_message_by_name(name)
    values = {s.name: data.draw(signal_values(m, s), label=s.name) for s in m.signals}
    frame = codec.frame_encoder(codec.message_layouts(m), codec.frame_bytes(m), m.length)(values)
    assert frame == m.encode(values, strict=True)
    names = [s.name for s in m.signals]
    raws = codec.raw_decoder(codec.message_layouts(m, names), codec.frame_bytes(m))(frame)
    ref = m.decode(frame, decode_choices=False, scaling=False)
    assert raws == tuple(ref[n] for n in names)


@pytest.mark.parametrize("name", ["PUMP_STATUS", "LOOP_PRESSURE", "MOTOR_STATUS", "OIL_STATUS", "CM_RATIO"])
@settings(max_examples=100, deadline=None)
@given(payload=st.binary(min_size=8, max_size=8))
def test_checked_decoder_gives_raws_and_flags_out_of_range(db, name, payload):
    m = db.get_message_by_name(name)
    names = [s.name for s in m.signals]
    fn = codec.checked_decoder(codec.message_layouts(m, names), codec.frame_bytes(m))
    ref = m.decode(payload, decode_choices=False, scaling=True)
    raw = m.decode(payload, decode_choices=False, scaling=False)
    in_range = all(s.minimum <= ref[s.name] <= s.maximum for s in m.signals)
    got = fn(payload)
    if not in_range:
        assert got is None
    else:
        assert got == tuple(raw[n] for n in names)


# -- the one bit extractor on layouts the shipped DBC does not have: Motorola, signed, odd lengths ----


@st.composite
def layouts(draw):
    """A message of 1..8 bytes with up to 4 signals, each in its own run of bytes, Intel or Motorola,
    at a random bit offset and length within it, signed or not, with a random scale and offset."""
    from cantools.database.can import Message, Signal
    from cantools.database.conversion import BaseConversion

    length = draw(st.integers(1, 8))
    cuts = sorted(draw(st.sets(st.integers(1, length - 1), max_size=min(3, length - 1)))) if length > 1 else []
    regions = list(zip([0, *cuts], [*cuts, length], strict=True))
    signals = []
    for k, (b0, b1) in enumerate(regions):
        bits = 8 * (b1 - b0)
        n = draw(st.integers(1, min(bits, 32)))
        off = draw(st.integers(0, bits - n))
        big = draw(st.booleans())
        if big:  # Motorola: the MSB in sawtooth numbering, counted from the region's first bit
            pos = 8 * b0 + off  # big-endian linear position of the MSB
            start = 8 * (pos // 8) + 7 - pos % 8
        else:
            start = 8 * b0 + off
        signals.append(
            Signal(
                name=f"s{k}",
                start=start,
                length=n,
                byte_order="big_endian" if big else "little_endian",
                is_signed=draw(st.booleans()) and n > 1,
                conversion=BaseConversion.factory(
                    scale=draw(st.sampled_from([1, 0.1, 0.25, 0.5, 2.0, 0.001])),
                    offset=draw(st.sampled_from([0, -40, 100.5, -1000])),
                ),
            )
        )
    return Message(frame_id=0x123, name="RANDOM", length=length, signals=signals, strict=True)


@settings(max_examples=300, deadline=None)
@given(msg=layouts(), data=st.data())
def test_bit_extractor_equals_cantools_on_random_layouts(msg, data):
    payloads = [data.draw(st.binary(min_size=msg.length, max_size=msg.length)) for _ in range(3)]
    names = [s.name for s in msg.signals]
    per_frame = codec.raw_decoder(codec.message_layouts(msg, names), codec.frame_bytes(msg))
    arr = np.frombuffer(b"".join(payloads), dtype=np.uint8).reshape(len(payloads), msg.length)
    vec = codec.decode_raw(msg, arr, names)
    for i, p in enumerate(payloads):
        ref = msg.decode(p, decode_choices=False, scaling=False)
        assert per_frame(p) == tuple(ref[n] for n in names)
        assert [int(vec[n][i]) for n in names] == [ref[n] for n in names]
    # encoding: the one bit inserter against cantools, per frame and vectorized
    raws = {s.name: msg.decode(payloads[0], decode_choices=False, scaling=False)[s.name] for s in msg.signals}
    phys = {s.name: raws[s.name] * s.scale + s.offset for s in msg.signals}
    want = msg.encode(raws, scaling=False, strict=False, padding=False)
    assert codec.frame_encoder(codec.message_layouts(msg), codec.frame_bytes(msg), msg.length)(phys) == want
    assert bytes(codec.encode(msg, {k: np.array([v]) for k, v in phys.items()})[0]) == want


@settings(max_examples=500, deadline=None)
@given(
    st.integers(1, 20),
    st.booleans(),
    st.sampled_from([1, 0.1, 0.25, 0.05, 0.01, 0.125, -0.5, 2.0, 0.001, 5]),
    st.sampled_from([0, -40, -320, 100.5, -50]),
    st.floats(-1e6, 1e6),
    st.floats(-1e6, 1e6),
    st.data(),
)
def test_raw_bounds_are_the_range_check_in_floating_point(n, signed, scale, offset, a, b, data):
    lo_v, hi_v = min(a, b), max(a, b)
    lay = codec.Layout("x", 0, n, signed, False, scale, offset, lo_v, hi_v)
    lo, hi = codec.raw_bounds(lay)
    r_min, r_max = (-(1 << (n - 1)), (1 << (n - 1)) - 1) if signed else (0, (1 << n) - 1)
    for r in {r_min, r_max, data.draw(st.integers(r_min, r_max)), lo, hi, lo - 1, hi + 1}:
        if r_min <= r <= r_max:
            assert (lo <= r <= hi) == (lo_v <= r * scale + offset <= hi_v)


@pytest.mark.parametrize("name", ["HST_PUMP", "HST_MOTOR", "HST_LOOP_PRESSURE", "VF", "CM_RATIO", "DM1"])
@settings(max_examples=100, deadline=None)
@given(payload=st.binary(min_size=8, max_size=8))
def test_checked_decoder_on_the_j1939_example_equals_cantools(name, payload):
    from cmcan.can.dbc import load_dbc
    from tests.conftest import ROOT

    m = load_dbc(ROOT / "dbc" / "j1939-example.dbc").get_message_by_name(name)
    names = [s.name for s in m.signals]
    ref = m.decode(payload, decode_choices=False, scaling=True)
    raw = m.decode(payload, decode_choices=False, scaling=False)
    got = codec.checked_decoder(codec.message_layouts(m, names), codec.frame_bytes(m))(payload)
    in_range = all(s.minimum <= ref[s.name] <= s.maximum for s in m.signals)
    assert got == (tuple(raw[n] for n in names) if in_range else None)


@settings(max_examples=400, deadline=None)
@given(
    st.integers(1, 32),
    st.booleans(),
    st.sampled_from([1, 0.1, 0.25, 0.05, 0.01, 0.125, -0.5, 2.0, 0.001, 5]),
    st.sampled_from([0, -40, -320, 100.5, -50]),
    st.none() | st.floats(-1e6, 1e6),
    st.none() | st.floats(-1e6, 1e6),
    st.data(),
)
def test_physical_range_is_what_the_encoder_sends_back(n, signed, scale, offset, a, b, data):
    """Every value of :func:`cmcan.can.dbc.physical_range` survives cmcan's encoder and decoder within half
    a step; three steps beyond it, a value comes back saturated or wrapped."""
    from cantools.database.can import Signal
    from cantools.database.conversion import BaseConversion

    from cmcan.can.dbc import physical_range

    if a is not None and b is not None and a > b:  # (min and max of -0.0 and 0.0 would both be -0.0)
        a, b = b, a
    sig = Signal("x", 0, n, is_signed=signed and n > 1, conversion=BaseConversion.factory(scale=scale, offset=offset))
    sig.minimum, sig.maximum = a, b
    lay = codec.Layout(
        "x", 0, n, bool(sig.is_signed), False, scale, offset, -np.inf if a is None else a, np.inf if b is None else b
    )
    lo, hi = physical_range(sig)
    if lo > hi:  # the DBC's range lies outside what the bits hold: nothing to carry
        return

    def sent(v: float) -> float:
        return codec.extract(codec.insert(0, codec.to_raw(lay, v), lay), lay) * scale + offset

    step = abs(scale)
    # (a range of one value may be 0.0 to -0.0, which hypothesis refuses as bounds)
    inside = data.draw(st.floats(lo, hi)) if lo < hi else lo
    for v in (lo, hi, inside):
        assert abs(sent(v) - v) <= step / 2 + 1e-9 * max(1.0, abs(v)), v
    for v in (lo - 3 * step, hi + 3 * step):
        assert abs(sent(v) - v) > step, v
