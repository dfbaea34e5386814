"""``cmcan replay``: the same core over any log format, timeline, emitted frames, warnings, plot."""

import csv
import json

import can
import numpy as np
import pytest

from cmcan.cli.errors import EX_CANTCREAT, EX_DATAERR, EX_NOINPUT
from cmcan.io.candump import write_candump
from tests.conftest import run_cli
from tests.helpers import sim_frames, write_log


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("replay")
    run, frames = sim_frames("two_set_validation", duration_h=1.2)
    log = write_log(d / "val.log", frames)
    _, short = sim_frames("two_set_validation", duration_h=0.08)
    write_log(d / "short.log", short)
    return d, log, run


def emitted(path):
    return [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(path))]


@pytest.fixture(scope="module")
def replayed(logs):
    """``cmcan replay`` of the 1.2 h log writing everything it can, once: its process and files."""
    d, log, _run = logs
    return run_cli(
        "replay",
        str(log),
        "--out",
        str(d / "tl.csv"),
        "--emit",
        str(d / "emit.log"),
        "--plot",
        str(d / "ratio.png"),
        "--json",
    )


def test_replay_writes_timeline_emit_plot_and_warnings(logs, replayed):
    d, _log, _run = logs
    res = replayed
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    lows = [w for w in summary["warnings"] if w["to"] == "low"]
    assert len(lows) == 1 and 1.0 < lows[0]["operating_h"] < 1.15
    assert summary["final"]["counters"]["frames_total"] == summary["final"]["counters"]["accepted"]
    with open(d / "tl.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == summary["final"]["counters"]["ticks"]
    gates = {r["gate"] for r in rows}
    assert "evaluating" in gates and gates & {"low_speed", "low_displacement", "low_flow"}
    out = emitted(d / "emit.log")
    assert {i for i, _ in out} == {0x3A0, 0x3A1, 0x3A2}
    assert (d / "ratio.png").stat().st_size > 10_000


@pytest.mark.parametrize("ext", ["asc", "blf", "csv", "trc"])
def test_other_log_formats_give_the_same_frames(logs, ext):
    d, _, _ = logs
    log = d / "short.log"
    ref = d / "ref_emit.log"
    if not ref.exists():
        assert run_cli("replay", str(log), "--emit", str(ref)).returncode == 0
    other = d / f"val.{ext}"
    with can.Logger(str(other)) as w:
        for m in can.LogReader(str(log)):
            w.on_message_received(m)
    res = run_cli("replay", str(other), "--emit", str(d / f"emit_{ext}.log"), "--force")
    assert res.returncode == 0, res.stderr
    assert emitted(d / f"emit_{ext}.log") == emitted(ref)


def test_replay_refuses_to_overwrite(logs):
    d, log, _ = logs
    keep = d / "keep.csv"
    keep.write_text("mine")
    res = run_cli("replay", str(log), "--out", str(keep))
    assert res.returncode == EX_CANTCREAT and keep.read_text() == "mine"


def test_replay_missing_and_garbage_logs(tmp_path):
    assert run_cli("replay", str(tmp_path / "nope.log")).returncode == EX_NOINPUT
    bad = tmp_path / "bad.log"
    bad.write_text("this is not a candump line\n")
    res = run_cli("replay", str(bad))
    assert res.returncode == EX_DATAERR and "bad.log" in res.stderr


def test_operating_hours_go_on_through_a_step_back_of_the_wall_clock(tmp_path):
    """An NTP or GPS fix sets the clock back 3 days three minutes into the log, before the leak's low
    warning: the monitor re-bases (one clock step), and operating hours (the warnings', the
    timeline's, the duration) go on as if the clock had not moved, the same from both engines. They
    used to go 72 h negative."""
    leak = {"type": "leakage", "start_h": 0.03, "extra_lpm": 8.0, "ref_dp_bar": 300}
    _, frames = sim_frames("two_set_validation", duration_h=0.12, events=[leak])
    t = frames.timestamp_s.copy()
    t0 = float(t[0])
    t[t >= t0 + 180.0] -= 3 * 86400.0
    write_candump(tmp_path / "step.log", t, frames.arbitration_id, frames.dlc, frames.data)
    log = write_log(tmp_path / "plain.log", frames)
    plain = json.loads(run_cli("replay", str(log), "--json").stdout)
    assert [w["operating_h"] > 180.0 / 3600.0 for w in plain["warnings"] if w["to"] == "low"] == [True]
    out = {}
    for engine in ("columnar", "streaming"):
        tl, em = tmp_path / f"{engine}.csv", tmp_path / f"{engine}.log"
        res = run_cli(
            "replay", str(tmp_path / "step.log"), "--engine", engine, "--out", str(tl), "--emit", str(em), "--json"
        )
        assert res.returncode == 0, res.stderr
        out[engine] = (res.stdout, tl.read_bytes(), em.read_bytes())
    assert out["columnar"] == out["streaming"]
    stepped = json.loads(out["columnar"][0])
    assert stepped["final"]["counters"]["clock_steps"] == 1
    assert abs(stepped["duration_h"] - plain["duration_h"]) < 1e-6
    lows = [w["operating_h"] for w in stepped["warnings"] if w["to"] == "low"]
    assert lows == pytest.approx([w["operating_h"] for w in plain["warnings"] if w["to"] == "low"], abs=1e-6)
    with open(tmp_path / "columnar.csv") as f:
        hours = np.array([float(r["operating_h"]) for r in csv.DictReader(f)])
    assert hours[0] >= 0 and (np.diff(hours) > 0).all() and hours[-1] == pytest.approx(plain["duration_h"], abs=1e-3)


def test_replay_says_when_the_configuration_does_not_fit_the_machine(logs, replayed, tmp_path):
    """A healthy drive read through a mapping 20 % off (a speed's gear ratio written wrong) sits far
    from 100 % from its first hour: replay says the configuration or model does not fit (a warning,
    and ``fit`` in --json) instead of leaving it to read as a worn drive; the right mapping fits."""
    import yaml

    from tests.conftest import ROOT

    _d, log, _run = logs
    good = json.loads(replayed.stdout)  # the same log through the shipped configuration
    assert good["fit"]["verdict"] == "fits" and 99.0 < good["fit"]["median_pct"] < 101.0
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    raw["signals"]["motor_speed_rpm"]["scale"] = 0.8
    cfg = tmp_path / "m.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    r = run_cli("replay", str(log), "--config", str(cfg), "--json")
    assert r.returncode == 0, r.stderr
    fit = json.loads(r.stdout)["fit"]
    assert fit["verdict"] == "does_not_fit" and 78.0 < fit["median_pct"] < 82.0 and fit["points"] >= 300
    assert "configuration or model does not fit" in r.stderr


def test_the_ratio_plots_axis_shows_a_failure_and_the_thresholds():
    from cmcan.plots import ratio_limits

    assert ratio_limits(np.array([99.5, 100.4]), 98.0, 102.0) == (95.0, 105.0)
    lo, hi = ratio_limits(np.array([100.0, 43.0]), 98.0, 102.0)  # the fall at a failure stays in view
    assert lo <= 43.0 and hi >= 105.0
    assert ratio_limits(np.array([-10.0, 500.0]), 98.0, 102.0) == (0.0, 200.0)  # what a CM frame can carry


def test_the_timeline_leaves_empty_what_a_tick_does_not_have(logs, tmp_path):
    """No 0.000 for the prediction and ratio of a tick that was not evaluated, nor for the filtered
    ratio before the filter is valid: empty cells, so an average over a column is over real values."""
    d, _log, _run = logs
    out = tmp_path / "tl.csv"
    assert run_cli("replay", str(d / "short.log"), "--out", str(out)).returncode == 0
    with open(out) as f:
        rows = list(csv.DictReader(f))
    evaluated = [r for r in rows if r["gate"] in ("evaluating", "extrapolated")]
    others = [r for r in rows if r["gate"] not in ("evaluating", "extrapolated")]
    assert evaluated and others
    for r in others:
        assert r["motor_speed_pred_rpm"] == r["motor_speed_whitebox_rpm"] == r["cm_ratio_raw_pct"] == ""
        assert r["motor_speed_meas_rpm"] != ""
    assert all(r["cm_ratio_raw_pct"] and float(r["motor_speed_pred_rpm"]) > 0 for r in evaluated)
    valid = [r["cm_filt_valid"] == "1" for r in rows]
    assert any(valid) and not all(valid)
    for r, v in zip(rows, valid, strict=True):
        assert (r["cm_ratio_filt_pct"] != "") == v and (r["extra_leak_lpm"] != "") == v
    mean = np.mean([float(r["cm_ratio_raw_pct"]) for r in evaluated])
    assert 99.0 < mean < 101.0


def test_replay_says_what_a_log_has_when_nothing_matched(logs):
    """The J1939 example's configuration on an 11-bit log: no input at all. Replay names what it
    expected and the log's busiest identifiers; a --channel-map naming a channel the log does not
    have is said too."""
    from tests.conftest import ROOT

    d, _log, _run = logs
    r = run_cli("replay", str(d / "short.log"), "--config", str(ROOT / "config" / "j1939-example.yaml"), "--json")
    assert r.returncode == 0, r.stderr
    assert "not one frame of the log was an input" in r.stderr
    assert "HST_MOTOR (PGN 0xFF11 on can0)" in r.stderr and "0x102 x" in r.stderr
    unknown = json.loads(r.stdout)["final"]["unknown_ids"]
    assert {u["id"] for u in unknown} == {"0x100", "0x101", "0x102", "0x103"}
    r = run_cli("replay", str(d / "short.log"), "--channel-map", "can7=can0")
    assert "--channel-map names 'can7', which the log does not have (it has can0)" in r.stderr
