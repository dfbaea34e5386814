"""The fleet report's service section is the service plan (:mod:`cmcan.fleet.plan`, one ranking):
its rows in the plan's order with their hours and dates, a small chart with numbered axes for each
machine with estimates; the statistics and the machines follow in the same order; each machine's
chart draws the thresholds that judged each stretch (the learning band while its baseline learned)
and its prognosis band.

The data sets are written here row by row (the data set's own writer), with known prognosis columns: a
simulated fleet would need hundreds of hours of wear before its prognosis sees a trend."""

from __future__ import annotations

import base64
import math
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyarrow")
pytest.importorskip("duckdb")

from cmcan.cli import main
from cmcan.fleet import dataset as ds
from cmcan.fleet import figures
from cmcan.fleet import plan as service
from cmcan.fleet.query import connect
from cmcan.fleet.report import build, service_series
from cmcan.monitor.baseline import Mode
from cmcan.monitor.prognosis import IMMINENT, NONE, STATE_CODES, TREND
from cmcan.monitor.tick import PROGNOSIS_HOURS

T0_S = 1767225600.0  # 2026-01-01
ROWS = 20  # timeline rows per log
NOT_CONFIGURED = 0
P10_H, P50_H, P90_H = (c for c in PROGNOSIS_HOURS if "_to_eol_" in c)


def _log(
    root: Path,
    machine: str,
    n: int,
    duration_h: float,
    state: list[int],
    p10_h: list[float],
    p50_h: list[float],
    p90_h: list[float],
    with_prognosis: bool = True,
    evaluated: list[int] | None = None,
    baseline: list[int] | None = None,
) -> None:
    """Commit one log of ``ROWS`` timeline rows spread over ``duration_h``; the ``n``-th log of its
    machine starts after the earlier ones (its operating hours follow theirs)."""
    first_s = T0_S + n * 86400.0
    log_time_h = np.linspace(0.0, duration_h, ROWS)
    rows = {
        "time_s": first_s + log_time_h * 3600.0,
        "log_time_h": log_time_h,
        "ticks": np.full(ROWS, 10, np.int64),
        "evaluated": np.asarray(evaluated or [10] * ROWS, np.int64),
        "cm_ratio_raw_pct": np.full(ROWS, 99.0),
        "cm_ratio_filt_pct": np.full(ROWS, 99.0),
    }
    if baseline is not None:
        rows["baseline_state"] = np.asarray(baseline, np.int64)
    if with_prognosis:
        rows["prognosis_state"] = np.asarray(state, np.int64)
        for name in PROGNOSIS_HOURS:  # the low-warning hours are not the report's: NaN
            rows[name] = np.full(ROWS, math.nan)
        rows.update({P10_H: np.asarray(p10_h), P50_H: np.asarray(p50_h), P90_H: np.asarray(p90_h)})
    prov = ds.Provenance(f"{machine}{n}".encode().hex().ljust(64, "0"), "c" * 64, "d" * 64, "e" * 64)
    writer = ds.LogWriter(root, machine, prov)
    writer.add_rows("timeline", rows)
    summary = {
        "log": f"/logs/{machine}_{n}.log",
        "log_name": f"{machine}_{n}.log",
        "first_time_s": first_s,
        "last_time_s": first_s + duration_h * 3600.0,
        "duration_h": duration_h,
        "evaluated_h": duration_h,
        "warnings_low": 0,
        "warnings_high": 0,
        "faults": 0,
        "final_level": "ok",
        "threshold_low_pct": 98.0,
        "threshold_high_pct": 102.0,
        "learning_low_pct": 95.0 if baseline is not None else None,
        "learning_high_pct": 105.0 if baseline is not None else None,
        "count_frames_total": 1000,
        "fit": "fits",
        "fit_median_pct": 100.0,
    }
    writer.commit(summary, ds.day_of(first_s))


def _constant(root: Path, machine: str, state: int, p10_h: float, p50_h: float, p90_h: float, n: int = 0) -> None:
    _log(root, machine, n, 10.0, [state] * ROWS, [p10_h] * ROWS, [p50_h] * ROWS, [p90_h] * ROWS)


TR, IM, NO = STATE_CODES[TREND], STATE_CODES[IMMINENT], STATE_CODES[NONE]


@dataclass(frozen=True)
class Built:
    root: Path
    page: str = field(repr=False)  # a failing test shows the data set, not the page's base64


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Built:
    root = ds.open_dataset(tmp_path_factory.mktemp("svc") / "ds", create=True)
    # imminent: first, though its p50 is further out than m-soon's; its p90 never gets there
    _constant(root, "m-imminent", IM, 12.0, 80.0, math.inf)
    _constant(root, "m-soon-b", TR, 40.0, 60.0, 120.0)
    _constant(root, "m-soon-a", TR, 30.0, 60.0, 110.0)  # same p50 as m-soon-b: p10 decides
    _constant(root, "m-never", TR, 300.0, math.inf, math.inf)  # a trend whose p50 never gets there: last
    # m-late: two logs (its second starts at operating hour 10); no trend in the first, an estimate from the
    # second's row 10, a row without one (NaN), then the latest row, not evaluated (the gate held the
    # tick back), with the estimate that came at it: the prognosis estimates on its operating clock,
    # whatever the gate says of the tick (seed 47's m016 of bench_fleet_plan: imminent on its last rows,
    # "no trend" in the plan while only evaluated rows were read)
    _constant(root, "m-late", NO, math.nan, math.nan, math.nan)
    hours = [math.nan] * 10 + [500.0 - i for i in range(8)] + [math.nan, 40.0]
    state = [NO] * 10 + [TR] * 10
    evaluated = [10] * 19 + [0]
    p10 = [h - 100 for h in hours[:-1]] + [20.0]
    p90 = [h + 200 for h in hours[:-1]] + [80.0]
    _log(root, "m-late", 1, 9.5, state, p10, hours, p90, evaluated=evaluated)
    # had a trend, none now: "no trend"
    _log(root, "m-flat", 0, 10.0, [TR] * 10 + [NO] * 10, [50.0] * 20, [90.0] * 10 + [math.nan] * 10, [150.0] * 20)
    _constant(root, "m-off", NOT_CONFIGURED, math.nan, math.nan, math.nan)  # no prognosis configured
    return Built(root, build(root))


def _table(page: str, table_id: str) -> list[list[str]]:
    table = re.search(rf"<table id='{table_id}'>(.*?)</table>", page, re.S)
    assert table is not None
    rows = re.findall(r"<tr class='([\w -]+)'>(.*?)</tr>", table.group(1), re.S)
    return [[cls, *[re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", r, re.S)]] for cls, r in rows]


# the plan: imminent, trend by p10 (m-late's latest row's 20 h first; m-never's p50 never gets there, its
# p10 is the largest), then no trend (m-flat lost its trend), then the machine without a prognosis
PLAN = ["m-imminent", "m-late", "m-soon-a", "m-soon-b", "m-never", "m-flat", "m-off"]


def test_the_service_section_is_the_plan_and_everything_follows_its_order(fleet):
    page = fleet.page
    rows = _table(page, "ranking")
    assert [r[2] for r in rows] == PLAN == [r.machine for r in service.build(fleet.root, None, T0_S)]
    assert [r[1] for r in rows] == [str(i) for i in range(1, len(PLAN) + 1)]
    assert [r[3] for r in rows] == ["imminent", "trend", "trend", "trend", "trend", "no trend", "no prognosis"]
    # one ranking: the statistics and the machines' charts in the plan's order, with the plan's rank
    assert [r[2] for r in _table(page, "statistics")] == PLAN
    assert [r[1] for r in _table(page, "statistics")] == [str(i) for i in range(1, len(PLAN) + 1)]
    assert re.findall(r"<h3 id='m-([\w-]+)'>", page) == PLAN
    assert page.index("id='service'") < page.index("id='overview'") < page.index("id='machines'")
    assert "id='service-table'" not in page and "Hours to service" not in page  # no second ranking


def test_each_row_has_the_plans_hours_and_states(fleet):
    by_machine = {r[2]: r for r in _table(fleet.page, "ranking")}
    # to end of life p10 / p50 / p90 as the plan has them ("never": the curve does not get there)
    assert by_machine["m-imminent"][8] == "12 / 80 / never"
    assert by_machine["m-soon-a"][8] == "30 / 60 / 110"
    assert by_machine["m-never"][8] == "300 / never / never"
    assert by_machine["m-late"][8] == "20 / 40 / 80"  # the estimate of its latest row, evaluated or not
    assert by_machine["m-imminent"][4] == "ok" and by_machine["m-imminent"][5] == "not configured"
    assert by_machine["m-off"][6] == "not configured"
    totals = re.search(r"<p id='plan-totals'>(.*?)</p>", fleet.page).group(1)
    assert totals == "7 machines: 1 imminent, 4 trend, 1 no trend, 1 no prognosis."


def _png_size(img_tag: str) -> tuple[int, int]:
    data = base64.b64decode(re.search(r"base64,([A-Za-z0-9+/=]+)", img_tag).group(1))
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def test_a_small_chart_for_each_machine_with_estimates(fleet):
    page = fleet.page
    table = re.search(r"<table id='ranking'>(.*?)</table>", page, re.S).group(1)
    charted = [m for m in PLAN if re.search(rf"<a href='#m-{m}'>.*?</tr>", table, re.S).group(0).count("<img")]
    assert charted == ["m-imminent", "m-late", "m-soon-a", "m-soon-b", "m-never", "m-flat"]  # had estimates
    imgs = re.findall(r"<img [^>]*>", table)
    w, h = _png_size(imgs[0])
    assert w <= 300 and h <= 130  # small, in a table cell
    assert "<script" not in page and "http" not in page.split("</style>", 1)[1]


@pytest.fixture
def drawn(monkeypatch) -> list:
    """The figures drawn, kept open instead of turned into PNG bytes."""
    figs: list = []
    monkeypatch.setattr(figures, "png_bytes", lambda fig: figs.append(fig) or b"")
    return figs


def test_the_small_chart_has_numbered_axes(drawn):
    figures.plot_service_spark([0.0, 5.0, 10.0], [30.0, 25.0, 20.0], [60.0, 55.0, 50.0], [math.inf] * 3)
    (ax,) = drawn[0].axes
    drawn[0].canvas.draw()
    assert ax.axison and ax.get_xlabel() == "operating h" and ax.get_ylabel() == "to EOL h"
    assert [t.get_text() for t in ax.get_xticklabels() if t.get_text()] and ax.get_ylim()[1] > 60.0
    assert [t.get_text() for t in ax.get_yticklabels() if t.get_text()]


def test_a_machines_chart_draws_the_thresholds_that_judged_and_its_prognosis_band(drawn):
    h = np.arange(10.0)
    learning = [True] * 4 + [False] * 6
    prognosis = ([5.0, 9.0], [40.0, 30.0], [60.0, 50.0], [90.0, 80.0])
    figures.plot_machine(h, h + 95, h + 95, 98.0, 102.0, [], [0.0], "m", learning=(learning, 95.0, 105.0),
                         prognosis=prognosis)  # fmt: skip
    ratio, band = drawn[0].axes
    low = next(line for line in ratio.get_lines() if str(line.get_label()).startswith("low threshold"))
    assert low.get_label() == "low threshold 98 % (95 % while learning)"
    assert list(low.get_ydata()) == [95.0] * 4 + [98.0] * 6
    assert band.get_ylabel() == "to end of life (h)" and [line.get_label() for line in band.get_lines()] == ["p50"]
    figures.plot_machine(h, h + 95, h + 95, 98.0, 102.0, [], [0.0], "m")  # no baseline, no prognosis: one panel
    assert len(drawn[1].axes) == 1


def test_the_report_passes_the_learning_band_where_the_baseline_learned(tmp_path, monkeypatch):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    baseline = [int(Mode.LEARNING)] * 8 + [int(Mode.MONITORING)] * 12
    _log(
        root, "m-new", 0, 10.0, [NO] * ROWS, [math.nan] * ROWS, [math.nan] * ROWS, [math.nan] * ROWS, baseline=baseline
    )
    seen = {}
    monkeypatch.setattr("cmcan.fleet.figures.plot_machine", lambda *a, **k: seen.update(k) or b"")
    build(root)
    mask, low, high = seen["learning"]
    assert (low, high) == (95.0, 105.0) and mask == [True] * 8 + [False] * 12


def test_a_sparkline_draws_the_estimates_on_the_operating_hours(fleet):
    con = connect(fleet.root)
    try:
        traces = service_series(con)
    finally:
        con.close()
    assert set(traces) == {"m-imminent", "m-soon-a", "m-soon-b", "m-never", "m-late", "m-flat"}
    hours, p10_h, p50_h, p90_h = traces["m-late"]
    # its second log's rows 10-17 (offset 10 h, 0.5 h apart): neither the NaN row nor the one not evaluated
    assert hours == pytest.approx([10.0 + 0.5 * i for i in range(10, 18)])
    assert p50_h == [500.0 - i for i in range(8)] and p10_h[0] == 400.0 and p90_h[-1] == 693.0
    assert traces["m-never"][2][0] == math.inf  # drawn off the top, not dropped


def test_a_data_set_without_any_prognosis_says_so_in_one_line(tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    _constant(root, "m-off", NOT_CONFIGURED, math.nan, math.nan, math.nan)
    _log(root, "m-old", 0, 5.0, [], [], [], [], with_prognosis=False)  # written before the prognosis
    page = build(root)
    section = page.split("<h2 id='service'>", 1)[1].split("<h2", 1)[0]
    assert "No machine in this data set has a prognosis configured" in section
    assert "<img" not in section  # the plan's rows, no chart


def test_a_data_set_written_before_the_prognosis_reports(tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    _log(root, "m-old", 0, 5.0, [], [], [], [], with_prognosis=False)  # no prognosis column in any file
    out = tmp_path / "r.html"
    assert main(["fleet", "report", str(root), "--out", str(out)]) == 0
    assert "No machine in this data set has a prognosis configured" in out.read_text()
