"""``cmcan simulate`` as a user runs it."""

import json

import yaml

from cmcan.cli.errors import EX_CANTCREAT, EX_DATAERR, EX_NOINPUT
from tests.conftest import run_cli, small_scenario


def test_simulate_writes_csv_and_log_and_reports_json(tmp_path):
    res = run_cli(
        "simulate",
        "single_set_leakage",
        "--duration-h",
        "0.01",
        "--out",
        str(tmp_path / "r.csv"),
        "--candump",
        str(tmp_path / "r.log"),
        "--json",
    )
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["samples"] == 3600 and summary["frames"] == 3600 * 3 + 360
    assert (tmp_path / "r.log").read_text().splitlines()[0].startswith("(1767225600.000000) can0 100#")


def test_refuses_to_overwrite_without_force(tmp_path):
    out = tmp_path / "r.csv"
    out.write_text("precious")
    res = run_cli("simulate", "single_set_healthy", "--duration-h", "0.001", "--out", str(out))
    assert res.returncode == EX_CANTCREAT
    assert "already exists" in res.stderr and out.read_text() == "precious"
    res = run_cli("simulate", "single_set_healthy", "--duration-h", "0.001", "--out", str(out), "--force")
    assert res.returncode == 0 and out.read_text().startswith("time_s,")


def test_bad_scenario_exits_dataerr_naming_file_and_field(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(small_scenario(oil={"model": "prescribed", "temp_c": 500})))
    res = run_cli("simulate", str(p), "--out", str(tmp_path / "r.csv"))
    assert res.returncode == EX_DATAERR
    assert str(p) in res.stderr and "oil.temp_c" in res.stderr and "[-30, 120]" in res.stderr
    assert not (tmp_path / "r.csv").exists()


def test_unknown_scenario_exits_noinput(tmp_path):
    res = run_cli("simulate", "no_such_scenario", "--out", str(tmp_path / "r.csv"))
    assert res.returncode == EX_NOINPUT and "no_such_scenario" in res.stderr


def test_a_flow_machine_cannot_be_simulated_and_says_so(tmp_path):
    from cmcan.cli.errors import EX_USAGE
    from tests.conftest import ROOT

    out = tmp_path / "r.csv"
    res = run_cli(
        "simulate", "single_set_healthy", "--duration-h", "0.01", "--out", str(out),
        "--config", str(ROOT / "examples" / "zema-rig" / "cmcan.yaml"),
    )  # fmt: skip
    assert res.returncode == EX_USAGE, res.stderr
    assert "drive.quantity is flow_lpm" in res.stderr and "motor speed" in res.stderr
    assert not out.exists()


def test_a_scenario_of_another_drive_than_the_configured_machine_is_warned_about(tmp_path):
    from tests.conftest import ROOT

    cfg = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    cfg["drive"]["motor_disp_cc"] = 80.0
    cfg["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump(cfg))
    args = ("simulate", "single_set_healthy", "--duration-h", "0.01", "--force", "--out", str(tmp_path / "r.csv"))
    res = run_cli(*args, "--config", str(other))
    assert res.returncode == 0, res.stderr  # simulating another drive on purpose is allowed, and said
    assert "WARNING" in res.stderr and "V_M 44 cm3/rev" in res.stderr and "drive.motor_disp_cc 80" in res.stderr
    same = run_cli(*args, "--config", str(ROOT / "config" / "cmcan.yaml"))
    assert same.returncode == 0 and "WARNING" not in same.stderr, same.stderr
