"""DBCs written by others, as real machines come with them: CAN FD flags on short messages,
multiplexed messages, vendor files with problems in messages cmcan does not read, and every DBC of
cantools' own test files through ``cmcan check``'s DBC path (where those files are at hand).

The DBCs here are made in the test in the shape of the public files the problems were found in
(cantools' ``fd_test.dbc`` and ``signed.dbc``, opendbc's ``vw_mqb``, ``tesla_can`` and
``hyundai_2015_ccan``); none of those files is copied."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from cmcan.cli.errors import EX_CONFIG
from tests.conftest import ROOT, run_cli

SHIPPED_DBC = ROOT / "dbc" / "cmcan.dbc"
OIL = 259  # OIL_STATUS in the shipped DBC: temp_c's message


def dbc_with(
    tmp_path: Path, *, messages: str = "", attributes: str = "", replace: dict[str, str] | None = None
) -> Path:
    """The shipped DBC with ``messages`` (BO_ blocks) added before its first message, ``attributes``
    (BA_DEF_/BA_ lines) at its end and ``replace`` applied."""
    text = SHIPPED_DBC.read_text()
    for old, new in (replace or {}).items():
        assert old in text, old
        text = text.replace(old, new)
    if messages:
        at = text.index("\nBO_ ")
        text = text[:at] + "\n" + messages.strip("\n") + "\n" + text[at:]
    if attributes:
        text = text.rstrip("\n") + "\n" + attributes.strip("\n") + "\n"
    out = tmp_path / "machine.dbc"
    out.write_text(text)
    return out


def config_with(tmp_path: Path, dbc: Path, edit=None) -> Path:
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(dbc)
    if edit is not None:
        edit(raw)
    path = tmp_path / "machine.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


# -- CAN FD declared by the DBC (cantools' fd_test.dbc: StandardCAN_FD messages of 8 bytes) -----------

FD_ATTRIBUTES = f"""
BA_DEF_ BO_  "CANFD_BRS" ENUM  "0","1";
BA_DEF_ BO_  "VFrameFormat" ENUM  "StandardCAN","ExtendedCAN","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","reserved","StandardCAN_FD","ExtendedCAN_FD";
BA_DEF_DEF_  "CANFD_BRS" "1";
BA_DEF_DEF_  "VFrameFormat" "StandardCAN";
BA_ "VFrameFormat" BO_ {OIL} 14;
"""  # noqa: E501


def test_an_fd_message_of_8_bytes_on_a_classic_bus_is_refused_by_check(tmp_path):
    dbc = dbc_with(tmp_path, attributes=FD_ATTRIBUTES)
    r = run_cli("check", "--config", str(config_with(tmp_path, dbc)))
    assert r.returncode == EX_CONFIG, r.stderr
    assert "signals.temp_c.message" in r.stderr and "OIL_STATUS is a CAN FD message" in r.stderr, r.stderr
    assert "VFrameFormat" in r.stderr and "can0 is not a CAN FD bus" in r.stderr
    # on a bus configured as CAN FD it is read
    fd_bus = config_with(tmp_path, dbc, lambda raw: raw.setdefault("frames", {}).update(fd=True))
    r = run_cli("check", "--config", str(fd_bus))
    assert r.returncode == 0, r.stderr


# -- vendor files with problems in messages cmcan does not read ----------------------------------------

# opendbc's vw_mqb: PLA_01 has two signals over the same bits (cantools' strict load refuses the file)
OVERLAPPING = """
BO_ 1010 PLA_01: 8 Gateway
 SG_ PLA_Bremsverzoegerung : 16|11@1+ (0.01,0) [0|20] "m/s2" XXX
 SG_ PLA_Bremsmoment : 24|13@1+ (1,0) [0|8000] "Nm" XXX
"""
# opendbc's tesla_can: a value table for a signal its message does not have (cantools refuses the
# file at any strictness)
ORPHAN_VALUES = """
BO_ 568 UI_driverAssistRoadSign: 8 UI
 SG_ UI_roadSign : 0|8@1+ (1,0) [0|255] "" XXX
"""
ORPHAN_VAL = 'VAL_ 568 UI_mapSpeedLimit 31 "SNA" 30 "UNLIMITED" 0 "UNKNOWN" ;'


def test_a_problem_in_a_message_cmcan_does_not_read_is_a_warning_naming_it(tmp_path):
    dbc = dbc_with(tmp_path, messages=OVERLAPPING + ORPHAN_VALUES, attributes=ORPHAN_VAL)
    import cantools

    with pytest.raises(Exception, match=r"overlapping|unused VAL_"):
        cantools.database.load_file(str(dbc), strict=True)
    r = run_cli("check", "--config", str(config_with(tmp_path, dbc)), "--json")
    assert r.returncode == 0, r.stderr
    ignored = json.loads(r.stdout)["dbc_messages_ignored"]
    assert set(ignored) == {"PLA_01", "UI_driverAssistRoadSign"}
    assert "overlapping" in ignored["PLA_01"] and "PLA_Bremsverzoegerung" in ignored["PLA_01"]
    assert "UI_mapSpeedLimit" in ignored["UI_driverAssistRoadSign"]
    assert "PLA_01" in r.stderr and "UI_mapSpeedLimit" in r.stderr  # the warning, once
    assert r.stderr.count("WARNING") == 1


def test_a_problem_in_a_message_cmcan_reads_is_refused(tmp_path):
    # the oil temperature's message with a second signal over its bits
    dbc = dbc_with(
        tmp_path,
        replace={
            ' SG_ oil_status_counter : 56|4@1+ (1,0) [0|15] "count" CMCAN': " SG_ oil_status_counter : 56|4@1+ (1,0) "
            '[0|15] "count" CMCAN\n SG_ oil_shadow : 8|8@1+ (1,0) [0|255] "" CMCAN'
        },
    )
    r = run_cli("check", "--config", str(config_with(tmp_path, dbc)))
    assert r.returncode == EX_CONFIG
    assert "signals.temp_c.message" in r.stderr and "oil_shadow" in r.stderr and "overlapping" in r.stderr, r.stderr


def test_a_dbc_that_does_not_parse_is_still_refused(tmp_path):
    bad = tmp_path / "bad.dbc"
    bad.write_text(SHIPPED_DBC.read_text().replace("BO_ 259 OIL_STATUS: 8", "BO_ 259 OIL_STATUS 8"))
    r = run_cli("check", "--config", str(config_with(tmp_path, bad)))
    assert r.returncode == EX_CONFIG and "not a valid DBC" in r.stderr and str(bad) in r.stderr


# -- multiplexed messages (opendbc's hyundai_2015_ccan EMS12: TEMP_ENG beside a multiplexer) -----------

MULTIPLEXED = """
BO_ 809 EMS12: 8 DRIVE_CTRL
 SG_ CONF_TCU m1 : 0|6@1+ (1.0,0.0) [0.0|63.0] "" CMCAN
 SG_ CAN_VERS m0 : 0|6@1+ (1.0,0.0) [0.0|7.7] "" CMCAN
 SG_ TQ_STND m3 : 0|6@1+ (10.0,0.0) [0.0|630.0] "degC" CMCAN
 SG_ MUL_CODE M : 6|2@1+ (1.0,0.0) [0.0|3.0] "" CMCAN
 SG_ TEMP_ENG : 8|8@1+ (0.75,-48.0) [-48.0|143.25] "degC" CMCAN
"""


def test_a_signal_of_a_multiplexed_message_that_is_in_every_frame_is_read(tmp_path):
    dbc = dbc_with(tmp_path, messages=MULTIPLEXED)

    def temp_eng(raw):
        raw["signals"]["temp_c"] = {"message": "EMS12", "signal": "TEMP_ENG"}

    cfg = config_with(tmp_path, dbc, temp_eng)
    r = run_cli("check", "--config", str(cfg))
    assert r.returncode == 0, r.stderr
    # decoded as cantools decodes it, per frame and in arrays, whatever the multiplexer says
    import cantools
    import numpy as np

    from cmcan.can import codec

    msg = cantools.database.load_file(str(dbc)).get_message_by_name("EMS12")
    frames = [bytes([mux << 6 | 5, t, 0, 0, 0, 0, 0, 0]) for mux in (0, 1, 3) for t in (0, 100, 255)]
    per_frame = codec.raw_decoder(codec.message_layouts(msg, ["TEMP_ENG"]), codec.frame_bytes(msg))
    arr = codec.decode(msg, np.frombuffer(b"".join(frames), dtype=np.uint8).reshape(-1, 8), ["TEMP_ENG"])["TEMP_ENG"]
    for i, f in enumerate(frames):
        want = msg.decode(f)["TEMP_ENG"]
        assert per_frame(f)[0] * 0.75 - 48.0 == pytest.approx(want) and arr[i] == pytest.approx(want)


def test_a_multiplexed_signal_is_refused_saying_so(tmp_path):
    dbc = dbc_with(tmp_path, messages=MULTIPLEXED)

    def tq(raw):
        raw["signals"]["temp_c"] = {"message": "EMS12", "signal": "TQ_STND"}

    r = run_cli("check", "--config", str(config_with(tmp_path, dbc, tq)))
    assert r.returncode == EX_CONFIG
    assert "signals.temp_c" in r.stderr and "EMS12.TQ_STND is multiplexed" in r.stderr and "MUL_CODE is 3" in r.stderr
    assert "integer" not in r.stderr, r.stderr
