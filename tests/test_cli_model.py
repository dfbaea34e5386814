"""``cmcan train`` and ``cmcan evaluate`` as a user runs them."""

import json

import numpy as np
import pytest

from cmcan.cli.errors import EX_CANTCREAT, EX_DATAERR, EX_NOINPUT
from tests.conftest import run_cli


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli_model")
    for name, hours in (("training_healthy", "0.5"), ("two_set_validation", "0.2")):
        res = run_cli(
            "simulate",
            name,
            "--duration-h",
            hours,
            "--out",
            str(d / f"{name}.csv"),
            "--candump",
            str(d / f"{name}.log"),
        )
        assert res.returncode == 0, res.stderr
    return d


@pytest.mark.slow
def test_train_from_a_candump_log_then_evaluate_with_plot(data):
    model = data / "m.onnx"
    res = run_cli("train", str(data / "training_healthy.log"), "--t-trn-h", "0.35", "--out", str(model), "--json")
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["residual_stats"]["set"] == "D_tst" and summary["residual_stats"]["rmse"] < 5
    res = run_cli(
        "evaluate",
        str(data / "training_healthy.csv"),
        "--t-trn-h",
        "0.35",
        "--model",
        str(model),
        "--healthy",
        str(data / "two_set_validation.csv"),
        "--json",
        "--plot",
        str(data / "e.png"),
    )
    assert res.returncode == 0, res.stderr + res.stdout
    rep = json.loads(res.stdout)
    f = rep["sets"]["D_tst"]
    assert f["rmse_graybox"] <= f["rmse_whitebox"] / 3
    assert (data / "e.png").stat().st_size > 10_000


def test_evaluate_default_model_prints_the_table(data):
    res = run_cli("evaluate", str(data / "training_healthy.csv"), "--t-trn-h", "0.3")
    assert res.returncode == 0, res.stderr + res.stdout
    assert "RMSE gray" in res.stdout and "[ok] D_tst: graybox_rmse <= whitebox_rmse / 3" in res.stdout


def test_train_names_missing_columns(tmp_path, data):
    bad = tmp_path / "bad.csv"
    lines = (data / "training_healthy.csv").read_text().splitlines()[:50]
    header = lines[0].split(",")
    drop = header.index("dp_bar")
    bad.write_text("\n".join(",".join(c for i, c in enumerate(line.split(",")) if i != drop) for line in lines))
    res = run_cli("train", str(bad), "--t-trn-h", "0.1", "--out", str(tmp_path / "m.onnx"))
    assert res.returncode == EX_DATAERR
    assert "bad.csv" in res.stderr and "missing column(s) dp_bar" in res.stderr


def test_train_missing_data_file(tmp_path):
    res = run_cli("train", str(tmp_path / "none.log"), "--t-trn-h", "0.1", "--out", str(tmp_path / "m.onnx"))
    assert res.returncode == EX_NOINPUT and "none.log" in res.stderr


def test_train_refuses_to_overwrite_a_model(tmp_path, data):
    out = tmp_path / "m.onnx"
    out.write_bytes(b"keep me")
    res = run_cli("train", str(data / "training_healthy.csv"), "--t-trn-h", "0.1", "--out", str(out))
    assert res.returncode == EX_CANTCREAT and out.read_bytes() == b"keep me"


def test_train_too_short_span(tmp_path, data):
    res = run_cli("train", str(data / "training_healthy.csv"), "--t-trn-h", "0.001", "--out", str(tmp_path / "m.onnx"))
    assert res.returncode == EX_DATAERR and "steady points before t_trn" in res.stderr


def test_evaluate_with_no_point_left_to_check_fails(data):
    """--t-trn-h past the end of the run leaves D_tst empty: nothing was checked, so nothing passed."""
    res = run_cli("evaluate", str(data / "training_healthy.csv"), "--t-trn-h", "10", "--json")
    assert res.returncode == 1, res.stderr + res.stdout
    rep = json.loads(res.stdout)
    assert rep["sets"]["D_tst"]["points"] == 0 and rep["passed"] is False
    assert list(rep["checks"].values()) == [False]


def test_evaluate_plot_labels_every_point_by_its_part_of_the_protocol(data, tmp_path):
    """Points after the end of training are the test set, never labelled as training; each set's
    white-box residuals carry that set's name."""
    from cmcan.cli.common import load_config, load_model, load_points
    from cmcan.model.evaluate import protocol
    from cmcan.plots import plot_residuals

    cfg = load_config(None)
    t_trn = 0.3
    report, sets = protocol(
        load_model(cfg, None),
        load_points(str(data / "training_healthy.csv"), cfg),
        t_trn,
        load_points(str(data / "two_set_validation.csv"), cfg),
        0.1,
    )
    panels = plot_residuals(sets, report, tmp_path / "e.png")
    assert (tmp_path / "e.png").stat().st_size > 10_000
    training, validation = panels
    assert training.mark_h == t_trn and validation.mark_h == 0.1
    for panel, after in ((training, "after the end of training"), (validation, "after the damage onset")):
        assert {s.whitebox for s in panel.series} == {False, True}
        for s in panel.series:
            late = np.asarray(s.hours) >= panel.mark_h
            assert len(late) and (late.all() if after in s.label else not late.any()), s.label
            if not late.any() and panel is training:
                assert "training" in s.label and "after" not in s.label
    labels = [s.label for s in training.series]
    assert len(set(labels)) == len(labels) == 4
