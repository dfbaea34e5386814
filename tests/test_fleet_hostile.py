"""Hostile fleet sources and a hostile machine, through the real command line on an embedded Dask
cluster: a link to a secret in a log folder and a manifest naming files outside it are never opened
and nothing of them reaches the data set or the report; /dev/zero and a FIFO named as logs are refused
at once instead of hanging the run; a data set that cannot be written (a file size limit: the kernel
refuses writes as a full disk would) ends the run with the path and exit 74, no traceback; an
unreachable scheduler leaves nothing behind."""

from __future__ import annotations

import csv
import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("distributed")
pytest.importorskip("duckdb")

from cmcan.fleet import dataset as ds
from cmcan.fleet.query import run_sql
from tests.conftest import ROOT, run_cli

pytestmark = pytest.mark.slow
SECRET = "root:$6$s3cr3t-hash-4711:20228:0:99999:7:::"


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Two machines of a simulated fleet, 8 h each in 4 h logs, and a secret outside its folder."""
    d = tmp_path_factory.mktemp("hostile")
    sim = d / "sim"
    r = run_cli(
        *("simulate", "fleet", "--machines", "2", "--hours", "8", "--log-hours", "4", "--out", str(sim), "--json")
    )
    assert r.returncode == 0, r.stderr
    secret = d / "private" / "shadow"
    secret.parent.mkdir()
    secret.write_text(SECRET + "\n")
    secret.chmod(0o600)
    return sim, secret


def no_secret_in(root: Path, *texts: str) -> None:
    for t in texts:
        assert "s3cr3t" not in t
    for f in root.rglob("*"):
        if f.is_file():
            assert b"s3cr3t" not in f.read_bytes(), f


def test_a_link_to_a_secret_in_a_log_folder_is_not_opened(fleet, tmp_path):
    sim, secret = fleet
    (sim / "logs" / "m001" / "evil.log").symlink_to(secret)
    try:
        out = tmp_path / "ds"
        cfg, model = sim / "types" / "compact" / "cmcan.yaml", sim / "types" / "compact" / "model.onnx"
        r = run_cli(
            *("fleet", "replay", str(sim / "logs" / "m001"), "--out", str(out), "--workers", "1"),
            *("--config", str(cfg), "--model", str(model)),
        )
        assert r.returncode == 65, r.stderr  # the run finished; one source was refused
        assert "refused" in r.stderr and "evil.log" in r.stderr and "--follow-symlinks" in r.stderr
        _, rows = run_sql(out, "SELECT stage, reason FROM quarantine")
        assert [s for s, _ in rows] == ["source"]
        assert run_sql(out, "SELECT count(*) FROM logs")[1] == [(2,)]
        report = tmp_path / "r.html"
        assert run_cli("fleet", "report", str(out), "--out", str(report)).returncode == 0
        no_secret_in(out, r.stdout, r.stderr, report.read_text())
        # asked to follow links, the secret is read as a log: refused as one, and still not quoted
        r = run_cli(
            *("fleet", "replay", str(sim / "logs" / "m001"), "--out", str(out), "--workers", "1"),
            *("--config", str(cfg), "--model", str(model), "--follow-symlinks"),
        )
        assert r.returncode == 65 and "evil.log" in r.stderr
        _, rows = run_sql(out, "SELECT stage, reason FROM quarantine")
        ((stage, reason),) = rows
        assert stage == "read" and "not a candump -l line" in reason and "quoted content left out" in reason
        assert run_cli("fleet", "report", str(out), "--out", str(report), "--force").returncode == 0
        no_secret_in(out, r.stdout, r.stderr, report.read_text())
    finally:
        (sim / "logs" / "m001" / "evil.log").unlink()


def test_a_manifest_naming_files_outside_it_dev_zero_or_a_fifo_is_refused_at_once(fleet, tmp_path):
    sim, secret = fleet
    fifo = sim / "pipe.log"
    os.mkfifo(fifo)
    try:
        with open(sim / "manifest.csv", newline="") as f:
            rows = list(csv.reader(f))
        hostile = sim / "hostile.csv"
        with open(hostile, "w", newline="") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerows(rows[:2])  # the header and one good log
            w.writerow(("m001", str(secret), rows[1][2], rows[1][3]))  # a log outside the root
            w.writerow(("m001", rows[1][1], str(secret), rows[1][3]))  # a configuration outside it
            w.writerow(("m001", "../private/shadow", rows[1][2], rows[1][3]))
            w.writerow(("m002", "/dev/zero", rows[1][2], rows[1][3]))
            w.writerow(("m002", "pipe.log", rows[1][2], rows[1][3]))
        out = tmp_path / "ds"
        r = run_cli("fleet", "replay", str(hostile), "--out", str(out), "--workers", "1", "--json", timeout=240)
        assert r.returncode == 65, r.stderr
        import json

        rep = json.loads(r.stdout)
        assert (rep["done"], rep["refused"]) == (1, 5)
        reasons = [x["reason"] for x in rep["refused_sources"]]
        assert sum("outside the manifest's root" in x for x in reasons) == 4  # /dev/zero too
        assert any("FIFO" in x for x in reasons)
        # even with the whole file system as the root, /dev/zero and the FIFO are not opened
        r = run_cli(
            *("fleet", "replay", str(hostile), "--out", str(tmp_path / "ds2"), "--workers", "1"),
            *("--manifest-root", "/", "--json"),
            timeout=240,
        )
        rep = json.loads(r.stdout)
        assert r.returncode == 65 and rep["refused"] == 2 and rep["quarantined"] >= 1
        reasons = [x["reason"] for x in rep["refused_sources"]]
        assert any("character device" in x for x in reasons) and any("FIFO" in x for x in reasons)
        no_secret_in(tmp_path, r.stdout, r.stderr)
    finally:
        fifo.unlink()


def test_a_data_set_that_cannot_be_written_ends_the_run_with_its_path_and_exit_74(fleet, tmp_path):
    sim, _secret = fleet
    out = tmp_path / "ds"

    def small_files() -> None:  # writes past 6 kB fail with EFBIG, as they would with ENOSPC on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (6000, 6000))

    r = subprocess.run(
        [sys.executable, "-m", "cmcan", "fleet", "replay", str(sim), "--out", str(out), "--workers", "1", "-q"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=small_files,
    )
    assert r.returncode == 74, r.stderr
    assert "Traceback" not in r.stderr and "cannot write" in r.stderr and str(out) in r.stderr
    assert "run the same command again" in r.stderr
    assert not ds.committed(out) and not (out / ds.STAGING).exists()
    r = run_cli("fleet", "replay", str(sim), "--out", str(out), "--workers", "1", "-q")
    assert r.returncode == 0 and len(ds.committed(out)) == 4, r.stderr  # the same command, with room, does it


def test_an_unreachable_scheduler_leaves_nothing_behind(fleet, tmp_path):
    sim, _secret = fleet
    out = tmp_path / "ds"
    r = run_cli("fleet", "replay", str(sim), "--out", str(out), "--scheduler", "tcp://127.0.0.1:9")
    assert r.returncode == 69 and "cannot reach the Dask scheduler" in r.stderr and "nothing was written" in r.stderr
    assert not out.exists()
