"""Fleet pieces: tick reductions, log statistics, sources, the data set's commit and quarantine, SQL."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

pytest.importorskip("pyarrow")
pytest.importorskip("duckdb")

from cmcan.errors import CmcanError
from cmcan.fleet import dataset as ds
from cmcan.fleet.aggregate import Downsampler, LogStats, reduce_runs
from cmcan.fleet.query import format_rows, run_sql
from cmcan.fleet.sources import discover, machine_of
from cmcan.fleet.task import LogJob, Options, process_log
from cmcan.monitor.gating import Gate
from cmcan.monitor.tick import TickColumns
from tests.conftest import ROOT, run_cli
from tests.helpers import sim_frames, write_log


def ticks(n: int, seed: int = 0, t0: float = 1767225600.0, period: float = 0.1) -> TickColumns:
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) * period
    if n > 10:  # a gap of a few seconds, as between bursts
        t[n // 2 :] += 7.3
    gate = np.where(rng.random(n) < 0.6, 0, rng.integers(1, 10, n)).astype(np.int8)
    ev = (gate == 0) | (gate == 6)  # evaluating or extrapolated
    return TickColumns(
        t_s=t,
        gate=gate,
        measured=rng.uniform(1000, 3000, n),
        predicted=np.where(ev, rng.uniform(1000, 3000, n), 0.0),
        whitebox=np.where(ev, rng.uniform(1000, 3000, n), 0.0),
        ratio_raw_pct=np.where(ev, rng.normal(99, 2, n), 0.0),
        ratio_filt_pct=rng.normal(99, 1, n),
        extra_leak_lpm=rng.normal(1, 0.5, n),
        filt_valid=rng.random(n) < 0.7,
        level=rng.integers(0, 4, n).astype(np.int8),
        reason=rng.integers(0, 6, n).astype(np.int8),
        time_below_s=rng.uniform(0, 100, n),
    )


def slice_cols(c: TickColumns, a: int, b: int) -> TickColumns:
    return type(c)(**{f.name: getattr(c, f.name)[a:b] for f in dataclasses.fields(c)})


def naive_rows(c: TickColumns, rate_hz: float) -> dict[str, list]:
    """The timeline's reductions written out as a loop over bins, to check the vectorised ones."""
    out: dict[str, list] = {
        k: []
        for k in (
            "time_s",
            "ticks",
            "evaluated",
            "cm_ratio_raw_pct",
            "cm_ratio_filt_pct",
            "warning_level",
            "measured",
            "gate",
        )
    }
    bins = np.floor(c.t_s * rate_hz + 1e-9)
    i = 0
    while i < len(c):
        j = i
        while j < len(c) and bins[j] == bins[i]:
            j += 1
        ev = [k for k in range(i, j) if c.gate[k] in (0, 6)]
        valid = [k for k in range(i, j) if c.filt_valid[k]]
        out["time_s"].append(bins[i] / rate_hz)
        out["ticks"].append(j - i)
        out["evaluated"].append(len(ev))
        out["cm_ratio_raw_pct"].append(np.mean([c.ratio_raw_pct[k] for k in ev]) if ev else np.nan)
        out["cm_ratio_filt_pct"].append(c.ratio_filt_pct[valid[-1]] if valid else np.nan)
        out["warning_level"].append(max(c.level[i:j]))
        out["measured"].append(np.mean(c.measured[i:j]))
        out["gate"].append(c.gate[j - 1])
        i = j
    return out


@pytest.mark.parametrize("rate_hz", [1.0, 0.2, 2.5])
def test_reduce_runs_matches_a_loop_over_bins(rate_hz):
    c = ticks(500, seed=3)
    got = reduce_runs(c, rate_hz)
    want = naive_rows(c, rate_hz)
    for k, v in want.items():
        np.testing.assert_allclose(np.asarray(got[k], dtype=float), np.asarray(v, dtype=float), rtol=1e-12, err_msg=k)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.integers(1, 60), min_size=1, max_size=12), st.sampled_from([1.0, 0.5, 3.0]))
def test_downsampler_over_chunks_equals_the_whole(cuts, rate_hz):
    c = ticks(sum(cuts), seed=len(cuts))
    d = Downsampler(rate_hz)
    parts, a = [], 0
    split_bin = False
    for n in cuts:
        chunk = slice_cols(c, a, a + n)
        if a > 0 and np.floor(c.t_s[a] * rate_hz + 1e-9) == np.floor(c.t_s[a - 1] * rate_hz + 1e-9):
            split_bin = True
        parts.append(d.add(chunk))
        a += n
    parts.append(d.finish())
    event(f"a bin cut by a chunk boundary: {split_bin}")
    whole = reduce_runs(c, rate_hz)
    for k, v in whole.items():
        got = np.concatenate([p[k] for p in parts if p])
        np.testing.assert_array_equal(got, v, err_msg=k)


def test_a_tick_field_added_later_gets_a_column_by_its_type():
    @dataclasses.dataclass(frozen=True)
    class More(TickColumns):
        extrapolated: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, bool))
        flow_pred_lpm: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    base = dataclasses.replace(ticks(40), t_s=1767225600.0 + np.arange(40) * 0.1)
    c = More(
        **{f.name: getattr(base, f.name) for f in dataclasses.fields(base)},
        extrapolated=np.arange(40) % 5 == 0,
        flow_pred_lpm=np.arange(40.0),
    )
    d = Downsampler(1.0)
    rows = [d.add(slice_cols(c, 0, 15)), d.add(slice_cols(c, 15, 40)), d.finish()]
    share = np.concatenate([r["extrapolated_share"] for r in rows if r])
    flow = np.concatenate([r["flow_pred_lpm"] for r in rows if r])
    assert share.tolist() == [0.2] * 4
    assert flow.tolist() == [4.5, 14.5, 24.5, 34.5]


def test_log_stats_percentiles_and_trends_against_numpy():
    rng = np.random.default_rng(5)
    n = 20000
    t0 = 1767225600.0
    t = t0 + np.sort(rng.uniform(0, 36000, n))
    gate = np.where(rng.random(n) < 0.7, 0, 4).astype(np.int8)
    h = (t - t0) / 3600
    ratio = 100 - 0.3 * h + rng.normal(0, 0.5, n)
    leak = 0.2 * h + rng.normal(0, 0.1, n)
    c = TickColumns(
        t,
        gate,
        ratio * 20,
        np.full(n, 2000.0),
        np.full(n, 2000.0),
        np.where(gate == 0, ratio, 0.0),
        ratio,
        leak,
        np.ones(n, bool),
        np.zeros(n, np.int8),
        np.zeros(n, np.int8),
        np.zeros(n),
    )
    s = LogStats(t0=t0)
    for a in range(0, n, 3000):
        s.add(slice_cols(c, a, a + 3000))
    ev = gate == 0
    r = ratio[ev]
    quantised = np.rint(r / 0.01) * 0.01
    for q in (1, 5, 50, 95, 99):
        assert s.percentile(q) == pytest.approx(np.percentile(quantised, q, method="inverted_cdf"), abs=1e-9)
    row = s.row()
    assert row["cm_ratio_trend_pct_per_h"] == pytest.approx(np.polyfit(h[ev], r, 1)[0], rel=1e-9)
    assert row["extra_leak_trend_lpm_per_h"] == pytest.approx(np.polyfit(h[ev], leak[ev], 1)[0], rel=1e-9)
    assert row["cm_ratio_filt_last_pct"] == ratio[ev][-1]
    assert LogStats().row()["cm_ratio_p50_pct"] != LogStats().row()["cm_ratio_p50_pct"]  # NaN without data


# -- sources ------------------------------------------------------------------------------------------


def test_machine_rule_for_folders_and_file_names(tmp_path):
    root = tmp_path / "fleet"
    for rel in (
        "exc-017/2026/01/a.log",
        "exc-017/b.log.gz",
        "wl_3/c.blf",
        "dz-9_20260102.log",
        "lone.asc",
        "notes.txt",
        "wl_3/run.csv",
    ):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(b"")
    jobs = discover([str(root)])
    got = {Path(j.log).relative_to(root).as_posix(): j.machine for j in jobs}
    assert got == {
        "exc-017/2026/01/a.log": "exc-017",
        "exc-017/b.log.gz": "exc-017",
        "wl_3/c.blf": "wl_3",
        "dz-9_20260102.log": "dz-9",
        "lone.asc": "lone",
    }
    globbed = discover([str(root / "*" / "*.log*")])
    assert {j.machine for j in globbed} == {"exc-017"}
    assert machine_of(root / "dz-9_20260102.log", root) == "dz-9"


def test_manifest_paths_defaults_and_errors(tmp_path):
    (tmp_path / "m.csv").write_text(f"machine,log,config\nexc-1,logs/a.log,cfg/x.yaml\nexc-2,{tmp_path}/b.log,\n")
    jobs = discover([str(tmp_path / "m.csv")], config=str(tmp_path / "default.yaml"))
    want = LogJob("exc-1", str(tmp_path / "logs/a.log"), str(tmp_path / "cfg/x.yaml"), None)
    assert jobs[0] == dataclasses.replace(want, origin=f"{tmp_path / 'm.csv'} line 2")  # errors name the line
    assert jobs[1].config == str(tmp_path / "default.yaml")  # an absolute path under the manifest's folder
    (tmp_path / "bad.csv").write_text("machine,file\nx,y\n")
    with pytest.raises(CmcanError, match=r"bad.csv: manifest lacks column\(s\) log"):
        discover([str(tmp_path / "bad.csv")])
    (tmp_path / "id.csv").write_text("machine,log\nexc 1/2,a.log\n")
    with pytest.raises(CmcanError, match=r"id.csv: line 2: machine id 'exc 1/2'"):
        discover([str(tmp_path / "id.csv")])
    with pytest.raises(CmcanError, match="no such file, folder or matching glob"):
        discover([str(tmp_path / "missing")])


# -- one log through the task -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleetlog")
    _run, frames = sim_frames("single_set_leakage", duration_h=0.05)
    return write_log(d / "m1_a.log", frames)


def test_a_log_is_committed_once_and_skipped_after(small_log, tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    opt = Options(dataset=str(root))
    job = LogJob("m1", str(small_log))
    r = process_log(job, opt)
    assert r["status"] == "done" and r["frames"] > 10000
    assert process_log(job, opt)["status"] == "skipped"
    _, rows = run_sql(root, "SELECT count(*), min(log_hash), min(model_hash), min(cmcan_version) FROM timeline")
    assert rows[0][0] > 100
    assert rows[0][1] == ds.sha256_file(small_log)
    from cmcan.model import default_model_path

    assert rows[0][2] == ds.sha256_file(default_model_path())
    _, logs = run_sql(root, "SELECT machine, evaluated, ticks, count_frames_total, day FROM logs")
    assert logs[0][0] == "m1" and 0 < logs[0][1] <= logs[0][2] and logs[0][3] == r["frames"]
    # one file per table and day, named by the log's key
    files = sorted(p.relative_to(root).as_posix() for p in root.rglob("*.parquet"))
    assert all(f.endswith(f"{r['key']}.parquet") for f in files)
    assert not list((root / ds.STAGING).glob("*"))


def test_timeline_rate_sets_the_rows(small_log, tmp_path):
    counts = {}
    for rate in (1.0, 0.1):
        root = ds.open_dataset(tmp_path / f"ds{rate}", create=True)
        process_log(LogJob("m1", str(small_log)), Options(dataset=str(root), rate_hz=rate))
        counts[rate] = run_sql(root, "SELECT count(*), sum(ticks), max(ticks) FROM timeline")[1][0]
    assert counts[1.0][1] == counts[0.1][1]  # every tick in some row
    assert counts[1.0][2] <= 10 and counts[0.1][2] <= 100
    assert counts[0.1][0] < counts[1.0][0] / 5


def test_bad_logs_go_to_quarantine_with_the_reason(small_log, tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    opt = Options(dataset=str(root))
    garbage = tmp_path / "m2_x.log"
    garbage.write_bytes(b"\x00\xff not a log at all\n" * 50)
    other = tmp_path / "m3_x.log"  # well-formed frames, but none the configuration knows
    other.write_text("".join(f"({1767225600 + i * 0.01:.6f}) can0 7FF#0011223344556677\n" for i in range(500)))
    missing = tmp_path / "m4_gone.log"
    res = {
        "m2": process_log(LogJob("m2", str(garbage)), opt),
        "m3": process_log(LogJob("m3", str(other)), opt),
        "m4": process_log(LogJob("m4", str(missing)), opt),
        "m5": process_log(LogJob("m5", str(small_log)), Options(dataset=str(root), timeout_s=1e-9)),
    }
    assert {k: v["status"] for k, v in res.items()} == dict.fromkeys(res, "quarantined")
    _, rows = run_sql(root, "SELECT machine, stage, reason FROM quarantine ORDER BY machine")
    got = {m: (stage, reason) for m, stage, reason in rows}
    assert got["m2"][0] == "replay" and "cannot read as a CAN log" in got["m2"][1] and "line 1" in got["m2"][1]
    assert got["m3"][0] == "check" and "wrong DBC" in got["m3"][1] and "0x100" in got["m3"][1]
    assert got["m4"][0] == "read" and "cannot read the log" in got["m4"][1]
    assert got["m5"][0] == "timeout"
    assert run_sql(root, "SELECT count(*) FROM logs")[1][0][0] == 0
    # quarantined with the same inputs: skipped on the next run unless asked to retry
    assert process_log(LogJob("m2", str(garbage)), opt)["status"] == "skipped"
    assert (
        process_log(LogJob("m2", str(garbage)), Options(str(root), retry_quarantined=True))["status"] == "quarantined"
    )
    # the timed-out log goes through when retried with time enough, and leaves the quarantine
    assert process_log(LogJob("m5", str(small_log)), Options(str(root), retry_quarantined=True))["status"] == "done"
    assert "m5" not in {r[0] for r in run_sql(root, "SELECT machine FROM quarantine")[1]}


def test_an_interrupted_commit_leaves_no_rows_and_is_cleaned(small_log, tmp_path, monkeypatch):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    opt = Options(dataset=str(root))
    real_replace = ds.os.replace
    calls = []

    def crash_after_first(src, dst):
        if ds.STAGING not in str(dst):
            calls.append(dst)
        if len(calls) == 2:
            raise KeyboardInterrupt  # Ctrl-C between two renames of the commit
        return real_replace(src, dst)

    monkeypatch.setattr(ds.os, "replace", crash_after_first)
    with pytest.raises(KeyboardInterrupt):
        process_log(LogJob("m1", str(small_log)), opt)
    monkeypatch.setattr(ds.os, "replace", real_replace)
    assert any((root / "timeline").rglob("*.parquet"))  # a data file made it in...
    assert run_sql(root, "SELECT count(*) FROM timeline")[1][0][0] == 0  # ...but no query sees it
    assert ds.remove_orphans(root) >= 1
    assert not any((root / "timeline").rglob("*.parquet"))
    assert process_log(LogJob("m1", str(small_log)), opt)["status"] == "done"


def test_new_inputs_replace_a_logs_old_results(small_log, tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    process_log(LogJob("m1", str(small_log)), Options(dataset=str(root)))
    cfg = tmp_path / "cfg.yaml"
    text = (ROOT / "config" / "cmcan.yaml").read_text().replace("../dbc/cmcan.dbc", str(ROOT / "dbc" / "cmcan.dbc"))
    cfg.write_text(text.replace("low_pct: 98.0", "low_pct: 97.0"))
    r = process_log(LogJob("m1", str(small_log), str(cfg)), Options(dataset=str(root)))
    assert r["status"] == "done"
    _, rows = run_sql(root, "SELECT count(*), count(DISTINCT config_hash), min(threshold_low_pct) FROM logs")
    assert rows[0] == (1, 1, 97.0)
    names = {p.stem for p in root.rglob("*.parquet")}
    assert names == {r["key"]}


def test_a_data_set_is_not_created_over_other_files(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "mine.txt").write_text("keep")
    with pytest.raises(CmcanError, match="not a cmcan fleet data set"):
        ds.open_dataset(tmp_path / "x", create=True)
    with pytest.raises(CmcanError, match=r"no _dataset\.json"):
        ds.open_dataset(tmp_path / "x", create=False)
    root = ds.open_dataset(tmp_path / "y", create=True)
    assert json.loads((root / "_dataset.json").read_text())["format"] == ds.FORMAT
    with ds.writer_lock(root), pytest.raises(CmcanError, match=r"another cmcan fleet replay"), ds.writer_lock(root):
        pass


def test_queries_on_an_empty_data_set_and_formats(tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    for t in ("timeline", "events", "logs", "quarantine", "machine_logs"):
        assert run_sql(root, f"SELECT count(*) FROM {t}")[1] == [(0,)]
    with pytest.raises(CmcanError, match="query failed"):
        run_sql(root, "SELECT nope FROM logs")
    cols, rows = ["a", "b"], [(1, 2.5), (None, float("nan"))]
    assert format_rows(cols, rows, "csv") == "a,b\n1,2.5\n,nan\n"
    assert json.loads(format_rows(cols, rows[:1], "json")) == [{"a": 1, "b": 2.5}]
    table = format_rows(cols, rows, "table", max_rows=1)
    assert table.splitlines()[0].split() == ["a", "b"] and "2 rows, first 1 shown" in table


def test_cli_usage_errors(tmp_path):
    r = run_cli("simulate", "fleet", "--out", str(tmp_path / "f"))
    assert r.returncode == 64 and "--machines N and --hours H" in r.stderr
    r = run_cli("simulate", "healthy_mixed_100h", "--out", str(tmp_path / "x.csv"), "--machines", "3")
    assert r.returncode == 64 and "only apply to `cmcan simulate fleet`" in r.stderr
    r = run_cli("fleet", "replay", str(tmp_path / "nothing"), "--out", str(tmp_path / "ds"))
    assert r.returncode == 66 and "no such file, folder or matching glob" in r.stderr
    r = run_cli("fleet", "replay", str(tmp_path), "--out", str(tmp_path / "ds"), "--rate-hz", "0")
    assert r.returncode == 64 and "--rate-hz" in r.stderr
    r = run_cli("fleet", "query", str(tmp_path), "SELECT 1")
    assert r.returncode == 66 and "not a cmcan fleet data set" in r.stderr
    assert Gate.EVALUATING == 0  # the timeline's 'evaluated' counts this gate


def _worker_environ() -> dict:
    import logging
    import os

    env: dict = {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS")}
    env["log_level"] = logging.getLogger("distributed.worker").getEffectiveLevel()
    return env


def test_the_embedded_cluster_leaves_glibc_malloc_thresholds_alone(caplog):
    """Dask's nanny would set MALLOC_TRIM_THRESHOLD_, which freezes glibc's mmap threshold: a replay's
    chunk arrays are then mapped and faulted in afresh (about 1.6x the CPU per log). One thread per
    worker stays. Without -v the workers stay quiet below CRITICAL: a heartbeat meeting the scheduler's
    close logs a traceback at ERROR, which a user would read as the command's failure."""
    pytest.importorskip("distributed")
    import logging

    from cmcan.fleet.run import close_client, make_client

    caplog.set_level(logging.WARNING)  # cmcan without -v (another test in this process may have set INFO)
    client = make_client(None, 1)
    try:
        env = client.submit(_worker_environ, pure=False).result(timeout=60)
    finally:
        close_client(client)
        os.environ.pop("DASK_LOGGING__DISTRIBUTED", None)  # the nanny sets it here too; not for later tests
    assert env == {"MALLOC_TRIM_THRESHOLD_": None, "OMP_NUM_THREADS": "1", "log_level": logging.CRITICAL}


def test_a_dask_close_that_times_out_is_said_not_the_commands_end(caplog):
    """Under load the client's or cluster's close can time out after the work is written (Dask raises
    TimeoutError): logged, the cluster still closed, nothing raised."""
    from cmcan.fleet.run import close_client

    closed = []

    class Part:
        def __init__(self, name, fails):
            self.name, self.fails = name, fails

        def close(self, timeout):
            closed.append(self.name)
            if self.fails:
                raise TimeoutError(f"timed out after {timeout:g} s.")

    client = Part("client", fails=True)
    client.cluster = Part("cluster", fails=True)
    with caplog.at_level("WARNING", logger="cmcan.fleet"):
        close_client(client)
    assert closed == ["client", "cluster"]
    assert "did not close within 10 s" in caplog.text and "cluster" in caplog.text
