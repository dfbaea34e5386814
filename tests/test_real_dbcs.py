"""DBCs written by others, as real machines come with them: CAN FD flags on short messages,
multiplexed messages, vendor files with problems in messages cmcan does not read, and every DBC of
cantools' own test files through ``cmcan check``'s DBC path (where those files are at hand).

The DBCs here are made in the test in the shape of the public files the problems were found in
(cantools' ``fd_test.dbc`` and ``signed.dbc``, opendbc's ``vw_mqb``, ``tesla_can`` and
``hyundai_2015_ccan``); none of those files is copied."""

from __future__ import annotations

from pathlib import Path

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
