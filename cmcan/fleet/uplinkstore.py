"""The ingest's side of the fleet data set: each batch committed as one file per table, then folded
into the machine/day partitions.

**Why two steps.** A Parquet file costs some 3 ms to write, hash, rename and list whatever it holds.
A batch written straight into the machine/day partitions costs one file per machine it touches: with
1,000 machines that capped the ingest near 200 messages/s. So a batch is committed as ONE file per
table (``<table>/<key>.parquet``, ``machine`` and ``day`` as columns, sorted by them: a *flat* file),
and a **fold** later rewrites the flat files' rows of closed days into the partitions, one file per
machine and day. A day is closed :data:`DAY_GRACE_S` after its end, so the summaries of its last
minutes are in before it is folded; rows of the open day go into one flat file per table (a *run*)
which the next fold after the day closes rewrites into the partitions. Rows of a day that closed
long ago (a gateway that was offline) go into its partition at the next fold, as one more file.

**Records.** Every commit and every fold writes one commit record
(``uplink_commits/day=<d>/<key>.parquet``: ``kind`` batch or fold, the files it wrote, each with
table, machine and day (None for a flat file), size and SHA-256, the ids of its rows as ranges of
``seq`` per machine and stream, and the record's own ``record_sha256``). A fold's record also names
the records it replaces (``folds``) and holds their ids. A record is *live* when no present record
folds it: the data set's rows are the files of the live records, so a row is read once whether its
batch was folded yet or not.

**Crash safety.** A commit or a fold writes its files and its record into its own staging folder,
syncs the file system, moves the files into place, syncs, moves the record last and syncs: it is in
the data set exactly when its record is. A kill before that leaves files no record lists, removed at
the next start (:func:`prepare`). A fold's sources stay until :data:`READER_GRACE_S` after it (a
reader that listed them before the fold still finds them), then go: their files first, their record
last, the records they folded before them; a kill part-way leaves records still folded by a present
one, finished at the next start. The ids come from the live records, and a fold's record holds its
sources' ids: dedup is the same before and after a fold and across a restart.

Paths come from checked names only (the machine id a safe partition name, the day a date from a
time between 1970 and 9999, file names the commit's key).
"""

from __future__ import annotations

import datetime as dt
import json
import os
import shutil
import threading
import uuid
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cmcan.fleet import dataset as ds
from cmcan.fleet.uplinkrows import COLUMNS, UPLINK_COMMITS, UPLINK_QUARANTINE, UPLINK_TABLES, Batch, Seen, ids_record

BATCH, FOLD = "batch", "fold"
FOLDS = "folds"
DAY_GRACE_S = 3600.0  # a day is folded this long after its end: its last summaries are in by then
READER_GRACE_S = 60.0  # a fold's sources stay this long: a reader that listed them still finds them
FOLD_ROWS = 20_000  # rows of a table a fold holds in memory at once (machines taken in chunks)
ROW_GROUP_ROWS = 2_000  # of a flat file: a fold reading some machines skips the other row groups
DATA_TABLES = (*UPLINK_TABLES, UPLINK_QUARANTINE)


def key_of(now_ns: int) -> str:
    """A commit's key: sortable by commit time, unique."""
    return f"{now_ns:020d}-{uuid.uuid4().hex[:8]}"


def place_of(root: Path, f: dict[str, Any]) -> Path:
    """Where a file a commit record lists lies in the data set (a flat file has no machine)."""
    if f["machine"] is None:
        return root / f["table"] / f["name"]
    return ds.partition(root, f["table"], f["machine"], f["day"]) / f["name"]


# -- the records ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Record:
    """A commit record as read back (records written before folds existed are batches)."""

    key: str
    path: Path
    kind: str
    committed_s: float
    files: tuple[dict[str, Any], ...]
    folds: tuple[str, ...]
    row: dict[str, Any]

    def ids(self) -> dict[str, Any]:
        try:
            return json.loads(self.row["ids"])
        except (KeyError, TypeError, ValueError):
            raise ds.Damaged([f"{self.path}: its ids are not readable"]) from None

    @property
    def level(self) -> int:
        """A batch 0; a fold of records of level L, L + 1 (size-tiered: a row is rewritten about
        log(rows) / log(fold_every) times before its day closes)."""
        return int(self.row.get("level") or 0)

    def flat_files(self) -> list[dict[str, Any]]:
        return [f for f in self.files if f["machine"] is None]

    def first_day(self) -> str | None:
        """The earliest day of its flat files' rows (None: it has none)."""
        days = [f["days"][0] for f in self.flat_files() if f.get("days")]
        return min(days) if days else None


def record_paths(root: Path) -> list[Path]:
    base = root / UPLINK_COMMITS
    return sorted(p for p in base.glob("day=*/*.parquet") if not p.name.startswith(".")) if base.is_dir() else []


def read_record(path: Path) -> Record:
    row = ds.read_record(path)
    try:
        files = tuple(json.loads(row[ds.FILES]))
        folds = tuple(json.loads(row.get(FOLDS) or "[]"))
    except (KeyError, TypeError, ValueError):
        raise ds.Damaged([f"{path}: its files are not readable"]) from None
    return Record(path.stem, path, row.get("kind") or BATCH, float(row["committed_s"]), files, folds, row)


def read_records(root: Path) -> tuple[list[Record], list[str]]:
    """Every commit record, and the problems of the damaged ones."""
    out, problems = [], []
    for p in record_paths(root):
        try:
            out.append(read_record(p))
        except ds.Damaged as exc:
            problems += exc.problems
    return out, problems


def folded(records: Iterable[Record]) -> set[str]:
    """The keys of the records whose flat files a present fold replaced."""
    return {k for r in records for k in r.folds}


def live_files(records: list[Record]) -> list[dict[str, Any]]:
    """The data set's uplink files: every partition file, and the flat files no present fold replaced."""
    done = folded(records)
    return [f for r in records for f in r.files if f["machine"] is not None or r.key not in done]


def unfolded(records: list[Record]) -> list[Record]:
    """The records with flat files no fold replaced yet: what the next fold may take."""
    done = folded(records)
    return [r for r in records if r.key not in done and r.flat_files()]


def committed_files(root: Path, verify: bool = False) -> tuple[dict[str, list[tuple[str | None, Path]]], list[str]]:
    """The live files of each uplink table (and its quarantine) with their machine (None for a flat
    file: its rows carry their machine), and what is wrong: a damaged record, a listed file missing
    or of another size, and (``verify``) of other content than its SHA-256 says."""
    out: dict[str, list[tuple[str | None, Path]]] = {t: [] for t in DATA_TABLES}
    records, problems = read_records(root)
    for f in live_files(records):
        path = place_of(root, f)
        out[f["table"]].append((f["machine"], path))
        problem = ds.file_problem(path, f, verify)
        if problem:
            problems.append(problem)
    return out, problems


def load_seen(root: Path) -> tuple[Seen, list[Record]]:
    """The ids of every record (a fold's record holds those of what it folded: merging both is
    harmless), and the records; a damaged record is named (:class:`cmcan.fleet.dataset.Damaged`):
    which ids it held is unknown."""
    records, problems = read_records(root)
    if problems:
        raise ds.Damaged(problems)
    seen = Seen()
    for r in records:
        seen.merge(r.ids())
    return seen, records


# -- writing: a commit or a fold -------------------------------------------------------------------------


def _listed(path: Path, table: str, machine: str | None, day: str | None, name: str, **extra: Any) -> dict[str, Any]:
    return {
        "table": table,
        "machine": machine,
        "day": day,
        "name": name,
        "bytes": path.stat().st_size,
        "sha256": ds.sha256_file(path),
        **extra,
    }


class _Stage:
    """A commit's staging folder (locked while it lives: a cleanup leaves it be), its files
    numbered, so no folder per machine is made and removed."""

    def __init__(self, root: Path, key: str) -> None:
        self.root = root
        self.dir = root / ds.STAGING / f"ingest-{key}"
        with ds.writing("create a staging folder", self.dir):
            self.lock = ds.hold_stage(self.dir)
            self.dir.mkdir()
        self.files: list[tuple[Path, dict[str, Any]]] = []

    def next_path(self) -> Path:
        return self.dir / f"{len(self.files)}.parquet"

    def add(self, path: Path, entry: dict[str, Any]) -> None:
        self.files.append((path, entry))

    def commit(self, record: dict[str, Any], day: str, key: str) -> Record:
        """The record into the folder; the disk synced; the files into place, synced; the record last, synced."""
        record = {**record, ds.FILES: json.dumps([e for _p, e in self.files])}
        staged_record = self.dir / "record.parquet"
        with ds.writing("write a commit", self.dir):
            ds.write_record(staged_record, record)
            ds.sync_filesystem(self.dir)  # every staged file on the disk
        with ds.writing("commit", self.root / UPLINK_COMMITS), ds.commit_lock(self.root):
            for p, e in self.files:  # the data files first, on the disk before the record
                _move(p, place_of(self.root, e))
            ds.sync_filesystem(self.root)
            path = self.root / UPLINK_COMMITS / f"day={day}" / f"{key}.parquet"
            _move(staged_record, path)
            ds.sync_filesystem(self.root)  # the record in place: committed
        return read_record(path)

    def close(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)
        self.dir.with_name(self.dir.name + ".lock").unlink(missing_ok=True)
        os.close(self.lock)


def _move(src: Path, dest: Path) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    os.replace(src, dest)


def _schema(table: str, flat: bool) -> Any:
    import pyarrow as pa

    head = [pa.field("machine", pa.string()), pa.field("day", pa.date32())] if flat and table in UPLINK_TABLES else []
    return pa.schema([*head, *(pa.field(k, pa.type_for_alias(t)) for k, t in COLUMNS[table].items())])


def _flat_table(table: str, parts: list[tuple[str, str, list[dict[str, Any]]]]) -> Any:
    """One table's rows of a batch, with their machine and day, in (machine, day) order."""
    import pyarrow as pa

    schema = _schema(table, flat=True)
    cols: dict[str, list[Any]] = {k: [] for k in schema.names}
    for machine, day, rows in parts:
        if table in UPLINK_TABLES:  # (the quarantine's rows have a machine column of their own)
            cols["machine"] += [machine] * len(rows)
            cols["day"] += [dt.date.fromisoformat(day)] * len(rows)
        for k in COLUMNS[table]:
            cols[k] += [r.get(k) for r in rows]
    return pa.table({k: pa.array(v, schema.field(k).type) for k, v in cols.items()}, schema=schema)


def _days(t: Any) -> list[str] | None:
    import pyarrow.compute as pc

    if "day" not in t.column_names or not t.num_rows:
        return None
    mm = pc.min_max(t["day"])
    return [str(mm["min"].as_py()), str(mm["max"].as_py())]


def _write_flat(stage: _Stage, table: str, t: Any, key: str) -> None:
    p = stage.next_path()
    ds.write_parquet(p, t, row_group_rows=ROW_GROUP_ROWS)
    stage.add(p, _listed(p, table, None, None, f"{key}.parquet", days=_days(t)))


def commit_batch(root: Path, batch: Batch, key: str, now_s: float) -> Record | None:
    """The batch's rows (one flat file per table) and quarantine rows, and its commit record, into the
    data set (see the module's notes); returns the record (None when the batch had nothing to write)."""
    if not batch.rows and not batch.quarantine:
        return None
    by_table: dict[str, list[tuple[str, str, list[dict[str, Any]]]]] = {}
    for (table, machine, day), rows in sorted(batch.rows.items()):
        by_table.setdefault(table, []).append((machine, day, rows))
    if batch.quarantine:
        by_table[UPLINK_QUARANTINE] = [("", "", batch.quarantine)]
    stage = _Stage(root, key)
    try:
        with ds.writing("write a batch", stage.dir):
            for table, parts in by_table.items():
                _write_flat(stage, table, _flat_table(table, parts), key)
        record = {
            "batch": key,
            "kind": BATCH,
            "committed_s": now_s,
            "messages": len(batch),
            "rows": sum(len(r) for r in batch.rows.values()),
            "quarantined": len(batch.quarantine),
            "duplicates": batch.duplicates,
            "ids": json.dumps(ids_record(batch.dedups)),
            "level": 0,
            FOLDS: "[]",
        }
        return stage.commit(record, ds.day_of(now_s), key)
    finally:
        stage.close()


# -- the fold ---------------------------------------------------------------------------------------------


def open_day(now_s: float) -> str:
    """The earliest day not yet closed: its rows stay in flat files."""
    return ds.day_of(now_s - DAY_GRACE_S)


def fold_due(records: list[Record], now_s: float, every: int) -> list[Record]:
    """What to fold now of ``records`` (:func:`unfolded`), if anything: all of them once a fold's
    flat file holds a closed day's rows (its day closed since), else ``every`` records of one
    level (batches, or folds of them, ...), else nothing. A batch holding closed days' rows (late
    or old data) waits for its level's turn: one fold a batch would cost a file per machine again."""
    close = open_day(now_s)
    if any(r.kind == FOLD and (d := r.first_day()) is not None and d < close for r in records):
        return list(records)
    by_level: dict[int, list[Record]] = {}
    for r in records:
        by_level.setdefault(r.level, []).append(r)
    return next((rs for _lv, rs in sorted(by_level.items()) if len(rs) >= every), [])


class Stopped(Exception):
    """A fold given up because the ingest stops (nothing of it committed)."""


def fold(
    root: Path, sources: list[Record], key: str, now_s: float, stop: threading.Event | None = None
) -> Record | None:
    """The rows of the flat files of ``sources`` (records no fold took yet: :func:`unfolded`)
    rewritten: those of closed days into their machine/day partitions (one file per table, machine
    and day), the others into one flat file per table; one record for it all, naming the records
    whose flat files it replaces and holding their ids (see the module's notes).
    Memory is bounded by :data:`FOLD_ROWS` rows of a table. Returns the fold's record."""
    if not sources:
        return None
    seen = Seen()
    for r in sources:
        seen.merge(r.ids())
    stage = _Stage(root, key)
    rows = 0
    try:
        with ds.writing("fold batches", stage.dir):
            for table in DATA_TABLES:
                paths = [place_of(root, f) for r in sources for f in r.flat_files() if f["table"] == table]
                if paths:
                    rows += _fold_table(stage, table, paths, key, open_day(now_s), stop)
        record = {
            "batch": key,
            "kind": FOLD,
            "committed_s": now_s,
            "messages": 0,
            "rows": rows,
            "quarantined": 0,
            "duplicates": 0,
            "ids": json.dumps({"ranges": seen.ranges, "keys": sorted(seen.keys)}),
            "level": max(r.level for r in sources) + 1,
            FOLDS: json.dumps(sorted(r.key for r in sources)),
        }
        return stage.commit(record, ds.day_of(now_s), key)
    finally:
        stage.close()
        _release_memory()


def _release_memory() -> None:
    """The memory a fold's Arrow tables held back to the system: the allocator keeps freed pages for
    reuse, which reads as the ingest's memory growing fold by fold."""
    import pyarrow as pa

    pa.default_memory_pool().release_unused()


def _fold_table(stage: _Stage, table: str, paths: list[Path], key: str, open_d: str, stop: Any) -> int:
    """One table's rows of the sources, machine by machine (chunks of at most about FOLD_ROWS rows)."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.dataset as pds
    import pyarrow.parquet as pq

    source = pds.dataset([str(p) for p in paths], schema=_schema(table, flat=True), format="parquet")
    if table == UPLINK_QUARANTINE:  # few rows, no partitions: one flat file
        _write_flat(stage, table, source.to_table(), key)
        return 0
    counts: Counter[str] = Counter()
    for p in paths:  # the machine column alone: which machines, how many rows each
        vc = pc.value_counts(pq.read_table(p, columns=["machine"])["machine"])
        counts.update(dict(zip(vc.field("values").to_pylist(), vc.field("counts").to_pylist(), strict=True)))
    open_date = pa.scalar(dt.date.fromisoformat(open_d), pa.date32())
    run: Any = None  # the flat file of the open day's rows, written in machine order
    run_path = stage.dir / f"run-{table}.parquet"  # (the partition files are numbered meanwhile)
    run_days: list[str] = []
    n = 0
    try:
        for lo, hi in _chunks(counts):
            if stop is not None and stop.is_set():
                raise Stopped
            field = pc.field("machine")
            t = source.to_table(filter=(field >= lo) & (field <= hi)).sort_by(
                [("machine", "ascending"), ("day", "ascending"), ("time_s", "ascending")]
            )
            n += t.num_rows
            closed = pc.less(t["day"], open_date)
            _write_partitions(stage, table, t.filter(closed), key)
            rest = t.filter(pc.invert(closed))
            if rest.num_rows:
                if run is None:
                    run = ds.parquet_writer(run_path, rest.schema)
                run.write_table(rest, row_group_size=ROW_GROUP_ROWS)
                run_days += _days(rest) or []
    finally:
        if run is not None:
            run.close()
    if run is not None:
        stage.add(run_path, _listed(run_path, table, None, None, f"{key}.parquet", days=[min(run_days), max(run_days)]))
    return n


def _chunks(counts: Counter[str]) -> list[tuple[str, str]]:
    """Consecutive machines (sorted) in ranges of at most FOLD_ROWS rows (a machine with more is alone)."""
    out: list[tuple[str, str]] = []
    lo, rows = None, 0
    prev = None
    for m in sorted(counts):
        if lo is not None and rows + counts[m] > FOLD_ROWS:
            out.append((lo, prev))  # type: ignore[arg-type]
            lo, rows = None, 0
        if lo is None:
            lo = m
        rows += counts[m]
        prev = m
    if lo is not None:
        out.append((lo, prev))  # type: ignore[arg-type]
    return out


def _write_partitions(stage: _Stage, table: str, t: Any, key: str) -> None:
    """Rows sorted by machine and day, one file per (machine, day), without those columns (the path
    holds them, as in the log-derived partitions)."""
    import numpy as np

    if not t.num_rows:
        return
    machines = t["machine"].to_numpy(zero_copy_only=False)
    days = t["day"].cast("int32").to_numpy(zero_copy_only=False)
    cut = np.flatnonzero((machines[1:] != machines[:-1]) | (days[1:] != days[:-1])) + 1
    body = t.drop_columns(["machine", "day"])
    for a, b in zip([0, *cut.tolist()], [*cut.tolist(), t.num_rows], strict=True):
        day = ds.day_of(float(days[a]) * 86400.0)
        p = stage.next_path()
        ds.write_parquet(p, body.slice(a, b - a))
        stage.add(p, _listed(p, table, str(machines[a]), day, f"{key}.parquet"))


# -- what a fold leaves, and what a kill leaves -----------------------------------------------------------


def drop(root: Path, records: dict[str, Record], key: str) -> int:
    """The flat files of a folded record gone. The records it folded first (deepest first: a record
    must not stop folding what it folded while that is still there), then its record rewritten
    without its flat files (or removed when nothing else is left in it), synced, then the files (a
    kill before leaves files no record lists, removed at the next start). Returns the files removed."""
    r = records.pop(key, None)
    if r is None:
        return 0
    n = sum(drop(root, records, k) for k in r.folds)
    flat = r.flat_files()
    if not flat:
        return n
    kept = [f for f in r.files if f["machine"] is not None]
    with ds.writing("remove folded files", r.path):
        if kept:
            ds.write_record(r.path, {**_without_hash(r.row), ds.FILES: json.dumps(kept)})
        else:
            r.path.unlink(missing_ok=True)
        ds.sync_filesystem(r.path.parent)
        for f in flat:
            place_of(root, f).unlink(missing_ok=True)
    return n + len(flat) + (0 if kept else 1)


def _without_hash(row: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in row.items() if k != ds.RECORD_HASH}


def drop_folded(root: Path, now_s: float, grace_s: float = READER_GRACE_S) -> int:
    """The flat files folded by a record committed more than ``grace_s`` ago (see :func:`drop`)."""
    records, _problems = read_records(root)
    by_key = {r.key: r for r in records}
    n = 0
    for r in reversed(records):  # the newest first: a chain of folds goes deepest first (see drop)
        if r.committed_s <= now_s - grace_s:
            for k in r.folds:
                n += drop(root, by_key, k)
    return n


def prepare(root: Path, now_s: float) -> int:
    """At start (one ingest per data set): what a kill left: files of the uplink tables no record
    lists (a commit or fold cut short), temporaries, and flat files of folds past their grace."""
    records, _problems = read_records(root)  # a damaged record is named by load_seen
    listed = {place_of(root, f) for r in records for f in r.files}
    n = 0
    for table in (*DATA_TABLES, UPLINK_COMMITS):
        base = root / table
        if not base.is_dir():
            continue
        for f in base.rglob("*"):
            is_tmp = f.name.startswith(".") and f.name.endswith(".tmp")
            if f.is_file() and (is_tmp or (table != UPLINK_COMMITS and f.suffix == ".parquet" and f not in listed)):
                f.unlink(missing_ok=True)
                n += 1
    return n + drop_folded(root, now_s)
