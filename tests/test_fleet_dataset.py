"""The fleet data set holds what was committed and says when it does not: damaged files are named by
query and report and re-done by the next replay; a log belongs to one machine; quarantine rows go when
their log commits; a path with glob characters is a path; the quarantine reason never quotes a file;
a full disk ends the run with the path and its exit status, not a traceback."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

pytest.importorskip("pyarrow")
pytest.importorskip("duckdb")
pytest.importorskip("distributed")

from cmcan.errors import CmcanError, Kind
from cmcan.fleet import dataset as ds
from cmcan.fleet.query import run_sql
from cmcan.fleet.run import run_fleet
from cmcan.fleet.task import LogJob, Options, process_log, safe_reason
from tests.conftest import run_cli
from tests.helpers import sim_frames, write_log

Q_LOGS = "SELECT machine, log_hash, evaluated, cm_ratio_p50_pct, warnings_low FROM logs ORDER BY 1, 2"
Q_TIMELINE = (
    "SELECT machine, count(*), sum(ticks), min(time_s), max(time_s), "
    "round(sum(cm_ratio_raw_pct) FILTER (WHERE evaluated > 0), 6) FROM timeline GROUP BY 1"
)


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("dslogs")
    _run, frames = sim_frames("single_set_leakage", duration_h=0.04)
    a = write_log(d / "m1_a.log", frames)
    _run, frames = sim_frames("single_set_healthy", duration_h=0.03)
    b = write_log(d / "m1_b.log", frames)
    return d, a, b


@pytest.fixture(scope="module")
def built(logs, tmp_path_factory):
    """A data set of two logs, as the reference the damaged copies are compared to."""
    _d, a, b = logs
    root = ds.open_dataset(tmp_path_factory.mktemp("ref") / "ds", create=True)
    for log in (a, b):
        assert process_log(LogJob("m1", str(log)), Options(dataset=str(root)))["status"] == "done"
    return root, run_sql(root, Q_LOGS), run_sql(root, Q_TIMELINE)


@pytest.fixture(scope="module")
def client():
    """A Dask cluster in this process (threads), so a monkeypatched writer is the one the tasks use."""
    from distributed import Client, LocalCluster

    with (
        LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as c,
    ):
        yield c


def copy_dataset(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


# -- what is committed is checked --------------------------------------------------------------------


def test_a_summary_cut_short_is_named_by_query_and_redone_by_replay(built, logs, tmp_path):
    root = copy_dataset(built[0], tmp_path / "ds")
    summary = sorted((root / "logs").rglob("*.parquet"))[0]
    summary.write_bytes(summary.read_bytes()[:100])
    r = run_cli("fleet", "query", str(root), "SELECT count(*) FROM logs")
    assert r.returncode == 65 and str(summary) in r.stderr and "fleet replay" in r.stderr
    r = run_cli("fleet", "report", str(root), "--out", str(tmp_path / "r.html"))
    assert r.returncode == 65 and str(summary) in r.stderr
    _d, a, b = logs
    res = [process_log(LogJob("m1", str(log)), Options(dataset=str(root))) for log in (a, b)]
    assert sorted(r["status"] for r in res) == ["done", "skipped"]  # the damaged one replayed, not skipped
    assert any("not readable" in (r.get("redone") or "") for r in res)
    assert run_sql(root, Q_LOGS) == built[1] and run_sql(root, Q_TIMELINE) == built[2]


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(which=st.integers(0, 1000), how=st.sampled_from(["overwrite", "cut", "append"]), where=st.floats(0.0, 0.95))
def test_any_damage_to_a_committed_file_is_named_never_read_silently(built, logs, tmp_path_factory, which, how, where):
    root = copy_dataset(built[0], tmp_path_factory.mktemp("damaged") / "ds")
    files = sorted(f for t in ("timeline", "events", "logs") for f in (root / t).rglob("*.parquet"))
    f = files[which % len(files)]
    table = f.relative_to(root).parts[0]
    blob = bytearray(f.read_bytes())
    at = int(where * len(blob))
    if how == "overwrite":
        n = min(300, len(blob) - at)
        blob[at : at + n] = bytes((x + 1) % 256 for x in blob[at : at + n])  # every byte changed
    elif how == "cut":
        blob = blob[:at]
    else:
        blob += b"\x00" * 10
    f.write_bytes(bytes(blob))
    event(f"{table} {how}")
    with pytest.raises(ds.Damaged) as exc:
        run_sql(root, f"SELECT count(*) FROM {table}")
    assert any(str(f) in p for p in exc.value.problems)
    _d, a, b = logs
    for log in (a, b):
        process_log(LogJob("m1", str(log)), Options(dataset=str(root)))
    assert run_sql(root, Q_LOGS) == built[1] and run_sql(root, Q_TIMELINE) == built[2]


def test_a_query_reading_only_the_summaries_does_not_need_the_timeline(built, tmp_path):
    root = copy_dataset(built[0], tmp_path / "ds")
    tl = sorted((root / "timeline").rglob("*.parquet"))[0]
    tl.write_bytes(tl.read_bytes()[:-50])
    assert run_sql(root, "SELECT count(*) FROM logs") == (["count_star()"], [(2,)])
    with pytest.raises(ds.Damaged, match=r"content differs|bytes, its commit record says"):
        run_sql(root, "SELECT count(*) FROM machine_logs m JOIN timeline t USING (machine, log_hash)")


# -- a data set path with glob characters is a path ----------------------------------------------------


def test_a_data_set_path_with_glob_characters_reads_that_data_set(built, logs, tmp_path):
    _d, a, _b = logs
    mine = ds.open_dataset(tmp_path / "ds[1]", create=True)
    process_log(LogJob("m7", str(a)), Options(dataset=str(mine)))
    copy_dataset(built[0], tmp_path / "ds1")  # what 'ds[1]' would match as a pattern
    assert run_sql(mine, "SELECT machine, count(*) FROM logs GROUP BY 1") == (
        ["machine", "count_star()"],
        [("m7", 1)],
    )
    r = run_cli("fleet", "query", str(mine), "SELECT DISTINCT machine FROM timeline", "--format", "csv")
    assert r.returncode == 0 and r.stdout.splitlines() == ["machine", "m7"], r.stderr
    r = run_cli("fleet", "report", str(mine), "--out", str(tmp_path / "r.html"))
    assert r.returncode == 0 and "m7" in (tmp_path / "r.html").read_text(), r.stderr


# -- quarantine rows and machines ------------------------------------------------------------------------


def test_a_log_quarantined_at_the_read_stage_leaves_the_quarantine_when_it_commits(logs, tmp_path):
    _d, a, _b = logs
    root = ds.open_dataset(tmp_path / "ds", create=True)
    late = tmp_path / "m3_late.log"
    r = process_log(LogJob("m3", str(late)), Options(dataset=str(root)))
    assert r["status"] == "quarantined" and "cannot read the log: No such file" in r["reason"]
    timed = process_log(LogJob("m3", str(a)), Options(dataset=str(root), timeout_s=1e-9))
    assert timed["status"] == "quarantined"
    assert run_sql(root, "SELECT stage FROM quarantine ORDER BY 1")[1] == [("read",), ("timeout",)]
    late.write_bytes(a.read_bytes())
    assert process_log(LogJob("m3", str(late)), Options(dataset=str(root)))["status"] == "done"
    assert run_sql(root, "SELECT stage FROM quarantine")[1] == [("timeout",)]  # the other log's row stays
    assert process_log(LogJob("m3", str(a)), Options(dataset=str(root)))["status"] == "skipped"  # same content
    assert run_sql(root, "SELECT count(*) FROM quarantine")[1] == [(0,)]  # committed: its rows went


def test_a_log_belongs_to_one_machine_and_a_machine_can_be_dropped(logs, tmp_path, client):
    _d, a, b = logs
    root = tmp_path / "ds"
    rep = run_fleet([LogJob("m1", str(a)), LogJob("m1", str(b))], Options(dataset=str(root)), client=client)
    assert rep.counts["done"] == 2
    rep = run_fleet([LogJob("m2", str(a))], Options(dataset=str(root)), client=client)
    assert rep.counts["done"] == 1 and rep.moved == [{"log": str(a), "from": "m1", "to": "m2"}]
    _, rows = run_sql(root, "SELECT machine, log_name FROM logs ORDER BY 1")
    assert rows == [("m1", "m1_b.log"), ("m2", "m1_a.log")]  # counted once, under its new machine
    _, rows = run_sql(root, "SELECT machine, count(DISTINCT log_hash) FROM timeline GROUP BY 1 ORDER BY 1")
    assert rows == [("m1", 1), ("m2", 1)]
    r = run_cli("fleet", "drop", str(root), "--machine", "m1", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["removed"]["m1"]["logs"] == 1
    assert run_sql(root, "SELECT DISTINCT machine FROM timeline")[1] == [("m2",)]
    r = run_cli("fleet", "drop", str(root), "--machine", "m1")
    assert r.returncode == 66 and "no rows of machine m1" in r.stderr
    r = run_cli("fleet", "drop", str(root), "--machine", "m1\n")
    assert r.returncode == 65 and "not usable as a partition name" in r.stderr


def test_the_same_content_under_two_names_is_replayed_once(logs, tmp_path, client):
    _d, a, _b = logs
    twin = tmp_path / "m5_twin.log"
    twin.write_bytes(a.read_bytes())
    rep = run_fleet(
        [LogJob("m4", str(a)), LogJob("m5", str(twin))], Options(dataset=str(tmp_path / "ds")), client=client
    )
    assert (rep.counts["done"], rep.counts["skipped"]) == (1, 1)
    assert any("has the same content as" in n for n in rep.notes)


# -- a commit is all or nothing; a cleanup never cuts one short ------------------------------------------


PROV = ds.Provenance("ab" * 32, "c" * 64, "d" * 64, "e" * 64)


def staged_writer(root: Path) -> ds.LogWriter:
    """A writer with two timeline rows staged on disk (flushed at once)."""
    import numpy as np

    w = ds.LogWriter(root, "m1", PROV)
    w.ROW_GROUP = 1
    w.add_rows("timeline", {"time_s": np.array([86400.0, 86401.0]), "cm_ratio_raw_pct": np.array([99.0, 98.0])})
    return w


def test_a_cleanup_waits_for_the_commits_and_leaves_a_live_writers_staging_folder(tmp_path):
    """What `fleet replay` interrupted by SIGINT did (2 in 4 runs under load): the driver removed the
    staging area while a worker committed. Now the cleanup waits for the commits in progress, and
    removes only what writers no longer hold."""
    root = ds.open_dataset(tmp_path / "ds", create=True)
    live = staged_writer(root)
    dead = root / ds.STAGING / "0123-dead.0000aaaa"  # a killed worker's folder: no lock held
    (dead / "timeline").mkdir(parents=True)
    (dead / "timeline" / "x.parquet").write_bytes(b"PAR1")
    orphan = ds.partition(root, "timeline", "m1", "1970-01-02") / "0123-orphan.parquet"  # an interrupted commit
    orphan.parent.mkdir(parents=True)
    orphan.write_bytes(b"PAR1")
    with ds.commit_lock(root):  # a commit in progress: the cleanup waits for it, here not at all
        assert ds.remove_orphans(root, wait_s=0) == 0
        assert dead.exists() and orphan.exists() and live.stage.exists()
    assert ds.remove_orphans(root, wait_s=0) == 2  # the dead folder and the orphan
    assert not dead.exists() and not orphan.exists()
    assert live.stage.exists() and (root / ds.STAGING / f"{live.stage.name}.lock").exists()  # its writer lives
    live.commit({"log_name": "a.log", "ticks": 2}, "1970-01-02")
    record = ds.check_committed(root, "m1", PROV.key)
    assert record is not None and [f["table"] for f in json.loads(record[ds.FILES])] == ["timeline"]
    assert sorted(p.name for p in (root / ds.STAGING).iterdir()) == []  # the folder and its lock gone


def test_a_commit_whose_staged_files_are_gone_commits_nothing(tmp_path):
    """A staged file removed before the commit (as the old cleanup did): the commit fails, naming it,
    and no summary says the log is there (before: a summary listing no files, skipped for ever)."""
    import shutil

    root = ds.open_dataset(tmp_path / "ds", create=True)
    w = staged_writer(root)
    shutil.rmtree(w.stage / "timeline")
    with pytest.raises(ds.DatasetError, match="a staged file of the log is gone") as exc:
        w.commit({"log_name": "a.log", "ticks": 2}, "1970-01-02")
    assert exc.value.kind == Kind.TEMPFAIL
    w.abort()
    assert not ds.is_committed(root, "m1", PROV.key) and not list((root / "logs").rglob("*.parquet"))
    assert not list((root / ds.STAGING).iterdir())


def test_a_commit_record_without_its_files_is_redone_not_skipped(built, logs, tmp_path):
    """A log committed with no files (its record lists none, its data files are not there): the next
    replay finds it damaged and re-does it."""
    root = copy_dataset(built[0], tmp_path / "ds")
    summary = sorted((root / "logs").rglob("*.parquet"))[0]
    record = ds.read_record(summary)
    for f in ds.data_files(root, "m1", record, "timeline") + ds.data_files(root, "m1", record, "events"):
        f.unlink()
    ds.write_record(summary, {k: v for k, v in record.items() if k != ds.RECORD_HASH} | {ds.FILES: "[]"})
    with pytest.raises(ds.Damaged, match="lists no timeline file"):
        ds.check_committed(root, "m1", summary.stem)
    _d, a, b = logs
    res = [process_log(LogJob("m1", str(log)), Options(dataset=str(root))) for log in (a, b)]
    assert sorted(r["status"] for r in res) == ["done", "skipped"]
    assert any("lists no timeline file" in (r.get("redone") or "") for r in res)
    assert run_sql(root, Q_LOGS) == built[1] and run_sql(root, Q_TIMELINE) == built[2]


# -- a full disk, no permission ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("err", "kind"),
    [(errno.ENOSPC, Kind.TEMPFAIL), (errno.EDQUOT, Kind.TEMPFAIL), (errno.EACCES, Kind.NO_PERMISSION),
     (errno.EROFS, Kind.CANT_CREATE)],
)  # fmt: skip
def test_an_os_error_of_the_data_set_ends_the_run_with_its_kind_and_path(
    logs, tmp_path, client, monkeypatch, err, kind
):
    _d, a, b = logs
    real = ds._write_table

    def failing(table, path, *options):
        if "_staging" in str(path) and "logs" in Path(path).parts:
            raise OSError(err, os.strerror(err), str(path))
        return real(table, path, *options)

    monkeypatch.setattr(ds, "_write_table", failing)
    with pytest.raises(ds.DatasetError) as exc:
        run_fleet([LogJob("m1", str(a)), LogJob("m1", str(b))], Options(dataset=str(tmp_path / "ds")), client=client)
    assert exc.value.kind == kind
    msg = str(exc.value)
    assert "_staging" in msg and os.strerror(err) in msg and "run the same command again" in msg
    assert not ds.committed(tmp_path / "ds")
    monkeypatch.setattr(ds, "_write_table", real)
    rep = run_fleet([LogJob("m1", str(a)), LogJob("m1", str(b))], Options(dataset=str(tmp_path / "ds")), client=client)
    assert rep.counts["done"] == 2  # nothing half-written was left in the way


# -- what a quarantine reason may say -----------------------------------------------------------------------


LEFT_OUT = "(...) [quoted content left out]"


@pytest.mark.parametrize(
    ("text", "want"),
    [
        (
            "/f/evil.log: line 1: not a candump -l line: 'root:*:20228:0:99999:7:::'",
            f"/f/evil.log: line 1: not a candump -l line: {LEFT_OUT}",
        ),
        ("/f/x.log: line 3: bad data 'secret'\nsecond line 'more'", f"/f/x.log: line 3: bad data {LEFT_OUT}"),
        (
            "cannot read as a .asc log: ValueError: could not convert string to float: b'k3y'",
            f"cannot read as a .asc log: ValueError: could not convert string to float: {LEFT_OUT}",
        ),
        ("/f/it's.log: line 2: not a candump -l line: 'x'", f"/f/it's.log: line 2: not a candump -l line: {LEFT_OUT}"),
        ("no frames in the log", "no frames in the log"),
        ("a\x1b[31mred\x07", "a?[31mred?"),
    ],
)
def test_a_quarantine_reason_never_quotes_the_file(text, want):
    assert safe_reason(text, ["/f/it's.log", "/f/evil.log"]) == want


def test_a_reason_is_one_short_line():
    out = safe_reason("x" * 1000 + "\nsecond")
    assert len(out) == 300 and out.endswith("...") and "second" not in out


def test_an_old_data_set_is_named_as_such(tmp_path):
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "_dataset.json").write_text('{"format": "cmcan-fleet/1"}')
    with pytest.raises(CmcanError, match=r"older cmcan.*replay the logs into a new data set"):
        ds.open_dataset(tmp_path / "old", create=False)
