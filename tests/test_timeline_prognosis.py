"""The replay's timeline CSV carries the prognosis where the configuration enables it: its columns
named as a tick's fields, the same bytes from both engines, an estimate near the truth on a short
wear run, and inf / NaN written as the timeline writes them elsewhere (by either formatter)."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest
import yaml

from cmcan import config as cfgmod
from cmcan.assemble import assemble
from cmcan.monitor.gating import Gate
from cmcan.monitor.prognosis import FIELDS, STATE_CODES
from cmcan.monitor.tick import PROGNOSIS_HOURS, TickColumns
from cmcan.replay import TimelineWriter, replay_file, timeline_columns
from cmcan.roles import MOTOR_SPEED
from tests.conftest import ROOT, run_cli
from tests.helpers import IMPLS, helpers_impl, sim_frames, write_log

FAIL_H = 70.0  # the motor's wear reaches its end of life (40 l/min) here
EOL = ("prognosis_to_eol_p10_h", "prognosis_to_eol_p50_h", "prognosis_to_eol_p90_h")


@pytest.fixture(scope="module")
def wear(tmp_path_factory):
    """A short wear run (2 s every half hour for 66 h, the motor wearing from 10 h to its end of life
    at 70 h) as a candump log, and a configuration with the prognosis on and the demo's time-lapse
    windows (a 30-sample filter, 10 s of debounce)."""
    d = tmp_path_factory.mktemp("wear")
    ev = [{"type": "wear", "component": "motor", "start_h": 10, "fail_h": FAIL_H, "fail_extra_lpm": 40}]
    sampling = {"mode": "bursts", "burst_s": 2.0, "every_min": 30.0}
    _, frames = sim_frames("run_to_failure", duration_h=66.0, events=ev, sampling=sampling)
    log = write_log(d / "wear.log", frames)
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    raw["filter"].update(samples=30, min_samples=10)
    raw["thresholds"]["debounce_s"] = 10.0
    raw["prognosis"] = {"enabled": True, "end_of_life": {"kind": "leak_lpm", "value": 40}}
    cfg = d / "machine.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    return d, log, cfg


def _rows(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def test_both_engines_write_the_prognosis_alike_and_near_the_truth(wear):
    d, log, cfg = wear
    res = run_cli("replay", str(log), "--config", str(cfg), "--out", str(d / "columnar.csv"), "--engine", "columnar")
    assert res.returncode == 0, res.stderr
    # the other engine in-process (a second Python start would double the test's time)
    c = cfgmod.load(cfg)
    replay_file(log, assemble(c).monitor, [TimelineWriter(d / "streaming.csv", c.quantity, True)], engine="streaming")
    columnar = (d / "columnar.csv").read_bytes()
    assert columnar == (d / "streaming.csv").read_bytes()

    text = columnar.decode("ascii")
    header = text.split("\r\n", 1)[0].split(",")
    assert tuple(header) == timeline_columns(MOTOR_SPEED, prognosis=True)
    assert tuple(header[-len(FIELDS) :]) == FIELDS  # named as a tick's fields, a rename follows
    rows = _rows(text)
    state = np.array([r["prognosis_state"] for r in rows])
    hour = np.array([float(r["operating_h"]) for r in rows])
    assert set(state) <= set(STATE_CODES) and {"none", "trend", "imminent"} <= set(state)
    assert (state[hour < 12.0] == "none").all()  # no trend invented before the wear shows
    # without an estimate the hours are empty cells; with one, p10 <= p50 <= p90
    none = state == "none"
    for name in PROGNOSIS_HOURS:
        assert all(rows[i][name] == "" for i in np.flatnonzero(none)), name
    direction = np.array([r["prognosis_direction"] for r in rows])
    assert (direction[none] == "none").all() and (direction[~none] == "low").all()  # wear: to the low warning
    eol = np.array([[float(rows[i][n]) for n in EOL] for i in np.flatnonzero(~none)])
    assert (eol[:, 0] <= eol[:, 1]).all() and (eol[:, 1] <= eol[:, 2]).all()
    # 10 h before the end of life the p50 is within 20 % (and the hour's countdown) of the truth
    near = np.flatnonzero(~none & (np.abs(hour - (FAIL_H - 10.0)) < 0.6))
    assert len(near)
    p50 = np.array([float(rows[i]["prognosis_to_eol_p50_h"]) for i in near])
    truth = FAIL_H - hour[near]
    assert (np.abs(p50 - truth) <= 0.2 * truth + 1.0).all(), (p50, truth)


def test_without_the_prognosis_the_timeline_has_no_prognosis_columns(wear, tmp_path):
    _, log, _ = wear
    c = cfgmod.load(None)
    assert c.prognosis.enabled is False
    out = tmp_path / "t.csv"
    replay_file(log, assemble(c).monitor, [TimelineWriter(out, c.quantity)], engine="columnar")
    header = out.read_text().split("\n", 1)[0].strip().split(",")
    assert tuple(header) == timeline_columns(MOTOR_SPEED) and not set(FIELDS) & set(header)


@pytest.mark.parametrize("impl", IMPLS)
def test_prognosis_cells_inf_and_absent_alike_by_either_formatter(tmp_path, impl):
    """inf (the estimate never gets there) as Python writes it, NaN (no estimate) an empty cell, as
    the timeline's other numbers: the C formatter and the arrays write the same bytes."""
    n = 5
    hours = np.array([math.nan, 12.345, math.inf, 0.0, 3999.5])
    c = TickColumns(
        t_s=np.arange(n, dtype=float),
        gate=np.full(n, int(Gate.EVALUATING), dtype=np.int8),
        measured=np.ones(n),
        predicted=np.ones(n),
        whitebox=np.ones(n),
        ratio_raw_pct=np.full(n, 100.0),
        ratio_filt_pct=np.full(n, 100.0),
        extra_leak_lpm=np.zeros(n),
        filt_valid=np.ones(n, dtype=bool),
        level=np.zeros(n, dtype=np.int8),
        reason=np.zeros(n, dtype=np.int8),
        time_below_s=np.zeros(n),
        prognosis_state=np.array([1, 2, 2, 3, 2], dtype=np.int8),
        **{name: hours for name in PROGNOSIS_HOURS},
    )
    out = {}
    for which in (impl, "numpy"):
        with helpers_impl(which):
            w = TimelineWriter(tmp_path / f"{which}.csv", MOTOR_SPEED, prognosis=True)
            w.start(0.0)
            w.ticks(c)
            w.close()
        out[which] = (tmp_path / f"{which}.csv").read_text()
    assert out[impl] == out["numpy"]
    rows = _rows(out[impl])
    assert [r["prognosis_state"] for r in rows] == ["none", "trend", "trend", "imminent", "trend"]
    for name in PROGNOSIS_HOURS:
        assert [r[name] for r in rows] == ["", "12.35", "inf", "0.00", "3999.50"], name
