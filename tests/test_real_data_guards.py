"""What train, score and evaluate say when real data are not what the configuration expects: a stuck
sensor, a column in other units, a label with no healthy point, nothing left to check. Each either
refuses with exit 65 naming the cause, or warns on stderr while doing its job; JSON stays strict."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from cmcan.cli.errors import EX_DATAERR
from cmcan.cli.jsonout import finite
from tests.conftest import run_cli
from tests.test_zema_rig import CONFIG, DATA, read_csv


def write_rows(path: Path, rows: list[dict[str, str]]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return path


def scaled(rows: list[dict[str, str]], column: str, factor: float) -> list[dict[str, str]]:
    return [{**r, column: repr(float(r[column]) * factor)} for r in rows]


def strict_json(text: str) -> dict:
    def refuse(name: str) -> None:
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """The rig model trained on its healthy cycles (the README's command)."""
    out = tmp_path_factory.mktemp("guards") / "rig.onnx"
    r = run_cli("train", str(DATA), "--points", "--config", str(CONFIG), "--where", "pump_leak=0", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "WARNING" not in r.stderr  # the real rig's physics is plausible: no doubt raised
    return out


def score(model: Path, data: Path, out: Path, *extra: str):
    return run_cli(
        "score", str(data), "--points", "--config", str(CONFIG), "--model", str(model), "--out", str(out), *extra
    )


def test_json_numbers_that_are_not_finite_become_null():
    got = finite({"a": math.nan, "b": [1.0, math.inf, {"c": -math.inf}], "d": (np.float64("nan"), 2), "e": "nan"})
    assert got == {"a": None, "b": [1.0, None, {"c": None}], "d": [None, 2], "e": "nan"}


def test_a_label_without_healthy_points_gives_strict_json_and_says_so(tmp_path, model):
    data = write_rows(tmp_path / "degraded.csv", [r for r in read_csv(DATA) if float(r["pump_leak"]) != 0][:300])
    r = score(model, data, tmp_path / "s.csv", "--label", "pump_leak=0", "--json")
    assert r.returncode == 0, r.stderr
    labels = strict_json(r.stdout)["labels"]
    assert labels and all(v["auc_vs_healthy"] is None for v in labels.values())
    r = score(model, data, tmp_path / "s2.csv", "--label", "pump_leak=0")
    assert "no AUC (no healthy point rated to compare with)" in r.stdout and "nan" not in r.stdout


def test_a_score_that_rates_no_point_is_an_error_and_keeps_the_statuses(tmp_path, model):
    # pressures in psi where the configuration reads bar: every point is implausible
    data = write_rows(tmp_path / "psi.csv", scaled(read_csv(DATA)[:200], "ps1_bar", 14.5038))
    r = score(model, data, tmp_path / "s.csv")
    assert r.returncode == EX_DATAERR, r.stderr
    assert "psi.csv: none of its 200 points could be rated (gated: implausible_input 200)" in r.stderr
    assert {row["status"] for row in read_csv(tmp_path / "s.csv")} == {"gated:implausible_input"}


def test_a_flow_in_other_units_is_scored_with_a_warning(tmp_path, model):
    # the flow in m^3/h: every ratio about 6 %, which is no wear
    data = write_rows(tmp_path / "m3h.csv", scaled(read_csv(DATA)[:200], "fs1_lpm", 0.06))
    r = score(model, data, tmp_path / "s.csv")
    assert r.returncode == 0, r.stderr
    assert "m3h.csv: the median CM ratio is 6.0 %" in r.stderr and "units" in r.stderr


def test_training_refuses_a_stuck_output(tmp_path):
    rows = [{**r, "fs1_lpm": "6.6"} for r in read_csv(DATA) if float(r["pump_leak"]) == 0]
    data = write_rows(tmp_path / "stuck.csv", rows)
    r = run_cli("train", str(data), "--points", "--config", str(CONFIG), "--out", str(tmp_path / "m.onnx"))
    assert r.returncode == EX_DATAERR, r.stderr
    assert "flow_lpm is 6.6 at every training point" in r.stderr and "stuck sensor" in r.stderr
    assert not (tmp_path / "m.onnx").exists()


def test_a_scored_stuck_output_is_warned_about(tmp_path, model):
    data = write_rows(tmp_path / "stuck.csv", [{**r, "fs1_lpm": "6.6"} for r in read_csv(DATA)[:200]])
    r = score(model, data, tmp_path / "s.csv")
    assert r.returncode == 0, r.stderr
    assert "stuck.csv: the measured flow_lpm is 6.6 at every rated point" in r.stderr


def test_training_on_a_flow_in_other_units_warns_about_the_physics(tmp_path):
    rows = [r for r in read_csv(DATA) if float(r["pump_leak"]) == 0]
    data = write_rows(tmp_path / "m3h.csv", scaled(rows, "fs1_lpm", 0.06))
    out = tmp_path / "m.onnx"
    r = run_cli("train", str(data), "--points", "--config", str(CONFIG), "--out", str(out), "--json")
    assert r.returncode == 0, r.stderr  # the model is written: unusual physics is the user's call
    warnings = strict_json(r.stdout)["warnings"]
    assert any(w.startswith("physics term ideal_flow") and "below its prior" in w for w in warnings), warnings
    assert "WARNING cmcan: " in r.stderr and "check the data's units" in r.stderr


def test_training_on_data_with_worn_drives_warns_that_it_is_no_healthy_reference(tmp_path):
    """The rig's cycles with every pump leakage level (two of them worn pumps): the model is written,
    with a warning that its own ratio spread is not a healthy drive's; the healthy cycles alone give
    none."""
    out = tmp_path / "m.onnx"
    args = ("train", str(DATA), "--points", "--config", str(CONFIG), "--where", "cooler_pct=100")
    mixed = run_cli(*args, "--out", str(out), "--json")
    assert mixed.returncode == 0, mixed.stderr
    said = [w for w in strict_json(mixed.stdout)["warnings"] if "of a model fit to a healthy drive" in w]
    assert len(said) == 1 and said[0].startswith("D_trn ratio p1..p99 ") and "--where" in said[0], said
    healthy = run_cli(*args, "--where", "pump_leak=0", "--out", str(out), "--force", "--json")
    assert healthy.returncode == 0, healthy.stderr
    assert not [w for w in strict_json(healthy.stdout)["warnings"] if "healthy drive" in w]


def test_rows_in_reverse_are_left_out_of_training_and_gap_with_their_reason(tmp_path):
    """A table whose flow is signed: the rows of reverse travel (negative flow) are refused as such by
    train (the gate report names them) and by gap, not taken as data nor crash anything."""
    rows = [r for r in read_csv(DATA) if float(r["pump_leak"]) == 0 and float(r["cooler_pct"]) == 100]
    signed = [{**r, "fs1_lpm": repr(-float(r["fs1_lpm"]))} if i % 10 == 0 else r for i, r in enumerate(rows)]
    data = write_rows(tmp_path / "signed.csv", signed)
    res = run_cli("train", str(data), "--points", "--config", str(CONFIG), "--out", str(tmp_path / "m.onnx"), "--json")
    assert res.returncode == 0, res.stderr
    gates = strict_json(res.stdout)["gates"]
    n_rev = len(range(0, len(rows), 10))
    refused = gates["refused"]
    assert refused["reverse"]["points"] == n_rev and "reverse travel" in refused["reverse"]["why"], gates
    assert gates["passed"] == len(rows) - n_rev
    from cmcan.config import load
    from cmcan.gap import data as gapdata
    from cmcan.io.points import read_points
    from cmcan.roles import FLOW, MODEL_INPUTS

    cfg = load(CONFIG)
    pts = read_points(data, cfg.points, (*MODEL_INPUTS, FLOW))
    d = gapdata.from_points(pts, FLOW, cfg.gate_limits)
    assert d.refused == n_rev, d.refused_why
    assert f"reverse travel: negative pump_disp_cc or flow_lpm ({n_rev} points)" in d.refused_why
