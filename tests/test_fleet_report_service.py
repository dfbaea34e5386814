"""The fleet report's "Hours to service": the machines the prognosis sees wearing, imminent first, then by
hours to end of life, each with its interval, the hour of the estimate and a sparkline; machines with no
trend named after the table, machines without a prognosis counted apart; one line when no machine has one.

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
from cmcan.fleet.query import connect
from cmcan.fleet.report import build, service_series
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
    # second's row 10, its last row without one (NaN: skipped), then a row not evaluated (not counted)
    _constant(root, "m-late", NO, math.nan, math.nan, math.nan)
    hours = [math.nan] * 10 + [500.0 - i for i in range(8)] + [math.nan, 1.0]
    state = [NO] * 10 + [TR] * 9 + [NO]
    evaluated = [10] * 19 + [0]
    _log(root, "m-late", 1, 9.5, state, [h - 100 for h in hours], hours, [h + 200 for h in hours], evaluated=evaluated)
    # had a trend, none now: "no trend"
    _log(root, "m-flat", 0, 10.0, [TR] * 10 + [NO] * 10, [50.0] * 20, [90.0] * 10 + [math.nan] * 10, [150.0] * 20)
    _constant(root, "m-off", NOT_CONFIGURED, math.nan, math.nan, math.nan)  # no prognosis configured
    return Built(root, build(root))


def _service_table(page: str) -> list[list[str]]:
    table = re.search(r"<table id='service-table'>(.*?)</table>", page, re.S)
    assert table is not None
    rows = re.findall(r"<tr class='(\w+)'>(.*?)</tr>", table.group(1), re.S)
    return [[cls, *[re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", r, re.S)]] for cls, r in rows]


def test_machines_are_ordered_imminent_first_then_by_hours_to_end_of_life(fleet):
    page = fleet.page
    rows = _service_table(page)
    assert [r[2] for r in rows] == ["m-imminent", "m-soon-a", "m-soon-b", "m-late", "m-never"]
    assert [r[0] for r in rows] == ["imminent", "trend", "trend", "trend", "trend"]
    assert page.index("id='ranking'") < page.index("id='service'") < page.index("id='machines'")


def test_each_row_has_its_interval_and_the_operating_hour_of_its_estimate(fleet):
    page = fleet.page
    by_machine = {r[2]: r for r in _service_table(page)}
    # p50, "p10 - p90", estimated at (operating hours: the log's offset added)
    assert by_machine["m-imminent"][4:7] == ["80.0", "12.0 &ndash; never", "10.0"]
    assert by_machine["m-soon-a"][4:7] == ["60.0", "30.0 &ndash; 110.0", "10.0"]
    assert by_machine["m-never"][4:7] == ["never", "300.0 &ndash; never", "10.0"]
    # the second log's row 17 at 8.5 h: its row 18 has no estimate (its state, trend, counts), row 19 was
    # not evaluated
    assert by_machine["m-late"][4:7] == ["493.0", "393.0 &ndash; 693.0", "18.5"]


def _png_size(img_tag: str) -> tuple[int, int]:
    data = base64.b64decode(re.search(r"base64,([A-Za-z0-9+/=]+)", img_tag).group(1))
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def test_one_inline_sparkline_per_ranked_machine(fleet):
    page = fleet.page
    table = re.search(r"<table id='service-table'>(.*?)</table>", page, re.S).group(1)
    imgs = re.findall(r"<img [^>]*>", table)
    assert len(imgs) == 5
    assert all('src="data:image/png;base64,' in i for i in imgs)
    w, h = _png_size(imgs[0])
    assert w <= 300 and h <= 80  # sparkline-sized
    assert "<script" not in page and "http" not in page.split("</style>", 1)[1]


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


def test_no_trend_is_listed_and_no_prognosis_is_not_ranked(fleet):
    page = fleet.page
    no_trend = re.search(r"<p id='service-no-trend'>(.*?)</p>", page, re.S).group(1)
    assert "m-flat" in no_trend and "(1)" in no_trend
    off = re.search(r"<p id='service-off'>(.*?)</p>", page, re.S).group(1)
    assert "1 machine without a prognosis configured" in off and "m-off" in off and "not ranked" in off
    ranked = [r[2] for r in _service_table(page)]
    assert "m-flat" not in ranked and "m-off" not in ranked


def test_a_data_set_without_any_prognosis_says_so_in_one_line(tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    _constant(root, "m-off", NOT_CONFIGURED, math.nan, math.nan, math.nan)
    _log(root, "m-old", 0, 5.0, [], [], [], [], with_prognosis=False)  # written before the prognosis
    page = build(root)
    section = page.split("<h2 id='service'>", 1)[1].split("<h2", 1)[0]
    assert "No machine in this data set has a prognosis configured" in section
    assert "<table" not in section and "<img" not in section


def test_a_data_set_written_before_the_prognosis_reports(tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    _log(root, "m-old", 0, 5.0, [], [], [], [], with_prognosis=False)  # no prognosis column in any file
    out = tmp_path / "r.html"
    assert main(["fleet", "report", str(root), "--out", str(out)]) == 0
    assert "No machine in this data set has a prognosis configured" in out.read_text()
