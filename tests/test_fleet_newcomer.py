"""The fleet workflow as a newcomer runs it, end to end through the real command line: `simulate fleet`
says what to run next and that works; the logs folder alone stops and names the manifest; one
configuration for every drive size flags the machines it does not fit instead of ranking them as worn;
a glob beside the manifest says which configuration each log got; a log replayed under another machine
moves; a log cut in its last line replays up to it with the cut recorded; the reports open in headless
Chromium (screenshots in tests/artifacts/)."""

from __future__ import annotations

import csv
import json
import shlex
import shutil

import pytest

pytest.importorskip("distributed")
pytest.importorskip("duckdb")

from cmcan.fitcheck import FIT_BAND_PCT
from cmcan.fleet.query import run_sql
from tests.chromium import chromium_path, open_page
from tests.conftest import ROOT, run_cli

pytestmark = pytest.mark.slow
ARTIFACTS = ROOT / "tests" / "artifacts"
Q_RESULTS = (
    "SELECT machine, log_name, evaluated, cm_ratio_p50_pct, warnings_low + warnings_high FROM logs ORDER BY 1, 2"
)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Three machines, one of each drive size (m001 compact, m002 mid, m003 large), 12 h in 4 h logs,
    and the commands `simulate fleet` says to run next, run as printed."""
    d = tmp_path_factory.mktemp("newcomer")
    r = run_cli(*("simulate", "fleet", "--machines", "3", "--hours", "12", "--log-hours", "4", "--out", "f"), cwd=d)
    assert r.returncode == 0, r.stderr
    printed = [line.strip() for line in r.stdout.splitlines() if line.startswith("  cmcan ")]
    assert printed == ["cmcan fleet replay f --out f-ds", "cmcan fleet report f-ds --out f-report.html"]
    runs = [run_cli(*shlex.split(cmd)[1:], cwd=d) for cmd in printed]
    return {"dir": d, "sim": d / "f", "ds": d / "f-ds", "report": d / "f-report.html", "runs": runs}


def test_the_commands_simulate_prints_replay_each_machine_with_its_own_configuration(fleet):
    replay, report = fleet["runs"]
    assert replay.returncode == 0, replay.stderr
    assert "read through its manifest.csv" in replay.stderr
    assert report.returncode == 0 and fleet["report"].exists(), report.stderr
    _, rows = run_sql(fleet["ds"], "SELECT machine, count(*), min(config_hash) = max(config_hash) FROM logs GROUP BY 1")
    assert sorted(rows) == [("m001", 3, True), ("m002", 3, True), ("m003", 3, True)]
    _, fits = run_sql(fleet["ds"], "SELECT machine, fit, fit_median_pct FROM machines ORDER BY 1")
    lo, hi = FIT_BAND_PCT
    assert [(m, f) for m, f, _ in fits] == [("m001", "fits"), ("m002", "fits"), ("m003", "fits")]
    assert all(lo + 3 <= med <= hi - 3 for _m, _f, med in fits)


def test_the_logs_folder_alone_stops_and_names_its_manifest(fleet):
    d = fleet["dir"]
    r = run_cli("fleet", "replay", "f/logs", "--out", "logs-ds", cwd=d)
    assert r.returncode == 64 and "f/manifest.csv names 9 of these logs" in r.stderr and "--config" in r.stderr
    assert not (d / "logs-ds").exists()


@pytest.fixture(scope="module")
def one_config(fleet):
    """Every size replayed with the mid-size configuration and model, as a newcomer would by `--config`."""
    d = fleet["dir"]
    r = run_cli(
        *("fleet", "replay", "f/logs", "--out", "mid-ds", "--workers", "2"),
        *("--config", "f/types/mid/cmcan.yaml", "--model", "f/types/mid/model.onnx"),
        cwd=d,
    )
    assert r.returncode == 0, r.stderr
    r = run_cli("fleet", "report", "mid-ds", "--out", "mid-report.html", cwd=d)
    assert r.returncode == 0, r.stderr
    return d / "mid-ds", d / "mid-report.html"


def test_a_configuration_that_does_not_fit_is_flagged_not_ranked_as_wear(one_config):
    ds, report = one_config
    _, rows = run_sql(ds, "SELECT machine, fit, fit_median_pct, fit_log FROM machines ORDER BY 1")
    got = {m: (f, med) for m, f, med, _log in rows}
    assert got["m002"][0] == "fits"
    assert got["m001"][0] == "does_not_fit" and got["m001"][1] > 120  # a compact drive read as mid: too fast
    assert got["m003"][0] == "does_not_fit" and got["m003"][1] < 70  # a large one: too slow
    assert all(log.endswith("T0000.log") for *_x, log in rows)  # judged on each machine's first hour
    text = report.read_text()
    assert text.count("Configuration or model does not fit this machine.") == 2
    assert "configuration or model does not fit</td>" in text


def test_a_glob_beside_the_manifest_says_which_configuration_each_log_got(fleet, tmp_path):
    d = fleet["dir"]
    r = run_cli("fleet", "replay", "f/logs/*/*.log", "f/manifest.csv", "--out", str(tmp_path / "ds"), cwd=d)
    assert r.returncode == 0, r.stderr
    notes = [line for line in r.stderr.splitlines() if "named by" in line]
    assert len(notes) == 9 and all("f/manifest.csv line" in n and "glob f/logs/*/*.log" in n for n in notes)
    assert all("the shipped configuration" in n and "types/" in n for n in notes)
    assert run_sql(tmp_path / "ds", Q_RESULTS) == run_sql(fleet["ds"], Q_RESULTS)  # the manifest's rows won


def test_a_log_replayed_under_another_machine_moves_and_a_machine_can_be_dropped(fleet, tmp_path):
    ds = tmp_path / "ds"
    shutil.copytree(fleet["ds"], ds)
    sim = fleet["sim"]
    with open(sim / "manifest.csv", newline="") as f:
        rows = list(csv.reader(f))
    renamed = sim / "renamed.csv"
    with open(renamed, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(rows[0])
        w.writerows([("m009", *row[1:]) for row in rows[1:] if row[0] == "m001"])
    r = run_cli("fleet", "replay", str(renamed), "--out", str(ds), "--workers", "1", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["done"] == 3 and [(m["from"], m["to"]) for m in rep["moved"]] == [("m001", "m009")] * 3
    _, n = run_sql(ds, "SELECT machine, count(*) FROM logs GROUP BY 1 ORDER BY 1")
    assert n == [("m002", 3), ("m003", 3), ("m009", 3)]  # nine logs, not twelve
    _, n = run_sql(ds, "SELECT count(DISTINCT machine), count(DISTINCT log_hash), count(*) FROM timeline")
    assert n[0][0] == 3 and n[0][1] == 9
    r = run_cli("fleet", "drop", str(ds), "--machine", "m009")
    assert r.returncode == 0 and "removed machine m009: 3 logs" in r.stdout
    assert run_sql(ds, "SELECT count(*) FROM logs")[1] == [(6,)]
    renamed.unlink()


def test_a_log_cut_in_its_last_line_replays_up_to_it_with_the_cut_recorded(fleet, tmp_path):
    sim = fleet["sim"]
    src = sorted((sim / "logs" / "m002").glob("*.log"))[-1]
    blob = src.read_bytes()
    lines = blob.count(b"\n")
    cut = tmp_path / "m002_cut.log"
    cut.write_bytes(blob[:-9])  # the last line ends mid-frame, without its line end
    whole = tmp_path / "whole" / "m002_cut.log"
    whole.parent.mkdir()
    whole.write_bytes(blob[: blob.rfind(b"\n", 0, len(blob) - 9) + 1])  # what is left of it: its whole lines
    cfg = ("--config", str(sim / "types" / "mid" / "cmcan.yaml"), "--model", str(sim / "types" / "mid" / "model.onnx"))
    r = run_cli("fleet", "replay", str(cut), "--out", str(tmp_path / "ds"), "--workers", "1", "--keep-truncated", *cfg)
    assert r.returncode == 0, r.stderr
    assert "replayed up to a cut last line" in r.stdout
    r = run_cli("fleet", "replay", str(whole), "--out", str(tmp_path / "ref"), "--workers", "1", *cfg)
    assert r.returncode == 0, r.stderr
    q = "SELECT log_name, count_frames_total, evaluated, cm_ratio_p50_pct, last_time_s FROM logs"
    _, got = run_sql(tmp_path / "ds", q.replace("FROM", ", cut_line FROM"))
    _, want = run_sql(tmp_path / "ref", q)
    assert got[0][:-1] == want[0] and got[0][1] == lines - 1
    assert got[0][-1] == lines  # the cut line's number


@pytest.mark.skipif(chromium_path() is None, reason="needs Debian's chromium package (.ci/run installs it)")
@pytest.mark.parametrize("which", ["workflow", "one_config"])
def test_the_reports_in_headless_chromium(fleet, one_config, which):
    report = fleet["report"] if which == "workflow" else one_config[1]
    shot = ARTIFACTS / f"fleet-report-{which}.png"
    page = open_page(
        report.as_uri(),
        shot,
        {
            "images": "Array.from(document.images).map(i => i.complete && i.naturalWidth > 0)",
            "ranked": "Array.from(document.querySelectorAll('#ranking tr td:nth-child(2)')).map(t => t.innerText)",
            "states": "Array.from(document.querySelectorAll('#ranking tr td:nth-child(3)')).map(t => t.innerText)",
            "flags": "Array.from(document.querySelectorAll('#ranking tr td:nth-child(12)')).map(t => t.innerText)",
        },
    )
    print(f"report screenshot: {shot}")
    assert page.errors == [] and all(u.startswith(("file:", "data:")) for u in page.requests)
    assert len(page.values["images"]) == 4 and all(page.values["images"])
    if which == "one_config":
        assert page.values["ranked"][:2] == ["m001", "m003"] or page.values["ranked"][:2] == ["m003", "m001"]
        # the service plan: their ratio says nothing of wear, "cannot judge", flagged, first of the ranking
        assert page.values["states"][:2] == ["cannot judge"] * 2
        assert all("does not fit" in f for f in page.values["flags"][:2])
        assert not any("does not fit" in f for f in page.values["flags"][2:])
    else:
        assert not any("does not fit" in f for f in page.values["flags"])
