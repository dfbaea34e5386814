"""The product's promises on the shipped scenarios, with the shipped configuration and model."""

import json

import pytest

from cmcan import config as cfgmod
from cmcan.assemble import assemble
from cmcan.replay import replay_columns
from cmcan.sim import degradation
from cmcan.sim import scenario as scn
from tests.conftest import ROOT, run_cli
from tests.helpers import sim_frames

pytestmark = pytest.mark.slow


def columnar(frames):
    """The shipped configuration's monitor after the replay's columnar engine took ``frames``."""
    cfg = cfgmod.load()
    mon = assemble(cfg).monitor
    replay_columns(mon, frames.to_columns(cfg.bus.channel))
    return mon


def warnings_h(mon, start):
    return [((h["t_s"] - start) / 3600.0, h["from"], h["to"]) for h in mon.totals.history]


def test_run_to_failure_warns_before_each_failure():
    # the whole life at full rate (10 M frames) through the replay's columnar engine; the daemon's
    # frame-by-frame path plays the same life in the demo (below), and the two engines are held
    # equal frame for frame in test_columnar
    run, frames = sim_frames("run_to_failure")
    mon = columnar(frames)
    events = warnings_h(mon, run.start_epoch_s)
    print(events)
    assert not [e for e in events if e[0] < 200.0]
    previous = 0.0
    for f in degradation.scheduled_failures(scn.load(scn.shipped("run_to_failure")).events):
        raised = [e for e in events if e[2] in ("low", "high") and previous < e[0] <= f["fail_h"]]
        assert raised, f"no warning before {f}"
        lead = f["fail_h"] - raised[0][0]
        print(f["component"], f["kind"], "warning at", raised[0][0], "lead", lead)
        assert lead >= 10.0
        assert raised[0][2] == ("high" if f["kind"] == "misposition" else "low")
        previous = f["fail_h"]


def test_healthy_mixed_duty_100h_with_oil_30_to_90_raises_no_warning():
    run, frames = sim_frames("healthy_mixed_100h")
    assert run["temp_c"].min() < 31 and run["temp_c"].max() > 89
    mon = columnar(frames)
    assert mon.totals.history == [] and mon.totals.warning_count == 0
    assert mon.counters["evaluated"] > 10_000  # the drive was really evaluated, not gated out


def test_demo_reports_lead_times_as_json(tmp_path):
    res = run_cli("demo", "--json", "--out-dir", str(tmp_path), timeout=900)
    assert res.returncode == 0, res.stderr + res.stdout
    assert "stepped" not in res.stderr  # the time-lapse's jumps are the log's, not wall-clock steps
    doc = json.loads(res.stdout)
    assert doc["passed"] and doc["frames_sent"] == doc["frames_processed"] > 1_000_000
    kinds = {f["kind"]: f for f in doc["failures"]}
    assert kinds["misposition"]["level"] == "high"
    assert all(f["lead_h"] >= 10 for f in doc["failures"])
    assert (tmp_path / "demo.png").stat().st_size > 20_000
    # beside each failure, what the default end of life (the ratio at 90 / 110 %) gave 10 h before it:
    # a trend, its quantiles in order, and the ratio reached that end of life after the estimate
    for f in doc["failures"]:
        if f["kind"] not in ("wear", "misposition"):
            continue
        d = f["prognosis_default_eol"]
        assert d["state"] in ("trend", "imminent") and d["at_h"] == f["fail_h"] - 10.0, d
        p10, p50, p90 = d["to_eol_h"]
        assert 0.0 <= p10 <= p50 <= p90 and d["reached_h"] > d["at_h"], d


@pytest.mark.slow
def test_the_demo_passes_the_same_checks_on_the_j1939_machine(tmp_path):
    res = run_cli(
        "demo",
        "--config",
        str(ROOT / "config" / "j1939-example.yaml"),
        "--json",
        "--no-plot",
        "--out-dir",
        str(tmp_path),
    )
    assert res.returncode == 0, res.stderr + res.stdout
    doc = json.loads(res.stdout)
    assert doc["passed"] and doc["frames_sent"] == doc["frames_processed"] > 1_000_000
    names = set(doc["checks"])
    for f in doc["failures"]:
        assert any(f"{f['component']} {f['kind']} failure" in n for n in names)
        assert f["lead_h"] >= 10
    assert {
        "no warning in the healthy first 200 h",
        "the misposition raises the high warning",
        "every frame sent was processed",
        "DM1 (J1939): the amber lamp and the drive's DTC follow every warning",
    } <= names
