"""J1939 encodings: identifier and PGN arithmetic against cantools, DM1 and BAM against an
independent decoder (pretty-j1939), checksums against the crc package."""

from __future__ import annotations

import json
import subprocess
import sys

import crc
import numpy as np
import pytest
from cantools import j1939 as cj
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.can import checksums
from cmcan.can.codec import Layout
from cmcan.can.frame import Frame
from cmcan.can.j1939 import dm1, ids, transport
from cmcan.io.candump import write_frames

can_ids = st.integers(0, ids.MAX_ID)


@given(can_ids)
def test_fields_and_pgn_match_cantools(can_id):
    u = cj.frame_id_unpack(can_id)
    assert ids.priority(can_id) == u.priority
    assert ids.source_address(can_id) == u.source_address
    assert ids.pdu_format(can_id) == u.pdu_format
    assert ids.pdu_specific(can_id) == u.pdu_specific
    assert ids.pgn(can_id) == cj.pgn_from_frame_id(can_id)
    assert ids.is_pdu1(ids.pdu_format(can_id), is_pf=True) == cj.is_pdu_format_1(u.pdu_format)


@given(st.lists(can_ids, min_size=1, max_size=50))
def test_pgn_over_arrays_is_the_scalar_pgn(values):
    arr = np.array(values, dtype=np.int64)
    assert ids.pgn(arr).tolist() == [ids.pgn(v) for v in values]


@given(st.integers(0, 7), st.integers(0, ids.MAX_PGN), st.integers(0, 255), st.integers(0, 255))
def test_make_id_round_trips(prio, pgn, sa, da):
    if ids.is_pdu1(pgn) and pgn & 0xFF:
        with pytest.raises(ValueError):
            ids.make_id(prio, pgn, sa, da)
        return
    can_id = ids.make_id(prio, pgn, sa, da)
    assert ids.pgn(can_id) == pgn
    assert ids.priority(can_id) == prio and ids.source_address(can_id) == sa
    assert ids.destination(can_id) == (da if ids.is_pdu1(pgn) else ids.GLOBAL_ADDRESS)
    u = cj.frame_id_unpack(can_id)
    assert cj.frame_id_pack(*u) == can_id
    assert ids.with_source(can_id, 0x42) == (can_id & ~0xFF) | 0x42


dtcs = st.builds(dm1.Dtc, st.integers(0, dm1.SPN_MAX), st.integers(0, 31), st.integers(0, 126))


@given(dtcs)
def test_dtc_bytes_round_trip_and_follow_the_j1939_73_layout(d):
    b = dm1.encode_dtc(d)
    assert len(b) == 4 and dm1.decode_dtc(b) == d
    assert b[0] | b[1] << 8 | (b[2] >> 5) << 16 == d.spn  # SPN: 16 low bits, then the top 3 above the FMI
    assert b[2] & 0x1F == d.fmi and b[3] >> 7 == 0 and b[3] & 0x7F == d.occurrence


@given(st.lists(dtcs, max_size=6), st.booleans())
def test_dm1_payload(ds, amber):
    ds = [d for d in ds if d.spn or d.fmi]  # the all-zero DTC means "none"
    lamps = dm1.Lamps(amber_warning=dm1.Lamp.ON if amber else dm1.Lamp.OFF)
    p = dm1.encode(lamps, ds)
    assert len(p) == max(8, 2 + 4 * len(ds))
    assert p[0] == (0x04 if amber else 0) and p[1] == 0xFF
    if not ds:
        assert p == bytes((p[0], 0xFF, 0, 0, 0, 0, 0xFF, 0xFF))
    back_lamps, back = dm1.decode(p)
    assert back_lamps == lamps and back == ds


@given(
    st.binary(min_size=9, max_size=transport.MAX_SIZE),
    st.integers(0, 253),
    st.floats(0.05, 0.2),
    st.integers(0, ids.MAX_PGN).filter(lambda p: not ids.is_pdu1(p) or not p & 0xFF),
)
@settings(max_examples=60, deadline=None)
def test_bam_frames_reassemble_and_keep_the_spacing(payload, sa, gap, pgn):
    frames = transport.bam_frames(1000.0, gap, pgn, payload, sa, "can0")
    cm, dts = frames[0], frames[1:]
    assert ids.pgn(cm.arbitration_id) == transport.PGN_TP_CM and ids.priority(cm.arbitration_id) == 7
    assert cm.data[0] == 32 and cm.data[1] | cm.data[2] << 8 == len(payload) and cm.data[3] == len(dts)
    assert all(f.extended and len(f.data) == 8 and ids.source_address(f.arbitration_id) == sa for f in frames)
    assert [f.data[0] for f in dts] == list(range(1, len(dts) + 1))
    stamps = np.array([f.timestamp_s for f in frames])
    assert np.allclose(np.diff(stamps), gap)
    r = transport.BamReceiver()
    got = [r.feed(f.arbitration_id, f.data) for f in frames]
    assert got[:-1] == [None] * (len(frames) - 1) and got[-1] == (sa, pgn, payload)
    assert dts[-1].data[1 + (len(payload) - 1) % 7 + 1 :] == b"\xff" * (6 - (len(payload) - 1) % 7)


def test_bam_gap_outside_j1939_21_is_refused():
    with pytest.raises(ValueError, match=r"50\.\.200 ms"):
        transport.bam_frames(0.0, 0.01, dm1.PGN_DM1, bytes(10), 0x8C)


def test_bam_receiver_drops_a_session_with_a_lost_packet():
    frames = transport.bam_frames(0.0, 0.1, dm1.PGN_DM1, bytes(range(20)), 0x8C)
    r = transport.BamReceiver()
    assert [r.feed(f.arbitration_id, f.data) for f in frames[:2] + frames[3:]] == [None] * 3
    assert r.aborted == 1


def pretty(frames: list[Frame], tmp_path) -> list[dict]:
    """DM1 as pretty-j1939, an independent J1939 decoder, reads it from a candump log."""
    log = tmp_path / "dm1.log"
    write_frames(log, frames)
    out = subprocess.run(
        [sys.executable, "-m", "pretty_j1939", "--color", "never", "--no-summary", str(log)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def dtc_text(d: dm1.Dtc) -> str:
    return f"SPN {d.spn} (Unknown), FMI {d.fmi}, OC {d.occurrence}"


@pytest.mark.parametrize(
    "dtc_list",
    [
        [],
        [dm1.Dtc(520192, 17, 3)],
        [dm1.Dtc(520192, 18, 1), dm1.Dtc(520193, 9, 126)],
        [dm1.Dtc(520192 + i, f, i + 1) for i, f in enumerate((15, 16, 2, 9, 17))],
    ],
    ids=["none", "one", "two-over-BAM", "five-over-BAM"],
)
def test_dm1_as_an_independent_decoder_reads_it(dtc_list, tmp_path):
    lamps = dm1.Lamps(amber_warning=dm1.Lamp.ON if dtc_list else dm1.Lamp.OFF)
    payload = dm1.encode(lamps, dtc_list)
    sa = 0x8C
    if len(payload) <= 8:
        frames = [Frame(5.0, "can0", ids.make_id(6, dm1.PGN_DM1, sa), True, False, False, False, payload)]
    else:
        frames = transport.bam_frames(5.0, 0.1, dm1.PGN_DM1, payload, sa, "can0")
    got = [m for m in pretty(frames, tmp_path) if m.get("PGN") == "DM1(65226)"]
    assert len(got) == 1, got
    m = got[0]
    assert m["SA"].endswith("(140)")
    assert m["Amber Warning Lamp Status"] == ("On" if dtc_list else "Off")
    assert m["Red Stop Lamp Status"] == m["Malfunction Indicator Lamp Status"] == m["Protect Lamp Status"] == "Off"
    decoded = [m[k] for k in sorted(k for k in m if k.startswith("DTC "))]
    assert decoded == [dtc_text(d) for d in dtc_list]


# -- checksums ------------------------------------------------------------------------------------------


def test_crc8_sae_j1850_matches_the_crc_package():
    ref = crc.Calculator(crc.Crc8.SAEJ1850)
    assert checksums.crc8_sae_j1850(b"123456789") == 0x4B == ref.checksum(b"123456789")
    rng = np.random.default_rng(1)
    for n in range(0, 65, 7):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert checksums.crc8_sae_j1850(data) == ref.checksum(data)


CRC_AT_0 = Layout("crc", 0, 8, False, False, 1.0, 0.0, 0.0, 255.0)
TSC1_SUM = Layout("cs", 60, 4, False, False, 1.0, 0.0, 0.0, 15.0)
TSC1_CTR = Layout("ctr", 56, 4, False, False, 1.0, 0.0, 0.0, 15.0)


@given(st.lists(st.binary(min_size=8, max_size=8), min_size=1, max_size=20), st.lists(can_ids, min_size=20))
def test_sealed_frames_verify_and_a_changed_byte_fails(rows, id_list):
    data = np.frombuffer(b"".join(rows), dtype=np.uint8).reshape(-1, 8)
    fid = np.array(id_list[: len(rows)], dtype=np.int64)
    for algorithm, lay in (("crc8_sae_j1850", CRC_AT_0), ("j1939_tsc1", TSC1_SUM)):
        assert checksums.problem(algorithm, 8, lay, TSC1_CTR) is None
        sealed = checksums.seal(algorithm, 8, lay, fid, data)
        check = checksums.verifier(algorithm, 8, lay)
        for i, row in enumerate(sealed):
            assert check(int(fid[i]), bytes(row))
        if algorithm == "crc8_sae_j1850":  # a CRC catches every single-bit error
            bad = sealed.copy()
            bad[:, 3] ^= 0x10
            assert not any(check(int(fid[i]), bytes(r)) for i, r in enumerate(bad))


CRC_AT_6 = Layout("crc", 48, 8, False, False, 1.0, 0.0, 0.0, 255.0)
CRC_AT_2_BE = Layout("crc", 40, 8, True, False, 1.0, 0.0, 0.0, 255.0)  # Motorola: byte 2 of 8


@pytest.mark.parametrize("lay", [CRC_AT_0, CRC_AT_6, CRC_AT_2_BE], ids=["byte0", "byte6", "byte2-motorola"])
@pytest.mark.parametrize("length", [8, 7])
def test_crc8_over_arrays_says_what_the_per_frame_verifier_says(lay, length):
    """The columnar engine's CRC check (a byte column at a time) against the daemon's, on sealed
    frames, frames with one flipped bit and random ones."""
    rng = np.random.default_rng(length)
    if checksums.whole_byte(lay, 8) >= length:
        assert checksums.crc8_ok(length, lay, np.zeros((1, 8), np.uint8)) is None  # left to the verifier
        return
    data = rng.integers(0, 256, (3000, 8), dtype=np.uint8)
    data[:, length:] = 0
    sealed = checksums.seal("crc8_sae_j1850", length, lay, np.zeros(3000, np.int64), data)
    flipped = sealed.copy()
    flipped[np.arange(3000), rng.integers(0, length, 3000)] ^= (1 << rng.integers(0, 8, 3000)).astype(np.uint8)
    check = checksums.verifier("crc8_sae_j1850", length, lay)
    for rows in (sealed, flipped, data):
        got = checksums.crc8_ok(length, lay, rows)
        want = [check(0, bytes(r[:length])) for r in rows]
        assert got is not None and got.tolist() == want
    assert checksums.crc8_ok(length, lay, sealed).all() and not checksums.crc8_ok(length, lay, flipped).any()


def test_tsc1_checksum_is_the_j1939_71_formula():
    # TSC1 from address 0x11 to the engine: identifier 0x0C000011, counter 5 in byte 8
    data = bytes([0x01, 0x20, 0x30, 0x40, 0xFF, 0xFF, 0xFF, 0x05])
    s = sum(data[:7]) + 5 + 0x11 + 0x00 + 0x00 + 0x0C
    want = (((s >> 6) & 3) + (s >> 3) + s) & 7
    sealed = checksums.seal("j1939_tsc1", 8, TSC1_SUM, np.array([0x0C000011]), np.frombuffer(data, np.uint8)[None])
    assert sealed[0, 7] == (want << 4) | 5
    check = checksums.verifier("j1939_tsc1", 8, TSC1_SUM)
    assert check(0x0C000011, bytes(sealed[0])) and not check(0x0C000012, bytes(sealed[0]))
    # a CAN FD frame padded beyond the 8-byte message: checked on the message (the sum of 64 bytes of
    # padding used to run past the fold table)
    for pad in (b"\xaa" * 4, b"\xff" * 56):
        assert check(0x0C000011, bytes(sealed[0]) + pad)
        assert not check(0x0C000011, bytes([data[0] ^ 1]) + bytes(sealed[0])[1:] + pad)
    assert not check(0x0C000011, bytes(sealed[0])[:7])


def test_checksum_layouts_the_algorithms_cannot_check_are_named():
    half = Layout("crc", 4, 4, False, False, 1.0, 0.0, 0.0, 15.0)
    assert "whole byte" in checksums.problem("crc8_sae_j1850", 8, half, None)
    assert "byte 8" in checksums.problem("j1939_tsc1", 8, CRC_AT_0, TSC1_CTR)
    assert "unknown" in checksums.problem("md5", 8, CRC_AT_0, None)
