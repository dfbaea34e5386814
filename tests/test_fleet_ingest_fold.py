"""The uplink rows' layout in the data set (``cmcan.fleet.uplinkstore``): a batch committed as one flat
file per table, folded later into the machine/day partitions. Every row is read once before, during
and after a fold and after its sources are removed; a kill at any step of a fold or of the removal
leaves, after the next start, each row once and every id known; the ids stay deduplicated across a
fold and a restart; which records a fold takes when."""

from __future__ import annotations

import contextlib
import json
import pathlib
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import pytest

pytest.importorskip("pyarrow")
import pyarrow.parquet as pq

from cmcan.fleet import dataset as ds
from cmcan.fleet import ingest as ig
from cmcan.fleet import uplinkstore as store
from cmcan.fleet.uplinkrows import UPLINK_QUARANTINE, Batch, Seen, parse
from tests.test_fleet_ingest import T0, payload, topic

DAY_S = 86400.0
MACHINES = ("wl-1", "wl-2", "wl-3")
# the entries of payload(seq) lie at T0 + 900 s * seq: seq 1..95 on 2026-01-01, 96.. on 2026-01-02
OPEN_DAY_2 = T0 + 1.5 * DAY_S + store.DAY_GRACE_S  # 2026-01-01 closed, 2026-01-02 open
ALL_CLOSED = T0 + 30 * DAY_S


def commit(root: Path, seen: Seen, seqs: range, machines: tuple[str, ...] = MACHINES, bad: bytes = b"") -> None:
    b = Batch()
    for m in machines:
        for seq in seqs:
            b.add(parse(topic(m), payload(m, seq), "cmcan", T0), seen, T0, None)
    if bad:
        b.add(parse(topic("wl-1", "event"), bad, "cmcan", T0), seen, T0, None)
    store.commit_batch(root, b, store.key_of(len(store.record_paths(root)) + 1), T0)
    b.committed_into(seen)


def rows(root: Path) -> Counter[tuple[str, str, str]]:
    """(table, machine, id or reason) of every row the readers see, and how often."""
    files, problems = store.committed_files(root, verify=True)
    assert not problems, problems
    out: Counter[tuple[str, str, str]] = Counter()
    for table, listed in files.items():
        for machine, p in listed:
            for r in pq.read_table(p).to_pylist():
                what = r["reason"] if table == UPLINK_QUARANTINE else r["id"]
                out[(table, machine or r["machine"], what)] += 1
    return out


def expected(seqs: range, bad: int = 0) -> Counter[tuple[str, str, str]]:
    want = Counter({("uplink_summaries", m, f"7d58-{s}"): 1 for m in MACHINES for s in seqs})
    if bad:
        want[(UPLINK_QUARANTINE, "wl-1", "payload is not JSON (Expecting value: line 1 column 1 (char 0))")] = bad
    return want


def dataset(tmp_path: Path, batches: int = 3, per: int = 40) -> tuple[Path, Seen]:
    """``batches`` commits of ``per`` entries of each machine (from 2026-01-01 into 2026-01-02), and
    one hostile message each."""
    root = ds.open_dataset(tmp_path / "ds", create=True)
    seen = Seen()
    for k in range(batches):
        commit(root, seen, range(k * per + 1, (k + 1) * per + 1), bad=b"junk%d" % k)
    return root, seen


def test_a_fold_moves_the_closed_days_into_partitions_and_every_row_is_read_once(tmp_path):
    root, _seen = dataset(tmp_path)
    want = expected(range(1, 121), bad=0)
    got = rows(root)
    assert Counter({k: v for k, v in got.items() if k[0] != UPLINK_QUARANTINE}) == want
    assert sum(v for k, v in got.items() if k[0] == UPLINK_QUARANTINE) == 3
    before = rows(root)
    records, _ = store.read_records(root)
    rec = store.fold(root, store.unfolded(records), store.key_of(10), OPEN_DAY_2)
    assert rows(root) == before  # the sources are still there: read once all the same
    parts = sorted((f["machine"], f["day"]) for f in rec.files if f["machine"] is not None)
    assert parts == [(m, "2026-01-01") for m in MACHINES]  # one file per machine and closed day
    flat = {f["table"]: f for f in rec.flat_files()}
    assert flat["uplink_summaries"]["days"] == ["2026-01-02", "2026-01-02"]  # the open day stays flat
    assert rec.level == 1 and set(rec.folds) == {r.key for r in records}
    assert store.drop_folded(root, OPEN_DAY_2 + 1.0) == 0  # within the readers' grace: nothing goes
    assert store.drop_folded(root, OPEN_DAY_2 + store.READER_GRACE_S + 1.0) == 3 * 2 + 3
    assert rows(root) == before
    left = list(root.rglob("*.parquet"))
    assert len(left) == 3 + 2 + 1  # the partitions, the fold's flat summaries and quarantine, its record
    # the day closes: the fold's flat rows into their partitions
    records, _ = store.read_records(root)
    assert store.fold_due(store.unfolded(records), ALL_CLOSED, every=20) == [rec]
    rec2 = store.fold(root, [rec], store.key_of(11), ALL_CLOSED)
    assert sorted((f["machine"], f["day"]) for f in rec2.files if f["machine"]) == sorted(
        [(m, "2026-01-02") for m in MACHINES]
    )
    store.drop_folded(root, ALL_CLOSED + store.READER_GRACE_S + 1.0)
    assert rows(root) == before


def test_the_query_reads_flat_and_partitioned_rows_as_one_table(tmp_path):
    pytest.importorskip("duckdb")
    from cmcan.fleet.query import run_sql

    root, _seen = dataset(tmp_path)
    records, _ = store.read_records(root)
    store.fold(root, store.unfolded(records)[:2], store.key_of(10), OPEN_DAY_2)  # two of three batches
    commit(root, Seen(), range(500, 503), machines=("wl-9",))  # a machine only in a flat file
    sql = (
        "SELECT machine, day, count(*) AS n, count(DISTINCT id) AS ids FROM uplink_summaries GROUP BY ALL ORDER BY 1, 2"
    )
    _cols, got = run_sql(root, sql)
    assert [(m, str(d), n, i) for m, d, n, i in got] == [
        *[(m, day, n, n) for m in MACHINES for day, n in (("2026-01-01", 95), ("2026-01-02", 25))],
        ("wl-9", "2026-01-06", 3, 3),
    ]
    _cols, got = run_sql(root, "SELECT count(*) FROM uplink_quarantine")
    assert got == [(3,)]


def crash_after(monkeypatch, n: int, *targets: tuple[object, str]) -> list[int]:
    """The n-th call of any of ``targets`` raises KeyboardInterrupt (as a kill at that step)."""
    calls = [0]
    for obj, name in targets:
        real = getattr(obj, name)

        def wrapped(*a, _real=real, **kw):
            if calls[0] == n:
                raise KeyboardInterrupt
            calls[0] += 1
            return _real(*a, **kw)

        monkeypatch.setattr(obj, name, wrapped)
    return calls


def restarted(root: Path, now_s: float) -> Seen:
    """What the ingest does at start: the orphans of a cut-short commit or fold removed, the ids read."""
    ds.remove_orphans(root)
    store.prepare(root, now_s)
    seen, _records = store.load_seen(root)
    return seen


FOLD_STEPS = 9  # the fold's syncs (3) and moves (3 partitions, 2 flat files, the record)


@pytest.mark.parametrize("step", range(FOLD_STEPS + 1))
def test_a_kill_at_any_step_of_a_fold_loses_and_doubles_nothing(tmp_path, monkeypatch, step):
    root, _seen = dataset(tmp_path)
    before = rows(root)
    records, _ = store.read_records(root)
    calls = crash_after(monkeypatch, step, (store, "_move"), (ds, "sync_filesystem"))
    try:
        store.fold(root, store.unfolded(records), store.key_of(10), OPEN_DAY_2)
        killed = False
    except KeyboardInterrupt:
        killed = True
    monkeypatch.undo()
    assert killed == (step < FOLD_STEPS) and calls[0] == min(step, FOLD_STEPS)
    seen = restarted(root, OPEN_DAY_2)
    assert rows(root) == before
    assert all((f"{m}/7d58", s) in seen for m in MACHINES for s in range(1, 121))
    # and the ingest goes on: the fold done (again), its sources removed after the grace
    records, _ = store.read_records(root)
    if store.unfolded(records) != [r for r in records if r.kind == store.FOLD]:
        store.fold(root, store.unfolded(records), store.key_of(11), OPEN_DAY_2)
    restarted(root, OPEN_DAY_2 + store.READER_GRACE_S + 1.0)
    assert rows(root) == before
    assert not list(root.glob(f"{ds.STAGING}/ingest-*"))


REMOVAL_STEPS = 24  # per source record: its record removed, a sync, its two files; 6 records


@pytest.mark.parametrize("step", range(0, REMOVAL_STEPS + 1, 3))
def test_a_kill_while_folded_files_are_removed_loses_and_doubles_nothing(tmp_path, monkeypatch, step):
    """Two levels folded (batches into runs, runs into one): the removal goes deepest first, each
    record rewritten or removed and synced before its files go."""
    root, _seen = dataset(tmp_path, batches=4, per=20)
    before = rows(root)
    records, _ = store.read_records(root)
    first = store.unfolded(records)
    store.fold(root, first[:2], store.key_of(10), T0 + 0.5 * DAY_S)  # both days open: runs only
    store.fold(root, first[2:], store.key_of(11), T0 + 0.5 * DAY_S)
    records, _ = store.read_records(root)
    runs = store.unfolded(records)
    assert [r.level for r in runs] == [1, 1]
    last = store.fold(root, runs, store.key_of(12), OPEN_DAY_2)  # 2026-01-01 into the partitions
    assert rows(root) == before
    calls = crash_after(monkeypatch, step, (pathlib.Path, "unlink"), (ds, "sync_filesystem"))
    with contextlib.suppress(KeyboardInterrupt):  # (a kill)
        store.drop_folded(root, OPEN_DAY_2 + store.READER_GRACE_S + 1.0)
    monkeypatch.undo()
    assert calls[0] == min(step, REMOVAL_STEPS)
    assert rows(root) == before  # whatever the step: the readers see each row once
    restarted(root, OPEN_DAY_2 + store.READER_GRACE_S + 1.0)
    assert rows(root) == before
    records, _ = store.read_records(root)
    assert [r.key for r in store.unfolded(records)] == [last.key]
    assert len(records) == 1  # every source record gone (none of them held a partition file)


def test_ids_stay_deduplicated_across_a_fold_and_a_restart(tmp_path):
    root, _seen = dataset(tmp_path)
    records, _ = store.read_records(root)
    store.fold(root, store.unfolded(records), store.key_of(10), OPEN_DAY_2)
    store.drop_folded(root, OPEN_DAY_2 + store.READER_GRACE_S + 1.0)
    seen, records = store.load_seen(root)
    assert len(records) == 1
    b = Batch()
    outcome = [b.add(parse(topic(m), payload(m, s), "cmcan", T0), seen, T0, None) for m in MACHINES for s in (1, 120)]
    assert outcome == ["duplicate"] * 6  # copies the broker delivers again after the restart
    assert b.add(parse(topic("wl-1"), payload("wl-1", 121), "cmcan", T0), seen, T0, None) == "new"
    assert b.add(parse(topic("wl-1", "event"), b"junk0", "cmcan", T0), seen, T0, None) == "duplicate"


def record(key: str, level: int, days: list[str] | None) -> store.Record:
    files = ({"table": "uplink_summaries", "machine": None, "day": None, "days": days},)
    kind = store.BATCH if level == 0 else store.FOLD
    return store.Record(key, Path(key), kind, 0.0, files, (), {"level": level})


def test_what_a_fold_takes_when():
    today = ["2026-01-02", "2026-01-02"]
    batches = [record(f"b{i}", 0, ["2026-01-01", "2026-01-02"]) for i in range(3)]
    runs = [record(f"r{i}", 1, today) for i in range(2)]
    now = T0 + 1.5 * DAY_S + store.DAY_GRACE_S  # 2026-01-02 open
    assert store.fold_due(batches[:2] + runs, now, every=3) == []  # no level full; old rows in batches wait
    assert store.fold_due(batches + runs, now, every=3) == batches  # the batches' level is full
    assert store.fold_due(batches[:1] + runs, now, every=2) == runs  # the runs' level is full
    closed = T0 + 2.5 * DAY_S + store.DAY_GRACE_S  # 2026-01-02 closed: every run holds a closed day
    assert store.fold_due(batches[:1] + runs, closed, every=20) == batches[:1] + runs


def test_the_ingest_folds_in_its_thread_and_acknowledges_only_committed_batches(tmp_path):
    from tests.test_fleet_ingest import LoopClient

    now = [100.0]
    m = SimpleNamespace(max_inflight=10, topic_prefix="cmcan", reconnect_min_s=1.0, reconnect_max_s=2.0)
    root = ds.open_dataset(tmp_path / "ds", create=True)
    ing = ig.Ingest(root, m, Seen(), clock=lambda: now[0], wall=lambda: T0, fold_every=2)  # type: ignore[arg-type]
    client = LoopClient(root, ing)
    ing.client, ing.connected = client, True
    workers = set()
    for k in range(5):
        client.inbox = [(topic(mc), payload(mc, s)) for mc in MACHINES for s in range(k * 4 + 1, k * 4 + 5)]
        ing.step()
        ing.housekeeping()
        assert ing.folder.wait(60)
        if ing.folder.thread is not None:
            workers.add(ing.folder.thread)
    ing.folder.poll()
    assert ing.stats.batches == 5 and ing.folder.folds >= 2 and len(client.acked) == 60
    # every fold in one worker thread (a thread per fold took an allocator arena each: memory in steps)
    assert len(workers) == 1
    got = rows(root)
    assert got == expected(range(1, 21))
    seen, _records = store.load_seen(root)
    assert all((f"{mc}/7d58", s) in seen for mc in MACHINES for s in range(1, 21))
    ing.folder.stop()
    assert ing.folder.thread is None and not workers.pop().is_alive()
    assert json.loads((root / "_dataset.json").read_text())["format"] == ds.FORMAT


def test_a_reader_slower_than_the_grace_reads_again_on_a_fresh_listing(tmp_path):
    """A fold and the removal of what it replaced between a reader's listing and its reading: read
    again on the new files, the same rows; a file missing while the records stand still is raised."""
    pytest.importorskip("duckdb")
    from cmcan.errors import CmcanError
    from cmcan.fleet.query import read

    root, _seen = dataset(tmp_path)
    sql = "SELECT machine, count(*), count(DISTINCT id) FROM uplink_summaries GROUP BY 1 ORDER BY 1"
    calls = []

    def slow(con):
        calls.append(1)
        if len(calls) == 1:  # listed and opened; now the ingest folds and, past its grace, drops the sources
            records, _ = store.read_records(root)
            store.fold(root, store.unfolded(records), store.key_of(10), OPEN_DAY_2)
            assert store.drop_folded(root, OPEN_DAY_2 + store.READER_GRACE_S + 1.0) > 0
        return con.execute(sql).fetchall()

    assert read(root, slow, {"uplink_summaries"}) == [(m, 120, 120) for m in MACHINES]
    assert len(calls) == 2

    # a listed file gone with the records unchanged: damage, named, not read around
    gone = next(p for _m, p in store.committed_files(root)[0]["uplink_summaries"])
    gone.unlink()
    calls.clear()
    with pytest.raises(CmcanError, match="missing"):
        read(root, lambda con: calls.append(1) or con.execute(sql).fetchall(), {"uplink_summaries"})
    assert calls == []
