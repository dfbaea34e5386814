"""Every signal width a DBC allows (1 to 64 bits), signed and unsigned, Intel and Motorola, decoded
exactly by the per-frame and the array extractors, in classic frames and CAN FD ones, against
cantools; and a configuration mapping 63- and 64-bit signals through check and both replay engines."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from cantools.database.can import Message, Signal
from cantools.database.conversion import BaseConversion
from hypothesis import event, given, settings
from hypothesis import strategies as st

from cmcan.can import codec
from cmcan.can.dbc import raw_range
from tests.conftest import ROOT, run_cli


def _signal(name: str, n: int, signed: bool, big: bool, first_bit: int, scale: float = 1.0) -> Signal:
    """A signal of ``n`` bits whose most (Motorola) or least (Intel) significant bit is at
    ``first_bit`` of the frame in big-endian linear (Motorola) or little-endian (Intel) numbering."""
    start = 8 * (first_bit // 8) + 7 - first_bit % 8 if big else first_bit
    return Signal(
        name=name,
        start=start,
        length=n,
        byte_order="big_endian" if big else "little_endian",
        is_signed=signed,
        conversion=BaseConversion.factory(scale=scale, offset=0),
    )


@st.composite
def wide_messages(draw):
    """A message of 8 bytes (or of 12..64 bytes, CAN FD) with one signal of any width 1..64 at a
    random place, and a second narrow one beside it where room is left."""
    fd = draw(st.booleans())
    length = draw(st.sampled_from([12, 16, 20, 24, 32, 48, 64])) if fd else 8
    # the widths where int64, float64 and the sign bit meet, as often as any other
    n = draw(st.one_of(st.sampled_from([1, 2, 31, 32, 33, 52, 53, 54, 62, 63, 64]), st.integers(1, 64)))
    signed = draw(st.booleans()) and n > 1
    big = draw(st.booleans())
    first = draw(st.integers(0, 8 * length - n))
    signals = [_signal("wide", n, signed, big, first)]
    # a neighbour in the bits before or after (same byte order: the test is the extractor, not overlap)
    if first >= 4:
        signals.append(_signal("low", 4, False, big, first - 4 if big else 0))
    event(f"{'fd' if fd else 'classic'} {'signed' if signed else 'unsigned'} {'motorola' if big else 'intel'}")
    event(f"width {'1-32' if n <= 32 else '33-62' if n < 63 else n}")
    if n >= 63:
        event(f"width {n} {'signed' if signed else 'unsigned'}")
    return Message(frame_id=0x123, name="WIDE", length=length, signals=signals, strict=False, is_fd=fd)


def _payload_with(msg: Message, value: int, rest: bytes) -> bytes:
    """A frame whose wide signal holds ``value`` (raw), the other bits from ``rest``."""
    lay = codec.layout(msg, "wide")
    size = codec.frame_bytes(msg)
    word = int.from_bytes(rest.ljust(size, b"\0"), "big" if lay.big_endian else "little")
    word &= ~(lay.mask << lay.shift)
    word = codec.insert(word, value, lay)
    return word.to_bytes(size, "big" if lay.big_endian else "little")[: msg.length]


@settings(max_examples=600, deadline=None)
@given(msg=wide_messages(), data=st.data())
def test_every_width_decodes_exactly_per_frame_and_in_arrays(msg, data):
    lay = codec.layout(msg, "wide")
    lo, hi = raw_range(msg.get_signal_by_name("wide"))
    # the extremes and their neighbours (where sign handling breaks), then anything
    values = [lo, hi, 0, min(hi, 1), max(lo, -1), lo + (hi > lo), hi - (hi > lo)]
    values += [data.draw(st.integers(lo, hi)) for _ in range(4)]
    payloads = [_payload_with(msg, v, data.draw(st.binary(min_size=msg.length, max_size=msg.length))) for v in values]
    names = [s.name for s in msg.signals]
    per_frame = codec.raw_decoder(codec.message_layouts(msg, names), codec.frame_bytes(msg))
    arr = np.frombuffer(b"".join(payloads), dtype=np.uint8).reshape(len(payloads), msg.length)
    vec = codec.decode_raw(msg, arr, names)
    phys = codec.decode(msg, arr, names)
    for i, p in enumerate(payloads):
        ref = msg.decode(p, decode_choices=False, scaling=False)
        assert ref["wide"] == values[i]
        assert per_frame(p) == tuple(ref[n] for n in names)
        assert [int(vec[n][i]) for n in names] == [ref[n] for n in names]
        assert phys["wide"][i] == float(ref["wide"])
    if not codec.fits_int64(lay):
        event("unsigned 64-bit: Python ints")
        assert vec["wide"].dtype == object
    else:
        assert vec["wide"].dtype == np.int64
    # the range check on raw values: every value of the bits is in range when the DBC gives none
    full = codec.Layout("wide", lay.shift, lay.length, lay.signed, lay.big_endian, 1.0, 0.0, -np.inf, np.inf)
    check = codec.checked_decoder([full], codec.frame_bytes(msg))
    assert [check(p) for p in payloads] == [(v,) for v in values]
    # encoding back: the same bits, per frame and in arrays
    enc = codec.frame_encoder([full], codec.frame_bytes(msg), msg.length)
    arr_enc = codec.encode_all([full], codec.frame_bytes(msg), msg.length, {"wide": np.array(values, dtype=float)})
    for i, v in enumerate(values):
        if abs(v) <= 2**53:  # a physical value is a float: beyond 2**53 it is not the integer
            want = msg.encode({"wide": v, **({"low": 0} if "low" in names else {})}, scaling=False, strict=False)
            assert enc({"wide": float(v)}) == want
            assert bytes(arr_enc[i]) == want


def test_the_array_extractor_keeps_unsigned_64_bit_values_above_2_63():
    msg = Message(frame_id=1, name="U64", length=8, signals=[_signal("wide", 64, False, False, 0)], strict=False)
    top = (1 << 64) - 1
    frames = np.frombuffer(top.to_bytes(8, "little") + (1 << 63).to_bytes(8, "little"), dtype=np.uint8).reshape(2, 8)
    got = codec.decode_raw(msg, frames, ["wide"])["wide"]
    assert got.tolist() == [top, 1 << 63]


def test_signed_63_and_64_bit_fix_up_needs_no_python_ints():
    """The signed fix-up of the array path once computed ``raw - 2**64`` in int64 (OverflowError)."""
    for n in (62, 63, 64):
        for big in (False, True):
            msg = Message(frame_id=1, name="S", length=8, signals=[_signal("s", n, True, big, 0)], strict=False)
            vals = [-(1 << (n - 1)), -1, 0, (1 << (n - 1)) - 1]
            rows = [msg.encode({"s": v}, scaling=False) for v in vals]
            arr = np.frombuffer(b"".join(rows), dtype=np.uint8).reshape(len(rows), 8)
            assert codec.decode_raw(msg, arr, ["s"])["s"].tolist() == vals


# -- a machine whose inputs are 63- and 64-bit signals, as cantools' signed.dbc has them ---------------

WIDE_MESSAGES = """
BO_ 768 WIDE_PUMP: 8 DRIVE_CTRL
 SG_ pump_speed_wide : 7|63@0- (1e-15,0) [0|4600] "rpm" CMCAN

BO_ 769 WIDE_MOTOR: 8 DRIVE_CTRL
 SG_ motor_speed_wide : 0|64@1+ (3e-16,0) [0|5500] "rpm" CMCAN

BO_ 770 WIDE_DP: 8 DRIVE_CTRL
 SG_ dp_wide : 0|64@1- (1e-16,0) [-900|900] "bar" CMCAN
"""


@pytest.fixture(scope="module")
def wide_machine(tmp_path_factory):
    """The shipped machine with pump speed (signed 63-bit Motorola), motor speed (unsigned 64-bit:
    about half of its values above 2**63) and dp (signed 64-bit) on messages added to a copy of the
    shipped DBC, and a short simulated log of it."""
    d = tmp_path_factory.mktemp("wide")
    shipped = (ROOT / "dbc" / "cmcan.dbc").read_text()
    at = shipped.index("\nBO_ ")
    (d / "wide.dbc").write_text(shipped[:at] + "\n" + WIDE_MESSAGES + shipped[at:])
    cfg = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    cfg["dbc"] = str(d / "wide.dbc")
    sig = cfg["signals"]
    sig["pump_speed_rpm"] = {"message": "WIDE_PUMP", "signal": "pump_speed_wide"}
    sig["motor_speed_rpm"] = {"message": "WIDE_MOTOR", "signal": "motor_speed_wide"}
    del sig["high_pressure_bar"], sig["low_pressure_bar"]
    sig["dp_bar"] = {"message": "WIDE_DP", "signal": "dp_wide"}
    (d / "cmcan.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    r = run_cli(
        "simulate", "single_set_healthy", "--config", str(d / "cmcan.yaml"), "--duration-h", "0.02",
        "--out", str(d / "run.csv"), "--candump", str(d / "run.log"),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    return d


def test_a_machine_on_63_and_64_bit_signals_checks_replays_and_scores(wide_machine):
    d = wide_machine
    cfg = str(d / "cmcan.yaml")
    assert run_cli("check", "--config", cfg).returncode == 0
    # the log holds motor speeds above 2**63 (raw): the values the array path once read as negative
    lines = [ln for ln in (d / "run.log").read_text().splitlines() if " 301#" in ln]
    raws = [int.from_bytes(bytes.fromhex(ln.split("#")[1]), "little") for ln in lines]
    assert sum(r >= 1 << 63 for r in raws) > len(raws) // 10
    outs = {}
    for engine in ("columnar", "streaming"):
        out = d / f"timeline_{engine}.csv"
        r = run_cli("replay", str(d / "run.log"), "--config", cfg, "--engine", engine, "--out", str(out), "--json")
        assert r.returncode == 0, r.stderr
        outs[engine] = out.read_bytes()
        c = json.loads(r.stdout)["final"]["counters"]
        assert c["accepted"] == c["frames_total"] and c["out_of_range"] == 0
        assert c["evaluated"] > 0.8 * c["ticks"]
    assert outs["columnar"] == outs["streaming"]
    r = run_cli("score", str(d / "run.log"), "--config", cfg, "--out", str(d / "scores.csv"), "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert abs(summary["ratio"]["ratio_p50_pct"] - 100.0) < 0.5
