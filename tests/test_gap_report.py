"""What the gap report shows a reader: the headline and figures over the points the diagnosis judges
(the others counted apart), a hold-out that tests no extrapolation called degenerate, an answer chosen
by the pair search said to be so, no pinned fit presented as a finding, the bench's rates with their
counts."""

from __future__ import annotations

import argparse
import json
import re

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from cmcan.cli.gap import bench_table
from cmcan.gap import bench
from cmcan.gap import data as gapdata
from cmcan.gap.context import MIN_REACH_C, holdout_mask, holdout_reach
from cmcan.gap.diagnose import diagnose
from cmcan.gap.effects import Inputs, Scale
from cmcan.gap.figures import heatmap_figure, variables_figure
from cmcan.sim.physics import DriveParams
from tests.conftest import ROOT, run_cli

P = DriveParams()
ZEMA = ROOT / "examples" / "zema-rig"
ZEMA_ARGS = (
    str(ZEMA / "data" / "cycles.csv"),
    "--points",
    str(ZEMA / "points.yaml"),
    "--drive",
    str(ZEMA / "drive.yaml"),
    "--quantity",
    "flow_lpm",
)


def _rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2)))


@pytest.fixture(scope="module")
def hot_sensor(tmp_path_factory):
    """A wheel loader whose oil-temperature sensor reads 6 C high: a right answer (the sensor's offset)
    on data that reach the relief valve and zero pressure, which the diagnosis does not judge."""
    tmp = tmp_path_factory.mktemp("hot")
    scen = tmp / "hot_sensor.yaml"
    scen.write_text(
        "name: hot_sensor\nseed: 4\nduration_h: 0.2\n"
        "oil: {model: profile, points: [[0, 30], [0.1, 85], [0.2, 40]]}\n"
        "duty: {kind: wheel_loader}\n"
        "sensors: {errors: {temp_c: {offset: 6.0}}}\n"
    )
    csv = tmp / "run.csv"
    res = run_cli("simulate", str(scen), "--out", str(csv))
    assert res.returncode == 0, res.stderr
    d = gapdata.load(csv)
    diag, arrays = diagnose(d, P)
    return d, diag, arrays


def test_the_headline_is_the_gap_at_the_judged_points_with_the_others_counted(hot_sensor):
    d, diag, arrays = hot_sensor
    assert "temp_sensor_offset" in diag.selected
    j = arrays.judged
    cov = diag.judged
    assert cov.judged == int(j.sum()) and cov.total == len(d.y)
    # every unjudged point has its reason, and this run reaches both ends the simulator cannot follow
    assert cov.near_relief > 0 and cov.no_pressure > 0
    assert cov.near_relief + cov.no_pressure + cov.transient == cov.unjudged
    g0, g1 = d.y - arrays.y_before, d.y - arrays.y_after
    assert diag.before.rmse == pytest.approx(_rmse(g0[j]))
    assert diag.after.rmse == pytest.approx(_rmse(g1[j]))
    assert diag.before.all_rmse == pytest.approx(_rmse(g0))
    # over every point the unjudged points (hundreds of rpm at the relief valve) hide the answer; over the
    # judged ones it shows
    assert diag.after.all_rmse > 0.9 * diag.before.all_rmse
    assert diag.after.rmse < 0.5 * diag.before.rmse


def test_the_gap_figure_is_scaled_to_the_judged_points_and_shows_the_others_apart(hot_sensor):
    d, diag, arrays = hot_sensor
    fig = variables_figure(diag, d, arrays)
    sets = {s.key: s for s in fig.sets}
    j, hold = arrays.judged, arrays.holdout
    assert (sets["not_judged"].mask == ~j).all()
    assert (sets["before_fit"].mask == (~hold & j)).all() and (sets["after_withheld"].mask == (hold & j)).all()
    lo, hi = fig.ylim
    for key in ("before_fit", "before_withheld", "after_withheld"):
        s = sets[key]
        shown = s.gap[s.mask]
        assert lo <= shown.min() and shown.max() <= hi, key  # no judged point off the axis
        assert f"({int(s.mask.sum())})" in s.label
    out = sets["not_judged"]
    beyond = int(np.sum((out.gap[out.mask] < lo) | (out.gap[out.mask] > hi)))
    assert beyond > 0 and f"; {beyond} beyond the axis" in out.label
    assert f"({diag.judged.unjudged}:" in out.label and "near the relief valve" in out.label
    # the axis is the judged points', far narrower than what the unjudged points span
    assert hi - lo < 0.5 * np.ptp(out.gap[out.mask])
    assert f"{int(j.sum())} of {len(d.y)} judged points" in fig.title and "temp_sensor_offset" in fig.title


def test_the_heat_map_is_over_judged_points_and_has_no_data_cells_apart(hot_sensor, tmp_path):
    d, diag, arrays = hot_sensor
    hm = heatmap_figure(d, arrays)
    j = arrays.judged
    assert hm.counts.sum() == j.sum()
    empty = hm.counts == 0
    assert np.isnan(hm.mean[empty]).all() and np.isfinite(hm.mean[~empty]).all()
    assert hm.empty_cells == int(empty.sum())
    g0 = (d.y - arrays.y_before)[j]
    assert np.nansum(hm.mean * hm.counts) == pytest.approx(g0.sum(), rel=1e-9, abs=1e-9)
    # the judged points' pressures only: the unjudged ones at the relief valve set no cell
    assert hm.dp_edges[-1] == pytest.approx(d.x.dp_bar[j].max())
    assert hm.dp_edges[-1] < d.x.dp_bar.max()
    from cmcan.gap.report import LABELS
    from cmcan.plots import plot_gap

    assert plot_gap(tmp_path, variables_figure(diag, d, arrays), hm, LABELS, diag.unit) == [
        "gap_heatmap.png",
        "gap_vs_variables.png",
    ]


def _table(temps: np.ndarray) -> gapdata.GapData:
    n = len(temps)
    x = Inputs(
        np.arange(n, dtype=float),
        np.full(n, 2000.0),
        np.linspace(30.0, 70.0, n),
        np.linspace(150.0, 160.0, n),
        temps,
        np.zeros(n),
        np.arange(n),
    )
    y = np.full(n, 1000.0)
    return gapdata.GapData(x, y, np.ones(n, bool), x.dp_bar, x.dp_bar, "motor_speed_rpm", "t.csv", "points")


@settings(max_examples=60, deadline=None)
@given(lo=st.floats(20.0, 80.0), span=st.floats(0.5, 30.0), n=st.integers(40, 400))
def test_a_holdout_is_degenerate_exactly_when_it_lies_too_close_to_the_fit_part(lo, span, n):
    temps = np.linspace(lo, lo + span, n)
    d = _table(temps)
    hold, spec = holdout_mask(d, "temp_c:top25")
    r = holdout_reach(d, hold, np.ones(n, bool), spec, Scale.of(P, d.x, d.y))
    reach = abs(np.median(temps[hold]) - np.median(temps[~hold]))
    assert r.reach == pytest.approx(reach)
    assert r.needed == MIN_REACH_C
    event("degenerate" if r.degenerate else "a real extrapolation")
    assert r.degenerate == (reach < MIN_REACH_C)
    if r.degenerate:
        assert "degenerate" in r.message and f"{temps[hold].min():.4g}" in r.message
    # the pressure spans 10 bar of 160: a hold-out by pressure is always degenerate here
    hold_dp, spec_dp = holdout_mask(d, "dp_bar:top25")
    assert holdout_reach(d, hold_dp, np.ones(n, bool), spec_dp, Scale.of(P, d.x, d.y)).degenerate


def _zema(tmp_path, *extra):
    out = tmp_path / "z"
    res = run_cli("gap", "diagnose", *ZEMA_ARGS, "--out", str(out), "--no-plots", *extra)
    assert res.returncode == 0, res.stderr
    return res.stdout, json.loads((out / "report.json").read_text()), (out / "report.md").read_text()


def test_a_holdout_over_oil_that_barely_varies_is_called_degenerate(tmp_path):
    """Healthy cycles with the oil at 35-36.5 C, withheld by temperature: said, and never high."""
    out, rep, md = _zema(tmp_path, "--where", "pump_leak=0", "--where", "ts1_c<36.5", "--holdout", "temp_c:top25")
    h = rep["holdout"]
    assert h["degenerate"] and h["reach"] < h["reach_needed"] == MIN_REACH_C
    assert "degenerate hold-out" in rep["verdict"] and "hold-out: the withheld part" in out
    assert "**Degenerate hold-out:**" in md
    assert rep["confidence"] is None or rep["confidence"]["level"] != "high"
    if rep["confidence"]:
        assert any("degenerate" in r for r in rep["confidence"]["reasons"])


def test_the_default_holdout_is_one_that_tests_an_extrapolation(tmp_path):
    """The leaking pump's oil spans 10 C (less than the 15 C that once decided) while its pressure
    spans 3 bar of 160: the hottest quarter, not the degenerate top pressure quarter."""
    _, rep, _ = _zema(tmp_path, "--where", "pump_leak=1")
    assert rep["holdout"]["spec"] == "temp_c:top25" and not rep["holdout"]["degenerate"]
    _, rep, _ = _zema(tmp_path / "dp", "--where", "pump_leak=1", "--holdout", "dp_bar:top25")
    assert rep["holdout"]["degenerate"]


def test_an_answer_of_the_pair_search_says_so_and_no_pinned_fit_reads_as_a_finding(tmp_path):
    out, rep, md = _zema(tmp_path, "--where", "pump_leak=0")
    ps = rep["pair_search"]
    assert ps is not None and ps["chosen"] is not None
    fitted = [f["name"] for f in rep["fitted"]]
    assert sorted(ps["chosen"]) == sorted(fitted)
    chosen = next(p for p in ps["pairs"] if p["names"] == ps["chosen"])
    assert chosen["eligible"] and chosen["heldout_reduction"] >= ps["needed"]
    assert f"chosen by the pair search: {' + '.join(ps['chosen'])}" in out
    assert "**The answer was chosen by the pair search" in md and "### Pairs fitted jointly" in md
    # each effect alone: a value pinned on its bound without significance is shown as the bound
    alone = md.split("### Each effect alone")[1].split("###")[0]
    pinned = [c for c in rep["candidates"] if not c["significant"] and any(q["at_bound"] for q in c["params"])]
    assert pinned, "the rig's single effects run into their bounds"
    for c in pinned:
        row = next(line for line in alone.splitlines() if line.startswith(f"| {c['name']} |"))
        assert "pinned at its bound" in row and "no finding" in row
        for q in c["params"]:
            assert f"{q['value']:.4g} ±" not in row, row
    # the effects that may be named come first
    rows = [line.split("|")[1].strip() for line in alone.splitlines() if line.startswith("| ") and "---" not in line]
    eligible = {c["name"]: c["eligible"] for c in rep["candidates"]}
    flags = [eligible[n] for n in rows[1:]]
    assert flags == sorted(flags, reverse=True)


def _score(case: str, right: bool, level: str | None = None, groups=(("x",),)) -> bench.Score:
    return bench.Score(0, case, ("x",), "sweep", (1.0,), groups, level, 0, right, 0.9, False, {})


def test_the_bench_gives_every_rate_with_its_counts():
    scores = [
        *(_score("single", True, "high") for _ in range(5)),
        _score("single", False, "medium"),
        _score("none", True, None, ()),
        _score("two", False, "low"),
        _score("two", True, "medium"),
        _score("outside", True, None, ()),
    ]
    s = bench.summarize(scores)
    assert (s.single_right.k, s.single_right.n) == (5, 6) and s.single_right_rate == pytest.approx(5 / 6)
    assert (s.two_found.k, s.two_found.n) == (1, 2) and (s.region_located.k, s.region_located.n) == (0, 0)
    lines = bench_table(s, argparse.Namespace(trials=10, seed=1))
    text = "\n".join(lines)
    assert "| single effects named right | 5/6 (83.3 %) |" in text
    assert "| two effects: both found | 1/2 (50.0 %) |" in text
    assert "| high-pressure leak located at high pressure | 0/0 (n/a) |" in text
    assert "| high | 5 | 5 | 5/5 (100.0 %) | 5 |" in text
    # no rate without its counts: every % in the figure table follows a k/n
    figure_rows = [line for line in lines[:16] if "%" in line and "median" not in line]
    assert figure_rows and all(re.search(r"\d+/\d+ \(\d+\.\d %\)", line) for line in figure_rows)
