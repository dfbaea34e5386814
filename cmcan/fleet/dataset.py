"""The fleet data set on disk: tables, layout, provenance, and each log's atomic commit.

Layout (hive partitioning, one Parquet file per log and partition; ``docs/fleet.md`` has the columns)::

    DATASET/_dataset.json                                    format, what wrote it
    DATASET/timeline/machine=<m>/day=<YYYY-MM-DD>/<key>.parquet
    DATASET/events/machine=<m>/day=<YYYY-MM-DD>/<key>.parquet
    DATASET/logs/machine=<m>/day=<YYYY-MM-DD>/<key>.parquet  one row per log: the commit record
    DATASET/quarantine/machine=<m>/<key>.parquet             logs that failed, with the reason

``<key>`` is ``<first 16 hex of the log's SHA-256>-<12 hex of its provenance>`` (the hashes of the
configuration, DBC and model it was replayed with), so a log replayed again with the same inputs
maps to the same files and a changed model to new ones.

A log is written to ``DATASET/_staging/`` first, then committed: the old results of the same log
(another provenance) are removed summary first, the new timeline and events files are renamed into
place, and the summary last. A log is in the data set exactly when its summary file is; a crash or
Ctrl-C part-way leaves at most files without a summary, which :func:`remove_orphans` deletes at the
start of the next run and which :mod:`cmcan.fleet.query` never shows.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import re
import shutil
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cmcan import __version__
from cmcan.errors import CmcanError, Kind

FORMAT = "cmcan-fleet/1"
TABLES = ("timeline", "events", "logs", "quarantine")
DATA_TABLES = ("timeline", "events")  # rows of a log, committed before its summary
SUMMARY_TABLE = "logs"
STAGING = "_staging"
MACHINE_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
HASH_CHUNK = 1 << 20


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class Provenance:
    """What a row was computed from: the log's content and the inputs it was replayed with."""

    log_hash: str
    config_hash: str
    dbc_hash: str
    model_hash: str
    cmcan_version: str = __version__

    @property
    def inputs_hash(self) -> str:
        return hashlib.sha256(f"{self.config_hash}:{self.dbc_hash}:{self.model_hash}".encode()).hexdigest()[:12]

    @property
    def key(self) -> str:
        return f"{self.log_hash[:16]}-{self.inputs_hash}"

    def columns(self) -> dict[str, str]:
        return {
            "log_hash": self.log_hash,
            "config_hash": self.config_hash,
            "dbc_hash": self.dbc_hash,
            "model_hash": self.model_hash,
            "cmcan_version": self.cmcan_version,
        }


def check_machine(machine: str, where: str) -> str:
    if not MACHINE_RE.match(machine):
        raise CmcanError(
            f"{where}: machine id {machine!r} is not usable as a partition name "
            "(letters, digits, '.', '_', '-'; at most 100, starting with a letter or digit)",
            Kind.DATA,
        )
    return machine


def day_of(t_s: float) -> str:
    return str(np.datetime64(int(t_s // 86400), "D"))


def days_of(t_s: np.ndarray) -> np.ndarray:
    return (np.floor(t_s / 86400.0).astype("int64")).astype("datetime64[D]").astype(str)


def partition(root: Path, table: str, machine: str, day: str | None = None) -> Path:
    p = root / table / f"machine={machine}"
    return p / f"day={day}" if day is not None else p


# -- the data set as a whole ------------------------------------------------------------------------


def open_dataset(root: Path, create: bool) -> Path:
    """Check (or create) a data set folder; refuses a folder that holds something else."""
    root = Path(root)
    marker = root / "_dataset.json"
    if marker.exists():
        try:
            meta = json.loads(marker.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise CmcanError(f"{marker}: not readable as JSON: {exc}", Kind.DATA) from None
        if meta.get("format") != FORMAT:
            raise CmcanError(f"{marker}: format {meta.get('format')!r}, expected {FORMAT!r}", Kind.DATA)
        return root
    if not create:
        raise CmcanError(f"{root}: not a cmcan fleet data set (no _dataset.json)", Kind.NO_INPUT)
    if root.exists() and any(root.iterdir()):
        raise CmcanError(f"{root}: folder exists, is not empty and is not a cmcan fleet data set", Kind.CANT_CREATE)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CmcanError(f"{root}: cannot create the data set folder: {exc}", Kind.CANT_CREATE) from None
    _atomic_text(marker, json.dumps({"format": FORMAT, "created_by": f"cmcan {__version__}"}, indent=2) + "\n")
    return root


@contextlib.contextmanager
def writer_lock(root: Path) -> Iterator[None]:
    """One ``fleet replay`` writes a data set at a time."""
    with open(root / "_lock", "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise CmcanError(f"{root}: another cmcan fleet replay is writing this data set", Kind.TEMPFAIL) from None
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _keys(root: Path, table: str) -> dict[tuple[str, str], list[Path]]:
    """(machine, key) -> files of a table."""
    out: dict[tuple[str, str], list[Path]] = {}
    base = root / table
    if not base.is_dir():
        return out
    for mdir in base.iterdir():
        if not mdir.name.startswith("machine="):
            continue
        machine = mdir.name[len("machine=") :]
        for f in mdir.rglob("*.parquet"):
            out.setdefault((machine, f.stem), []).append(f)
    return out


def committed(root: Path) -> set[tuple[str, str]]:
    """(machine, key) of every log whose summary is in the data set."""
    return set(_keys(root, SUMMARY_TABLE))


def remove_orphans(root: Path) -> int:
    """Delete the staging area, temporaries of interrupted writes and data files of logs without a
    summary (an interrupted commit)."""
    shutil.rmtree(root / STAGING, ignore_errors=True)
    n = 0
    for table in TABLES:
        for tmp in (root / table).rglob(".*.tmp"):
            tmp.unlink(missing_ok=True)
            n += 1
    done = committed(root)
    for table in DATA_TABLES:
        for mk, files in _keys(root, table).items():
            if mk not in done:
                for f in files:
                    f.unlink(missing_ok=True)
                    n += 1
    return n


def is_committed(root: Path, machine: str, key: str) -> bool:
    return any(partition(root, SUMMARY_TABLE, machine).glob(f"day=*/{key}.parquet"))


def is_quarantined(root: Path, machine: str, key: str) -> bool:
    return (partition(root, "quarantine", machine) / f"{key}.parquet").exists()


# -- writing one log ----------------------------------------------------------------------------------


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _table(columns: dict[str, Any]) -> Any:
    import pyarrow as pa

    n = max((len(v) for v in columns.values() if not isinstance(v, str)), default=1)
    arrays = {}
    for k, v in columns.items():
        if isinstance(v, str):  # a constant (provenance): dictionary-encoded on disk by Parquet anyway
            arrays[k] = pa.array([v] * n, pa.string())
        elif isinstance(v, list) and all(x is None for x in v):
            arrays[k] = pa.array(v, pa.string())
        else:
            arrays[k] = pa.array(v)
    return pa.table(arrays)


def write_parquet(path: Path, columns: dict[str, Any] | Any) -> None:
    """One Parquet file, written under a hidden temporary name and renamed."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = columns if isinstance(columns, pa.Table) else _table(columns)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    pq.write_table(table, tmp, compression="zstd")
    os.replace(tmp, path)


class LogWriter:
    """A log's rows, staged file by file, then committed at once (see the module's notes)."""

    ROW_GROUP = 65536

    def __init__(self, root: Path, machine: str, prov: Provenance) -> None:
        self.root = root
        self.machine = machine
        self.prov = prov
        self.stage = root / STAGING / f"{prov.key}.{uuid.uuid4().hex[:8]}"
        self.stage.mkdir(parents=True)
        self._writers: dict[tuple[str, str], Any] = {}
        self._buffers: dict[tuple[str, str], list[Any]] = {}
        self._buffered: dict[tuple[str, str], int] = {}

    def _staged(self, table: str, day: str) -> Path:
        return self.stage / table / f"day={day}" / f"{self.prov.key}.parquet"

    def add_rows(self, table: str, rows: dict[str, Any], time_col: str = "time_s") -> None:
        """Rows (columns of equal length, provenance added here) into their day partitions."""
        n = len(rows[time_col])
        if n == 0:
            return
        days = days_of(np.asarray(rows[time_col], dtype=np.float64))
        for day in np.unique(days).tolist():
            sel = days == day
            part = {k: np.asarray(v)[sel] for k, v in rows.items()}
            t = _table({**part, **self.prov.columns()})
            key = (table, day)
            self._buffers.setdefault(key, []).append(t)
            self._buffered[key] = self._buffered.get(key, 0) + t.num_rows
            if self._buffered[key] >= self.ROW_GROUP:
                self._flush(key)

    def _flush(self, key: tuple[str, str]) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        parts = self._buffers.pop(key, [])
        self._buffered.pop(key, None)
        if not parts:
            return
        t = pa.concat_tables(parts, promote_options="permissive")
        w = self._writers.get(key)
        if w is None:
            path = self._staged(*key)
            path.parent.mkdir(parents=True, exist_ok=True)
            w = pq.ParquetWriter(path, t.schema, compression="zstd")
            self._writers[key] = w
        w.write_table(t.cast(w.schema))

    def commit(self, summary: dict[str, Any], day: str) -> None:
        """Old results of this log out (summary first), new data files in, the new summary last."""
        for key in list(self._buffers):
            self._flush(key)
        for w in self._writers.values():
            w.close()
        self._writers.clear()
        row = {k: [v] for k, v in summary.items()}
        write_parquet(
            self.stage / SUMMARY_TABLE / f"day={day}" / f"{self.prov.key}.parquet", {**row, **self.prov.columns()}
        )
        self._remove_previous()
        staged = sorted(self.stage.rglob("*.parquet"), key=lambda p: p.parts[-3] == SUMMARY_TABLE)
        for f in staged:  # the summary sorts last
            table, dpart = f.parts[-3], f.parts[-2]
            dest = partition(self.root, table, self.machine) / dpart / f.name
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(f, dest)
        for q in partition(self.root, "quarantine", self.machine).glob(f"{self.prov.log_hash[:16]}-*.parquet"):
            q.unlink(missing_ok=True)
        shutil.rmtree(self.stage, ignore_errors=True)

    def _remove_previous(self) -> None:
        """The same log's files from an earlier replay with other inputs (its summary goes first)."""
        prefix = self.prov.log_hash[:16]
        for table in (SUMMARY_TABLE, *DATA_TABLES):
            for f in partition(self.root, table, self.machine).glob(f"day=*/{prefix}-*.parquet"):
                if f.stem != self.prov.key:
                    f.unlink(missing_ok=True)

    def abort(self) -> None:
        for w in self._writers.values():
            with contextlib.suppress(Exception):
                w.close()
        self._writers.clear()
        shutil.rmtree(self.stage, ignore_errors=True)


def write_quarantine(root: Path, machine: str, key: str, row: dict[str, Any]) -> None:
    write_parquet(partition(root, "quarantine", machine) / f"{key}.parquet", {k: [v] for k, v in row.items()})
