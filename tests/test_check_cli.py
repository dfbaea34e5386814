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
