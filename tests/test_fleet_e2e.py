"""The whole fleet path through the real command line on a small simulated fleet: simulate, replay on
an embedded Dask cluster, check against the ground truth, rerun, Ctrl-C and resume, report in
headless Chromium (its screenshot kept in tests/artifacts/), query."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("distributed")
pytest.importorskip("duckdb")

from cmcan.fleet import dataset as ds
from cmcan.fleet.query import run_sql
from tests.chromium import chromium_path, open_page
from tests.conftest import ROOT, run_cli

pytestmark = pytest.mark.slow
ARTIFACTS = ROOT / "tests" / "artifacts"


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Six machines of three sizes, 60 h each in 20 h logs, half degrading; one corrupt log added."""
    d = tmp_path_factory.mktemp("fleet")
    out = d / "sim"
    r = run_cli(
        "simulate",
        "fleet",
        "--machines",
        "6",
        "--hours",
        "60",
        "--log-hours",
        "20",
        "--seed",
        "4",
        "--out",
        str(out),
        "--json",
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["machines"] == 6 and summary["degrading"] == 3 and summary["logs"] == 18
    truth = json.loads((out / "truth.json").read_text())
    corrupt = out / "logs" / "m002" / "m002_corrupt.log"
    corrupt.write_bytes(b"(1767225600.000000) can0 100#00112233\n\x00\x01garbage that is no candump line\n")
    with open(out / "manifest.csv", "a", newline="") as f:
        csv.writer(f, lineterminator="\n").writerow(
            ("m002", "logs/m002/m002_corrupt.log", "types/mid/cmcan.yaml", "types/mid/model.onnx")
        )
    dataset = d / "ds"
    t = time.monotonic()
    r = run_cli("fleet", "replay", str(out / "manifest.csv"), "--out", str(dataset), "--workers", "2", "--json")
    print(f"fleet replay: {time.monotonic() - t:.1f} s")
    return {"sim": out, "truth": truth, "ds": dataset, "first": r, "corrupt": corrupt}


def test_fleet_replay_flags_every_degrading_machine_before_its_failure_and_no_healthy_one(fleet):
    r = fleet["first"]
    assert r.returncode == 65, r.stderr  # one log quarantined in this run
    rep = json.loads(r.stdout)
    assert (rep["logs"], rep["done"], rep["quarantined"]) == (19, 18, 1)
    assert rep["workers"] == 2
    _, rows = run_sql(
        fleet["ds"],
        "SELECT machine, sum(warnings_low + warnings_high), min(first_warning_time_s) FILTER "
        "(WHERE NOT isnan(first_warning_time_s)), list(DISTINCT final_level) FROM logs GROUP BY machine",
    )
    got = {m: (n, first) for m, n, first, _levels in rows}
    assert len(got) == 6
    for m in fleet["truth"]["machines"]:
        n, first = got[m["machine"]]
        if m["degrading"]:
            fail = min(f["fail_epoch_s"] for f in m["failures"])
            assert n >= 1 and first is not None, f"{m['machine']} ({m['degradation']}) was never flagged"
            assert first < fail, f"{m['machine']} flagged {(first - fail) / 3600:.1f} h after its failure"
            lead_h = (fail - first) / 3600.0
            print(f"{m['machine']} {m['type']} {m['degradation']}: flagged {lead_h:.1f} h before failure")
        else:
            assert n == 0, f"healthy {m['machine']} was flagged"
    # the warning direction matches the fault: wear pulls the ratio down, misposition pushes it up
    _, ev = run_sql(fleet["ds"], "SELECT machine, list(DISTINCT to_level) FROM events GROUP BY machine")
    levels = dict(ev)
    for m in fleet["truth"]["machines"]:
        if m["degrading"]:
            want = "high" if m["degradation"] == "misposition" else "low"
            assert want in levels[m["machine"]]


def test_the_corrupt_log_is_in_quarantine_with_its_reason(fleet):
    _, rows = run_sql(fleet["ds"], "SELECT machine, log, stage, reason, log_hash FROM quarantine")
    assert len(rows) == 1
    machine, log, stage, reason, log_hash = rows[0]
    assert (machine, Path(log).name, stage) == ("m002", "m002_corrupt.log", "replay")
    assert "line 2" in reason and log_hash == ds.sha256_file(fleet["corrupt"])


def test_every_row_carries_its_provenance(fleet):
    sim = fleet["sim"]
    model = ds.sha256_file(sim / "types" / "mid" / "model.onnx")
    cfg = ds.sha256_file(sim / "types" / "mid" / "cmcan.yaml")
    dbc = ds.sha256_file(sim / "dbc" / "cmcan.dbc")
    for table in ("timeline", "events", "logs"):
        _, rows = run_sql(
            fleet["ds"],
            f"SELECT count(*), count(DISTINCT log_hash), min(model_hash), min(config_hash), min(dbc_hash), "
            f"count(cmcan_version) FROM {table} WHERE machine = 'm002'",
        )
        n, logs, m, c, d, v = rows[0]
        if table == "events" and n == 0:
            continue
        assert (m, c, d, v) == (model, cfg, dbc, n)
        assert logs == (3 if table != "events" else logs)
    _, rows = run_sql(fleet["ds"], "SELECT log, log_hash FROM logs WHERE machine = 'm002'")
    assert all(ds.sha256_file(log) == h for log, h in rows)


def test_a_rerun_skips_everything(fleet):
    before = sorted(p.stat().st_mtime_ns for p in fleet["ds"].rglob("*.parquet"))
    r = run_cli(
        "fleet", "replay", str(fleet["sim"] / "manifest.csv"), "--out", str(fleet["ds"]), "--workers", "2", "--json"
    )
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert (rep["done"], rep["skipped"], rep["quarantined"], rep["frames"]) == (0, 19, 0, 0)
    assert sorted(p.stat().st_mtime_ns for p in fleet["ds"].rglob("*.parquet")) == before


def test_query_command(fleet):
    r = run_cli(
        "fleet",
        "query",
        str(fleet["ds"]),
        "SELECT machine, count(*) AS logs FROM logs GROUP BY 1 ORDER BY 1",
        "--format",
        "csv",
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["machine,logs", *[f"m00{i},3" for i in range(1, 7)]]
    r = run_cli("fleet", "query", str(fleet["ds"]), "SELECT * FROM nowhere")
    assert r.returncode == 65 and "query failed" in r.stderr


@pytest.mark.skipif(chromium_path() is None, reason="needs Debian's chromium package (.ci/run installs it)")
def test_the_report_loads_in_headless_chromium_without_errors(fleet, tmp_path):
    html = tmp_path / "report.html"
    r = run_cli("fleet", "report", str(fleet["ds"]), "--out", str(html))
    assert r.returncode == 0, r.stderr
    text = html.read_text()
    assert "<script" not in text and "http://" not in text and "https://" not in text  # self-contained
    shot = ARTIFACTS / "fleet-report.png"
    page = open_page(
        html.as_uri(),
        shot,
        {
            "images": "Array.from(document.images).map(i => i.complete && i.naturalWidth > 0)",
            "ranked": "Array.from(document.querySelectorAll('#ranking tr td:nth-child(2)')).map(t => t.innerText)",
            "states": "Array.from(document.querySelectorAll('#ranking tr td:nth-child(3)')).map(t => t.innerText)",
            "quarantine": "document.getElementById('quarantine').innerText",
        },
    )
    print(f"report screenshot: {shot}")
    assert page.errors == []
    assert all(u.startswith(("file:", "data:")) for u in page.requests), page.requests
    assert page.values["images"] and all(page.values["images"]) and len(page.values["images"]) == 7
    # the machines that need a look come first
    degrading = {m["machine"] for m in fleet["truth"]["machines"] if m["degrading"]}
    ranked = page.values["ranked"]
    assert set(ranked[: len(degrading)]) == degrading and len(ranked) == 6
    assert all(s != "ok" for s in page.values["states"][: len(degrading)])
    assert page.values["quarantine"] == "Quarantine (1)"
    assert shot.stat().st_size > 20_000 and shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    r = run_cli("fleet", "report", str(fleet["ds"]), "--out", str(html))
    assert r.returncode == 73 and "--force" in r.stderr


def test_ctrl_c_keeps_whole_logs_and_a_rerun_finishes(fleet, tmp_path):
    """SIGINT in the middle of a run: the logs committed stay whole, nothing else is left, and the
    same command again does exactly the rest."""
    with open(fleet["sim"] / "manifest.csv", newline="") as f:
        rows = list(csv.reader(f))
    manifest = tmp_path / "manifest.csv"
    with open(manifest, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(rows[0])
        for row in rows[1:]:
            if row[0] in ("m001", "m002", "m003"):
                w.writerow([row[0], *(str(fleet["sim"] / p) for p in row[1:])])
    n_logs = 10  # 3 machines x 3 logs, and the corrupt one
    dataset = tmp_path / "ds"
    root = ("--manifest-root", str(fleet["sim"]))  # the manifest here names the simulated fleet's files
    cmd = [sys.executable, "-m", "cmcan", "fleet", "replay", str(manifest), "--out", str(dataset), "--workers", "1"]
    cmd += root
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if len(list((dataset / "logs").rglob("*.parquet"))) >= 2:
            break
        time.sleep(0.2)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    _out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "run the same command again" in err
    committed = ds.committed(dataset)
    assert 2 <= len(committed) < 9
    # every data file belongs to a committed log, nothing is staged
    for table in ds.DATA_TABLES:
        for p in (dataset / table).rglob("*.parquet"):
            assert (p.parts[-3].split("=", 1)[1], p.stem) in committed, p
    assert not any((dataset / ds.STAGING).rglob("*"))
    assert not list(dataset.rglob("*.tmp"))
    r = run_cli("fleet", "replay", str(manifest), "--out", str(dataset), "--workers", "1", "--json", *root)
    rep = json.loads(r.stdout)
    assert rep["skipped"] + rep["done"] + rep["quarantined"] == n_logs
    assert rep["done"] == 9 - len(committed)
    assert rep["skipped"] == len(committed) + (rep["quarantined"] == 0)  # the corrupt log, if quarantined before
    assert len(ds.committed(dataset)) == 9
    # the same results as the uninterrupted run
    q = (
        "SELECT machine, log_hash, evaluated, cm_ratio_p50_pct FROM logs "
        "WHERE machine IN ('m001','m002','m003') ORDER BY 2"
    )
    assert run_sql(dataset, q)[1] == run_sql(fleet["ds"], q)[1]


def test_the_same_code_runs_against_an_existing_scheduler(fleet, tmp_path):
    """--scheduler ADDRESS: the tasks run on a cluster the command did not start, with the same results."""
    from distributed import LocalCluster

    logs = sorted((fleet["sim"] / "logs" / "m004").glob("*.log"))
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        dataset = tmp_path / "ds"
        r = run_cli(
            "fleet", "replay", *map(str, logs), "--out", str(dataset), "--scheduler", cluster.scheduler_address,
            "--config", str(fleet["sim"] / "types" / "compact" / "cmcan.yaml"),
            "--model", str(fleet["sim"] / "types" / "compact" / "model.onnx"), "--json",
        )  # fmt: skip
        assert r.returncode == 0, r.stderr
        rep = json.loads(r.stdout)
        assert (rep["done"], rep["workers"]) == (3, 1)
        assert len(cluster.scheduler_info["workers"]) == 1  # still up: the command leaves a cluster it did not start
    q = "SELECT machine, log_hash, model_hash, evaluated, cm_ratio_p50_pct FROM logs ORDER BY log_hash"
    mine = run_sql(dataset, q)[1]
    assert mine == run_sql(fleet["ds"], q.replace("FROM logs", "FROM logs WHERE machine = 'm004'"))[1]
