"""``cmcan fleet plan``: one ranked row per machine. The ranking rule and the dates on facts given
here (pure), then the command over a data set written row by row with the data set's own writer."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from cmcan.fleet.plan import GROUPS, Facts, plan
from cmcan.monitor.baseline import Mode
from cmcan.monitor.prognosis import IMMINENT, NONE, STATE_CODES, TREND

T0_S = 1767225600.0  # 2026-01-01 00:00 UTC
DAY_S = 86400.0
TR, IM, NO = STATE_CODES[TREND], STATE_CODES[IMMINENT], STATE_CODES[NONE]
NAN3 = (math.nan, math.nan, math.nan)


def facts(machine: str, **over) -> Facts:
    base = dict(
        machine=machine,
        last_heard_s=T0_S + 10 * DAY_S,
        operating_h=100.0,
        level="ok",
        prognosis_state=NO,
        baseline_state=Mode.MONITORING,
        recent_h=80.0,
        recent_days=10.0,
        fit="fits",
    )
    return Facts(**{**base, **over})


def test_the_ranking_is_one_rule_over_every_group():
    machines = [
        facts("no-prognosis", prognosis_state=0, baseline_state=0),
        facts("flat"),
        facts("learning", baseline_state=Mode.LEARNING),
        facts("suspect", baseline_state=Mode.SUSPECT),
        facts("misfit", fit="does_not_fit"),
        facts("trend-late", prognosis_state=TR, to_eol_h=(90.0, 120.0, 200.0)),
        facts("trend-b", prognosis_state=TR, to_eol_h=(40.0, 70.0, 110.0)),
        facts("trend-a", prognosis_state=TR, to_eol_h=(30.0, 70.0, 110.0)),  # same p50 as trend-b: p10 decides
        facts("imminent", prognosis_state=IM, to_eol_h=(12.0, 80.0, math.inf)),
        # warns now while the prognosis has no trend yet: first all the same, never "no trend"
        facts("warns", level="low", prognosis_state=NO),
    ]
    rows = plan(machines, T0_S + 10 * DAY_S)
    assert [r.machine for r in rows] == [
        "warns",
        "imminent",
        "trend-a",
        "trend-b",
        "trend-late",
        "misfit",
        "suspect",
        "learning",
        "flat",
        "no-prognosis",
    ]
    assert [r.rank for r in rows] == list(range(1, 11))
    assert [r.group for r in rows] == [GROUPS[i] for i in (0, 1, 2, 2, 2, 3, 3, 4, 5, 6)]
    warns = rows[0]
    assert warns.to_warning_h == 0.0 and "warning_without_trend" in warns.flags
    assert rows[1].to_eol_h == [12.0, 80.0, math.inf] and "eol_not_reached" in rows[1].flags
    assert rows[1].due_date[2] is None
    assert {r.machine: r.baseline_state for r in rows}["no-prognosis"] == "not_configured"
    assert {r.machine: r.prognosis_state for r in rows}["no-prognosis"] == "not_configured"


def test_dates_follow_the_machines_own_utilisation():
    # 80 h in the last 10 days: 8 h a day; 40 h to the p50 is 5 days after it was last heard
    f = facts("m", prognosis_state=TR, direction=1, to_warning_h=16.0, to_eol_h=(24.0, 40.0, 80.0))
    (r,) = plan([f], f.last_heard_s)
    assert r.utilisation_h_per_day == 8.0
    assert r.due_date == ["2026-01-14", "2026-01-16", "2026-01-21"]
    assert r.warning_date == "2026-01-13" and r.direction == "low"
    # the same hours at twice the duty: the dates come twice as soon
    (busy,) = plan([dataclasses.replace(f, recent_h=160.0)], f.last_heard_s)
    assert busy.due_date == ["2026-01-12", "2026-01-13", "2026-01-16"]
    # a machine that did not run in its recent days: no date, flagged
    (idle,) = plan([dataclasses.replace(f, recent_h=0.0)], f.last_heard_s)
    assert idle.due_date == [None, None, None] and "no_utilisation" in idle.flags


def test_a_machine_not_heard_for_a_week_is_flagged_stale():
    f = facts("m")
    assert "stale" not in plan([f], f.last_heard_s + 6 * DAY_S)[0].flags
    r = plan([f], f.last_heard_s + 8 * DAY_S)[0]
    assert "stale" in r.flags and r.last_heard_days == 8.0


# -- the command over a data set -------------------------------------------------------------------

ROWS = 24


def _log(
    root: Path,
    machine: str,
    day: int,
    level: list[str],
    state: list[int],
    p50: list[float],
    summary: dict | None = None,
    **cols,
) -> None:
    """One 8 h log on calendar day ``day``: ``ROWS`` timeline rows with these columns (``summary``: more
    of its logs row)."""
    from cmcan.fleet import dataset as ds

    first_s = T0_S + day * DAY_S
    log_time_h = np.linspace(0.0, 8.0, ROWS)
    p50a = np.asarray(p50, float)
    rows = {
        "time_s": first_s + log_time_h * 3600.0,
        "log_time_h": log_time_h,
        "ticks": np.full(ROWS, 10, np.int64),
        "evaluated": np.full(ROWS, 10, np.int64),
        "cm_ratio_raw_pct": np.full(ROWS, 99.0),
        "cm_ratio_filt_pct": np.full(ROWS, 99.0),
        "warning_level": np.asarray(level, object),
        "baseline_state": np.full(ROWS, int(Mode.MONITORING), np.int64),
        "prognosis_state": np.asarray(state, np.int64),
        "prognosis_direction": np.where(np.asarray(state) >= TR, 1, 0).astype(np.int64),
        "prognosis_to_warning_h": np.full(ROWS, math.nan),
        "prognosis_to_eol_p10_h": p50a * 0.6,
        "prognosis_to_eol_p50_h": p50a,
        "prognosis_to_eol_p90_h": p50a * 2.0,
        **cols,
    }
    prov = ds.Provenance(f"{machine}{day}".encode().hex().ljust(64, "0"), "c" * 64, "d" * 64, "e" * 64)
    writer = ds.LogWriter(root, machine, prov)
    writer.add_rows("timeline", rows)
    writer.commit(
        {
            "log": f"/logs/{machine}_{day}.log",
            "log_name": f"{machine}_{day}.log",
            "first_time_s": first_s,
            "last_time_s": first_s + 8 * 3600.0,
            "duration_h": 8.0,
            "evaluated_h": 8.0,
            "warnings_low": 0,
            "warnings_high": 0,
            "faults": 0,
            "final_level": level[-1],
            "threshold_low_pct": 98.0,
            "threshold_high_pct": 102.0,
            "count_frames_total": 1000,
            "fit": "fits",
            "fit_median_pct": 100.0,
            "end_of_life": "wear: the CM ratio at 90 %",
            **(summary or {}),
        },
        ds.day_of(first_s),
    )


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    pytest.importorskip("duckdb")
    pytest.importorskip("pyarrow")
    from cmcan.fleet import dataset as ds

    root = ds.open_dataset(tmp_path_factory.mktemp("plan") / "ds", create=True)
    # m-wear: a trend from day 0 (p50 60 h), warning low from day 3's second half
    for day in range(4):
        level = ["ok"] * ROWS if day < 3 else ["ok"] * 12 + ["low"] * 12
        _log(root, "m-wear", day, level, [TR] * ROWS, [60.0 - 8 * day] * ROWS)
    for day in range(4):  # m-ok: healthy, no trend
        _log(root, "m-ok", day, ["ok"] * ROWS, [NO] * ROWS, [math.nan] * ROWS)
    return root


def _plan(capsys, *args: str) -> tuple[int, dict]:
    from cmcan.cli import main

    code = main(["fleet", "plan", *args])
    got = capsys.readouterr()
    return code, (json.loads(got.out) if "--json" in args and code == 0 else {"text": got.out, "err": got.err})


def test_the_plan_command_ranks_the_data_sets_machines(dataset, capsys):
    code, doc = _plan(capsys, str(dataset), "--json")
    assert code == 0
    rows = {r["machine"]: r for r in doc["machines"]}
    assert [r["machine"] for r in doc["machines"]] == ["m-wear", "m-ok"]
    wear = rows["m-wear"]
    for key in ("machine", "rank", "warning_level", "baseline_state", "prognosis_state", "direction",
                "to_warning_h", "to_eol_h", "due_date", "utilisation_h_per_day", "flags"):  # fmt: skip
        assert key in wear
    assert (wear["warning_level"], wear["group"], wear["direction"]) == ("low", "warning_now", "low")
    assert wear["to_eol_h"] == pytest.approx([36 * 0.6, 36.0, 72.0])
    assert wear["end_of_life"] == "wear: the CM ratio at 90 %"
    # 32 operating hours over the 3 1/3 calendar days since day 0: 9.6 h a day; p50 36 h: 3.75 days
    assert wear["utilisation_h_per_day"] == pytest.approx(32.0 / (3 + 8 / 24), rel=1e-3)
    assert wear["due_date"][1] == "2026-01-08"
    ok = rows["m-ok"]
    assert (ok["group"], ok["prognosis_state"], ok["to_eol_h"]) == ("no_trend", "none", [None, None, None])


def test_the_plan_at_an_earlier_time_sees_only_the_rows_up_to_it(dataset, capsys):
    code, doc = _plan(capsys, str(dataset), "--json", "--at", "2026-01-02T12:00")
    assert code == 0
    wear = next(r for r in doc["machines"] if r["machine"] == "m-wear")
    assert (wear["warning_level"], wear["group"]) == ("ok", "trend")
    assert wear["to_eol_h"][1] == pytest.approx(52.0)  # day 1's estimate
    assert wear["last_heard_days"] == pytest.approx(0.5 - 8 / 24, abs=0.01)


def test_the_plan_as_a_table_and_a_bad_time(dataset, capsys):
    code, doc = _plan(capsys, str(dataset))
    assert code == 0
    text = doc["text"]
    assert text.splitlines()[1].split()[:3] == ["1", "m-wear", "warning_now"]
    assert "2 machines: 1 warning now, 1 no trend" in text
    assert "end of life for m-wear, m-ok: wear: the CM ratio at 90 %" in text
    code, doc = _plan(capsys, str(dataset), "--at", "yesterday")
    assert code == 64
    assert "--at 'yesterday'" in doc["err"]


def test_a_machine_fleet_train_left_out_is_flagged_and_cannot_be_judged():
    """A leak within the on-board guard's allowance is learnt as the machine's own baseline; the type
    model's training named it all the same: the plan says so, and does not rank it with the quiet."""
    why = "arrives leaking: delivers less than the type (does not fit the type)"
    rows = plan([facts("quiet"), facts("named", type_verdict=why)], T0_S + 10 * DAY_S)
    named = next(r for r in rows if r.machine == "named")
    assert named.group == "cannot_judge" and "left_out_of_type" in named.flags and named.rank == 1
    assert "left_out_of_type" not in next(r for r in rows if r.machine == "quiet").flags


def test_the_verdict_is_read_from_the_replay_models_metadata():
    from types import SimpleNamespace

    from cmcan.fleet.task import type_verdict

    why = "arrives leaking: delivers less than the type (off the reference model)"
    model = SimpleNamespace(meta=SimpleNamespace(training={"unit_spread": {"outliers": {"m4": {"why": why}}}}))
    assert type_verdict(model, "m4") == why
    assert type_verdict(model, "m1") is None
    # a model of cmcan train (no spread), of an older fleet train (outliers a list), none at all
    for training in ({}, {"unit_spread": {"outliers": ["m4"]}}, None, {"unit_spread": None}):
        assert type_verdict(SimpleNamespace(meta=SimpleNamespace(training=training)), "m4") is None
    assert type_verdict(None, "m4") is None


def test_the_logs_type_verdict_reaches_the_plan(tmp_path, capsys):
    pytest.importorskip("duckdb")
    pytest.importorskip("pyarrow")
    from cmcan.fleet import dataset as ds

    root = ds.open_dataset(tmp_path / "ds", create=True)
    why = "arrives leaking: delivers less than the type (off the reference model)"
    _log(root, "m-leak", 0, ["ok"] * ROWS, [NO] * ROWS, [math.nan] * ROWS)
    _log(root, "m-ok", 0, ["ok"] * ROWS, [NO] * ROWS, [math.nan] * ROWS)
    # the leaking machine's later log, replayed with the type model that names it
    _log(root, "m-leak", 1, ["ok"] * ROWS, [NO] * ROWS, [math.nan] * ROWS, summary={"type_verdict": why})
    code, doc = _plan(capsys, str(root), "--json", "--at", "2026-01-02T12:00")
    assert code == 0
    rows = {r["machine"]: r for r in doc["machines"]}
    assert rows["m-leak"]["flags"] == ["left_out_of_type"] and rows["m-leak"]["group"] == "cannot_judge"
    assert rows["m-leak"]["type_verdict"] == why  # fleet train's words, from its latest log
    assert rows["m-ok"]["flags"] == [] and rows["m-ok"]["group"] == "no_trend"
    assert rows["m-ok"]["type_verdict"] is None
