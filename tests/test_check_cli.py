"""``cmcan check`` says which configuration it checked and, when a step fails, which passed before."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from cmcan.cli.errors import EX_CONFIG
from tests.conftest import ROOT, run_cli


def shipped_config(cwd: Path) -> str:
    """The shipped file as the command line sees it from ``cwd``: an installed cmcan's copy, or the
    checkout's when cmcan is installed in development mode (not the test process's, which imports
    the checkout)."""
    code = "from cmcan.config import default_config_path; print(default_config_path())"
    found = subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, check=True)
    return found.stdout.strip()


def test_check_without_config_names_the_shipped_file_and_a_local_one_it_did_not_check(tmp_path):
    shipped = shipped_config(tmp_path)
    (tmp_path / "config").mkdir()
    shutil.copyfile(ROOT / "config" / "cmcan.yaml", tmp_path / "config" / "cmcan.yaml")
    r = run_cli("check", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    first = r.stdout.splitlines()[0]
    assert shipped in first and "shipped with cmcan" in first
    assert "config/cmcan.yaml is not the file checked" in r.stdout and "--config config/cmcan.yaml" in r.stdout
    r = run_cli("check", "--json", cwd=tmp_path)
    out = json.loads(r.stdout)
    assert out["config"] == shipped and out["config_is_shipped"] is True


def test_a_model_mismatch_says_the_configuration_dbc_and_mapping_passed(tmp_path):
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    raw["drive"]["motor_disp_cc"] = 50.0  # the shipped model was trained at 44
    cfg = tmp_path / "m.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    r = run_cli("check", "--config", str(cfg))
    assert r.returncode == EX_CONFIG
    (line,) = r.stderr.strip().splitlines()  # one line: the error, then what passed before it
    error, passed = line.split(" [passed before it: ")
    assert "motor displacement" in error and "DBC" in passed and "signal mapping" in passed
    assert "; model" not in passed
    out = json.loads(run_cli("check", "--config", str(cfg), "--json").stdout)
    assert out["ok"] is False and [p.split()[0] for p in out["passed"]] == ["configuration", "DBC", "signal"]


# -- several drives on one gateway: every shared identifier ----------------------------------------


def merged(raw: dict, changes: dict) -> dict:
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(raw.get(key), dict):
            merged(raw[key], value)
        else:
            raw[key] = value
    return raw


def drive(tmp_path: Path, name: str, dbc: Path | None = None, example: bool = False, **sections) -> Path:
    """A drive's configuration (the shipped 11-bit one, or the J1939 example) with its own state
    directory; ``sections`` merged into it."""
    src = "j1939-example" if example else "cmcan"
    raw = yaml.safe_load((ROOT / "config" / f"{src}.yaml").read_text())
    raw["dbc"] = str(dbc or ROOT / "dbc" / f"{src}.dbc")
    raw["state"]["directory"] = str(tmp_path / f"state-{name}")
    merged(raw, sections)
    p = tmp_path / f"{name}.yaml"
    p.write_text(yaml.safe_dump(raw))
    return p


def other_cm_ids(tmp_path: Path) -> Path:
    """The shipped DBC with CM_RATIO, CM_SPEED and CM_WARNING moved; CM_BASELINE, CM_PROGNOSIS kept."""
    text = (ROOT / "dbc" / "cmcan.dbc").read_text()
    for old, new in (
        ("928 CM_RATIO", "944 CM_RATIO"),
        ("929 CM_SPEED", "945 CM_SPEED"),
        ("930 CM_WARNING", "946 CM_WARNING"),
    ):
        assert f"BO_ {old}:" in text
        text = text.replace(f"BO_ {old}:", f"BO_ {new}:").replace(
            f"BO_TX_BU_ {old.split()[0]} ", f"BO_TX_BU_ {new.split()[0]} "
        )
    p = tmp_path / "other.dbc"
    p.write_text(text)
    return p


def parts_of(*files: Path):
    from cmcan.daemon.preflight import load_config, prepare

    return [prepare(load_config(str(f)), need_state=False, read_only=True).parts for f in files]


UPLINK = {"enabled": True, "machine_id": "wl-0042"}


def test_two_drives_sharing_cm_baseline_prognosis_and_the_uplink_ids_are_refused(tmp_path):
    """The issue's gateway: the two drives' CM_RATIO, CM_SPEED and CM_WARNING differ, but both send
    CM_BASELINE and CM_PROGNOSIS with one identifier on can0 and publish as one machine and client.
    Before, check said "nothing shared"."""
    on = {"baseline": {"enabled": True}, "prognosis": {"enabled": True}, "uplink": UPLINK}
    a = drive(tmp_path, "left", **on)
    b = drive(tmp_path, "right", dbc=other_cm_ids(tmp_path), **on)
    r = run_cli("check", "--config", str(tmp_path))
    assert r.returncode == EX_CONFIG, r.stdout + r.stderr
    err = r.stderr
    assert "nothing shared" not in r.stdout
    assert "both send identifier 0x3A4 on can0 (CM_BASELINE / CM_BASELINE)" in err, err
    assert "both send identifier 0x3A5 on can0 (CM_PROGNOSIS / CM_PROGNOSIS)" in err
    assert "0x3A0" not in err and "0x3B0" not in err  # the CM_RATIOs differ: not said
    assert "the same uplink.machine_id 'wl-0042'" in err and "the same uplink.mqtt.client_id 'cmcan-wl-0042'" in err
    # each fixed in turn: the uplink ids, then the prognosis off on one side: CM_BASELINE alone is left
    drive(tmp_path, "right", dbc=other_cm_ids(tmp_path), **{**on, "uplink": {"enabled": True, "machine_id": "wl-0043"}})
    drive(tmp_path, "left", **{**on, "prognosis": {"enabled": False}})
    from cmcan.drives import conflicts

    problems = conflicts(parts_of(a, b))
    assert len(problems) == 1 and "0x3A4" in problems[0] and "CM_BASELINE" in problems[0], problems


def test_what_check_compares_is_every_output_message_the_monitor_sends(tmp_path):
    """The identifiers compared come from the one declaration of the output messages (the
    configuration's output items), and are exactly the monitor's outputs, DM1 included."""
    from dataclasses import fields

    from cmcan.drives import sends
    from cmcan.monitor.payloads import OutputMessage

    on = {"baseline": {"enabled": True}, "prognosis": {"enabled": True}}
    for f in (drive(tmp_path, "plain", **on), drive(tmp_path, "j", example=True, **on)):
        (p,) = parts_of(f)
        got = sends(p)
        out = p.monitor.outputs
        built = {
            (m.extended, m.frame_id)
            for m in (getattr(out, x.name) for x in fields(out))
            if isinstance(m, OutputMessage)
        }
        if p.monitor.dm1_producer is not None:
            built.add((True, p.monitor.dm1_producer.frame_id))
        assert {(ext, fid) for _ch, ext, fid in got} == built
        names = {item.message for _k, item in p.cfg.output_items()}
        assert {"CM_BASELINE", "CM_PROGNOSIS"} <= names and set(got.values()) - {"DM1"} == names


def test_j1939_address_ranges_that_overlap_are_refused(tmp_path):
    """An arbitrary address capable drive that may move to the other's address."""
    name = {"identity_number": 1001, "function_instance": 0, "arbitrary_address_capable": True}
    a = drive(tmp_path, "a", example=True, j1939={"source_address": 0x8C, "addresses": [0x8D, 0x8E], "name": name})
    b = drive(
        tmp_path,
        "b",
        example=True,
        j1939={"source_address": 0x8E, "name": {**name, "identity_number": 1002, "arbitrary_address_capable": False}},
    )
    from cmcan.drives import conflicts

    problems = conflicts(parts_of(a, b))
    assert problems == [
        f"{a} and {b} may both claim J1939 address 0x8E on can0 (j1939.source_address and j1939.addresses overlap)"
    ], problems
    drive(
        tmp_path,
        "b",
        example=True,
        j1939={"source_address": 0x90, "name": {**name, "identity_number": 1002, "arbitrary_address_capable": False}},
    )
    assert conflicts(parts_of(a, b)) == []
    r = run_cli("check", "--config", str(a), "--config", str(b))
    assert r.returncode == 0 and "no identifier, J1939 address or NAME" in r.stdout, r.stdout + r.stderr
    assert "0x18FF208C (CM_RATIO)" in r.stdout
