"""The fleet data set on disk: tables, layout, provenance, each log's atomic commit and its check.

Layout (hive partitioning, one Parquet file per log and partition; ``docs/fleet.md`` has the columns)::

    DATASET/_dataset.json                                    format, what wrote it
    DATASET/timeline/machine=<m>/day=<YYYY-MM-DD>/<key>.parquet
    DATASET/events/machine=<m>/day=<YYYY-MM-DD>/<key>.parquet
    DATASET/logs/machine=<m>/day=<YYYY-MM-DD>/<key>.parquet  one row per log: the commit record
    DATASET/quarantine/machine=<m>/<key>.parquet             logs that failed, with the reason

``<key>`` is ``<first 16 hex of the log's SHA-256>-<12 hex of its provenance>`` (the hashes of the
configuration, DBC and model it was replayed with and of the monitor state it started from), so a
log replayed again with the same inputs maps to the same files and a changed model to new ones.

A log is written to its own folder in ``DATASET/_staging/`` first, then committed: its commit record
(the summary) is written into that folder, listing every file the log's writer wrote there, each of
them checked present first (a staged file that is gone fails the commit: nothing of the log is
committed); then the old results of the same log (another provenance, or another machine: a log
belongs to one machine) are removed summary first, the new timeline and events files are renamed
into place, and the summary last. A log is in the data set exactly when its summary file is; a
crash or Ctrl-C part-way leaves at most files without a summary, which :func:`remove_orphans`
deletes (at the start of the next run, and when a run is interrupted or fails).

**A cleanup never cuts a commit short.** A writer holds a lock on its staging folder
(``_staging/<folder>.lock``) from before the folder exists until it is gone, and a commit holds the
data set's commit lock (``_commit.lock``, shared between commits); :func:`remove_orphans` takes the
commit lock alone, so it waits for the commits in progress (and holds new ones back), and removes
only the staging folders whose writer is gone: a writer still replaying keeps its folder.

**What is committed is checked.** Every file is written with Parquet page checksums; the summary
(the commit record) lists each data file of the log with its size and SHA-256, and carries the
SHA-256 of its own values (``record_sha256``). :func:`check_committed` reads a record back and
checks every file it names (and that a log with ticks names its timeline): a damaged log is re-done
by the next ``fleet replay`` and named by ``query`` and ``report`` (:class:`Damaged`), never read
silently wrong.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import hashlib
import json
import math
import os
import re
import shutil
import time
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cmcan import __version__
from cmcan.errors import DISK_FULL, CmcanError, Kind, kind_of_oserror

FORMAT = "cmcan-fleet/2"
OLD_FORMATS = ("cmcan-fleet/1",)
TABLES = ("timeline", "events", "logs", "quarantine")
DATA_TABLES = ("timeline", "events")  # rows of a log, committed before its summary
SUMMARY_TABLE = "logs"
QUARANTINE = "quarantine"
STAGING = "_staging"
COMMIT_LOCK = "_commit.lock"
CLEANUP_WAIT_S = 60.0  # how long a cleanup waits for the commits in progress before it leaves things be
# A partition name: no '/', no '=', nothing a shell or a glob reads specially, no trailing newline
# (fullmatch: '$' would accept one).
MACHINE_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")
HASH_CHUNK = 1 << 20
RECORD_HASH = "record_sha256"
FILES = "files"


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def file_problem(path: Path, entry: Mapping[str, Any], verify: bool = True) -> str | None:
    """What is wrong with a committed file against its commit record's entry (its size, then, with
    ``verify``, its SHA-256), or None."""
    try:
        size = path.stat().st_size
    except OSError:
        return f"{path}: missing"
    if size != entry["bytes"]:
        return f"{path}: {size} bytes, its commit record says {entry['bytes']}"
    if verify and sha256_file(path) != entry["sha256"]:
        return f"{path}: content differs from its commit record (SHA-256)"
    return None


# -- errors of the data set's own files -------------------------------------------------------------


class DatasetError(CmcanError):
    """Writing or reading the data set's own files failed (not a log's fault): the run stops."""


def dataset_error(exc: OSError, doing: str, path: str | Path | None = None) -> DatasetError:
    """An OSError of the data set as a message naming the file and what the system said."""
    where = path or exc.filename or "the data set"
    name = errno.errorcode.get(exc.errno or 0, "")
    why = exc.strerror or str(exc)
    hint = {
        Kind.TEMPFAIL: " (is the disk full?)" if exc.errno in DISK_FULL else "",
        Kind.IO_ERROR: " (is the disk full?)" if exc.errno in DISK_FULL else "",
        Kind.NO_PERMISSION: " (this user may not write there)",
    }.get(kind_of_oserror(exc), "")
    return DatasetError(f"{where}: cannot {doing}: {why}{f' ({name})' if name else ''}{hint}", kind_of_oserror(exc))


@contextlib.contextmanager
def writing(doing: str, path: str | Path | None = None) -> Iterator[None]:
    """OSErrors inside become a :class:`DatasetError` (kind by errno) naming the file."""
    try:
        yield
    except DatasetError:
        raise
    except OSError as exc:
        raise dataset_error(exc, doing, path) from None


@dataclass(frozen=True)
class Provenance:
    """What a row was computed from: the log's content, the inputs it was replayed with, and the
    monitor state it started from (``state_hash``: empty for a fresh start)."""

    log_hash: str
    config_hash: str
    dbc_hash: str
    model_hash: str
    cmcan_version: str = __version__
    state_hash: str = ""
    options: str = ""  # replay options that change the results of some logs (keep_truncated)

    @property
    def inputs_hash(self) -> str:
        extra = f":{self.state_hash}:{self.options}" if self.state_hash or self.options else ""
        text = f"{self.config_hash}:{self.dbc_hash}:{self.model_hash}{extra}"
        return hashlib.sha256(text.encode()).hexdigest()[:12]

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
    if not isinstance(machine, str) or not MACHINE_RE.fullmatch(machine):
        raise CmcanError(
            f"{where}: machine id {machine!r} is not usable as a partition name "
            "(letters, digits, '.', '_', '-'; at most 100, starting with a letter or digit)",
            Kind.DATA,
        )
    return machine


def day_of(t_s: float) -> str:
    return _day(int(t_s // 86400))


@functools.lru_cache(maxsize=1024)  # the ingest asks for the same few days for every message
def _day(days: int) -> str:
    return str(np.datetime64(days, "D"))


def days_of(t_s: np.ndarray) -> np.ndarray:
    return (np.floor(t_s / 86400.0).astype("int64")).astype("datetime64[D]").astype(str)


def partition(root: Path, table: str, machine: str, day: str | None = None) -> Path:
    p = root / table / f"machine={machine}"
    return p / f"day={day}" if day is not None else p


def machines_in(root: Path, table: str) -> list[str]:
    """Machines with a partition folder in a table (valid names only)."""
    base = root / table
    if not base.is_dir():
        return []
    out = []
    for d in base.iterdir():
        name = d.name[len("machine=") :] if d.name.startswith("machine=") else ""
        if d.is_dir() and not d.is_symlink() and MACHINE_RE.fullmatch(name):
            out.append(name)
    return sorted(out)


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
        fmt = meta.get("format") if isinstance(meta, dict) else None
        if fmt in OLD_FORMATS:
            raise CmcanError(
                f"{marker}: format {fmt!r} was written by an older cmcan, without the integrity records this "
                f"version checks ({FORMAT!r}); replay the logs into a new data set",
                Kind.DATA,
            )
        if fmt != FORMAT:
            raise CmcanError(f"{marker}: format {fmt!r}, expected {FORMAT!r}", Kind.DATA)
        return root
    if not create:
        raise CmcanError(f"{root}: not a cmcan fleet data set (no _dataset.json)", Kind.NO_INPUT)
    if root.exists() and not root.is_dir():
        raise CmcanError(f"{root}: exists and is not a folder", Kind.CANT_CREATE)
    if root.exists() and any(root.iterdir()):
        raise CmcanError(f"{root}: folder exists, is not empty and is not a cmcan fleet data set", Kind.CANT_CREATE)
    with writing("create the data set folder", root):
        root.mkdir(parents=True, exist_ok=True)
        _atomic_text(marker, json.dumps({"format": FORMAT, "created_by": f"cmcan {__version__}"}, indent=2) + "\n")
    return root


@contextlib.contextmanager
def writer_lock(root: Path) -> Iterator[None]:
    """One ``fleet replay`` (or ``fleet drop``) writes a data set at a time."""
    with writing("open the data set's lock file", root / "_lock"):
        f = open(root / "_lock", "a+")  # noqa: SIM115 - held for the whole block
    with f:
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
    for machine in machines_in(root, table):
        for f in partition(root, table, machine).rglob("*.parquet"):
            if not f.name.startswith("."):
                out.setdefault((machine, f.stem), []).append(f)
    return out


def committed(root: Path) -> set[tuple[str, str]]:
    """(machine, key) of every log whose summary is in the data set."""
    return set(_keys(root, SUMMARY_TABLE))


def log_index(root: Path) -> dict[str, set[str]]:
    """The first 16 hex of each log hash with results or a quarantine row -> its machines."""
    out: dict[str, set[str]] = {}
    for table in (SUMMARY_TABLE, QUARANTINE):
        for machine, key in _keys(root, table):
            out.setdefault(key.split("-", 1)[0], set()).add(machine)
    return out


def remove_orphans(root: Path, wait_s: float = CLEANUP_WAIT_S, writers_wait_s: float = 0.0) -> int:
    """Delete the staging folders whose writer is gone, temporaries of interrupted writes and data
    files of logs without a summary (an interrupted commit), once no commit is in progress (waited
    for up to ``wait_s``; after that nothing is removed: the next run does it). A writer still alive
    keeps its folder (``writers_wait_s``: how long to wait for writers that are ending). Returns the
    files and folders removed."""
    with writing("clean the data set's staging area", root / STAGING), commit_lock(root, wait_s) as alone:
        if not alone:
            return 0
        n = _remove_stages(root / STAGING)
        deadline = time.monotonic() + writers_wait_s
        while _held_stages(root / STAGING) and time.monotonic() < deadline:
            time.sleep(0.1)
            n += _remove_stages(root / STAGING)
        with contextlib.suppress(OSError):  # the staging area itself, once empty (a writer's lock keeps it)
            (root / STAGING).rmdir()
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


@contextlib.contextmanager
def commit_lock(root: Path, wait_s: float | None = None) -> Iterator[bool]:
    """The data set's commit lock: shared by commits (``wait_s`` None: waits as long as it takes),
    alone for a cleanup (True once it has it; False when commits still hold it after ``wait_s``)."""
    fd = os.open(root / COMMIT_LOCK, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        if wait_s is None:
            fcntl.flock(fd, fcntl.LOCK_SH)
            yield True
            return
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    yield False
                    return
                time.sleep(0.05)
        yield True
    finally:
        os.close(fd)  # (the lock goes with it)


def hold_stage(stage: Path) -> int:
    """The lock on a staging folder (``<folder>.lock``, taken before the folder is made): a
    descriptor held while the writer lives. A cleanup removes a lock file only while it holds it,
    so a lock that is no longer the file at its path is taken again."""
    path = stage.with_name(stage.name + ".lock")
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)


def _remove_stages(staging: Path) -> int:
    """The staging folders (and lock files) of writers that are gone; those of live writers stay."""
    if not staging.is_dir():
        return 0
    n = 0
    for entry in sorted(staging.iterdir()):
        if entry.name.endswith(".lock"):
            continue
        lock = entry.with_name(entry.name + ".lock")
        fd = _free_lock(lock)
        if fd == -1:  # its writer is alive
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
        n += 1
        if fd is not None:
            lock.unlink(missing_ok=True)
            os.close(fd)
    for lock in staging.glob("*.lock"):  # a writer gone before it made its folder
        if not lock.with_suffix("").exists() and (fd := _free_lock(lock)) not in (None, -1):
            lock.unlink(missing_ok=True)
            os.close(fd)  # type: ignore[arg-type]
    return n


def _held_stages(staging: Path) -> bool:
    """Whether some staging folder's writer is alive."""
    held = False
    for lock in staging.glob("*.lock") if staging.is_dir() else ():
        fd = _free_lock(lock)
        if fd == -1:
            held = True
        elif fd is not None:
            os.close(fd)
    return held


def _free_lock(path: Path) -> int | None:
    """A staging lock taken if nobody holds it (its descriptor); -1 if a writer holds it; None if
    there is no such file."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return -1
    return fd


def summary_path(root: Path, machine: str, key: str) -> Path | None:
    return next(iter(sorted(partition(root, SUMMARY_TABLE, machine).glob(f"day=*/{key}.parquet"))), None)


def is_committed(root: Path, machine: str, key: str) -> bool:
    return summary_path(root, machine, key) is not None


# -- records and their check ------------------------------------------------------------------------


class Damaged(CmcanError):
    """A committed file is not what its commit record says (cut short, overwritten, missing)."""

    def __init__(self, problems: list[str]) -> None:
        shown = "; ".join(problems[:5]) + (f"; and {len(problems) - 5} more" if len(problems) > 5 else "")
        super().__init__(
            f"damaged data set files: {shown}. Run `cmcan fleet replay` with the same sources to re-do the "
            "logs they belong to",
            Kind.DATA,
        )
        self.problems = problems


def _canonical(v: Any) -> Any:
    if isinstance(v, float) and math.isnan(v):
        return "NaN"
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return _canonical(v.item())
    return v


def record_hash(row: dict[str, Any]) -> str:
    """SHA-256 of a one-row record's values (as Parquet gives them back), without the hash itself."""
    body = {k: _canonical(v) for k, v in sorted(row.items()) if k != RECORD_HASH}
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=str).encode()).hexdigest()


def read_record(path: Path) -> dict[str, Any]:
    """A one-row record (summary or quarantine row), its page checksums and its own hash checked;
    :class:`Damaged` names the file otherwise."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        t = pq.read_table(path, page_checksum_verification=True)
        rows = t.to_pylist()
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise Damaged([f"{path}: not readable ({type(exc).__name__}: {str(exc).splitlines()[0][:120]})"]) from None
    if len(rows) != 1 or RECORD_HASH not in rows[0]:
        raise Damaged([f"{path}: not a one-row record with its {RECORD_HASH}"])
    row = rows[0]
    if row[RECORD_HASH] != record_hash(row):
        raise Damaged([f"{path}: its values do not match its {RECORD_HASH}"])
    return row


def check_files(root: Path, machine: str, record: dict[str, Any], tables: Any = DATA_TABLES) -> list[str]:
    """What is wrong with the data files of ``tables`` a commit record names (empty: all there, whole)."""
    try:
        files = json.loads(record.get(FILES) or "[]")
    except ValueError:
        return [f"the commit record of {machine} {record.get('log_name')} lists its files unreadably"]
    problems = []
    ticks = record.get("ticks") or 0
    if "timeline" in tables and ticks > 0 and not any(f["table"] == "timeline" for f in files):
        # a commit whose staged files were removed under it: its record lists less than it had
        problems.append(
            f"the commit record of {machine} {record.get('log_name')} lists no timeline file for its {ticks} ticks"
        )
    for f in files:
        if f["table"] not in tables:
            continue
        problem = file_problem(partition(root, f["table"], machine, f["day"]) / f["name"], f)
        if problem:
            problems.append(problem)
    return problems


def data_files(root: Path, machine: str, record: dict[str, Any], table: str) -> list[Path]:
    files = json.loads(record.get(FILES) or "[]")
    return [partition(root, table, machine, f["day"]) / f["name"] for f in files if f["table"] == table]


def check_committed(root: Path, machine: str, key: str) -> dict[str, Any] | None:
    """The commit record of a log if it is in the data set and whole; None if it is not there;
    :class:`Damaged` if it is there and damaged."""
    path = summary_path(root, machine, key)
    if path is None:
        return None
    record = read_record(path)
    problems = check_files(root, machine, record)
    if problems:
        raise Damaged(problems)
    return record


def remove_log(root: Path, machine: str, log_hash16: str, keep_key: str | None = None) -> int:
    """A log's files in a machine's partitions (the summary first), except those of ``keep_key``."""
    n = 0
    with writing("remove old results", partition(root, SUMMARY_TABLE, machine)):
        for table in (SUMMARY_TABLE, *DATA_TABLES):
            for f in partition(root, table, machine).glob(f"day=*/{log_hash16}-*.parquet"):
                if f.stem != keep_key:
                    f.unlink(missing_ok=True)
                    n += 1
    return n


def remove_quarantine(root: Path, machine: str, keys: list[str], log_hash16: str | None) -> None:
    """Quarantine rows of a log in a machine's partition: by path key and by its content hash."""
    base = partition(root, QUARANTINE, machine)
    with writing("remove a quarantine row", base):
        for k in keys:
            (base / f"{k}.parquet").unlink(missing_ok=True)
        if log_hash16:
            for q in base.glob(f"{log_hash16}-*.parquet"):
                q.unlink(missing_ok=True)


def drop_machine(root: Path, machine: str) -> dict[str, int]:
    """Every row of a machine, summaries first (its logs leave the data set at once), then its data
    files and quarantine rows. Returns the files removed per table."""
    out = {}
    with writing(f"remove machine {machine}", root):
        for table in (SUMMARY_TABLE, *DATA_TABLES, QUARANTINE):
            d = partition(root, table, machine)
            out[table] = sum(1 for _ in d.rglob("*.parquet")) if d.is_dir() else 0
            shutil.rmtree(d, ignore_errors=True)
    return out


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
            arrays[k] = pa.array(v, pa.type_for_alias(NULLABLE_TYPES.get(k, "string")))
        else:
            arrays[k] = pa.array(v)
    return pa.table(arrays)


def _write_table(table: Any, path: Path, row_group_rows: int | None = None) -> None:
    import pyarrow.parquet as pq

    pq.write_table(table, path, compression="zstd", write_page_checksum=True, row_group_size=row_group_rows)


def parquet_writer(path: Path, schema: Any) -> Any:
    """A Parquet file written in parts, as every file of the data set is (zstd, page checksums)."""
    import pyarrow.parquet as pq

    return pq.ParquetWriter(path, schema, compression="zstd", write_page_checksum=True)


def sync_filesystem(path: Path) -> None:
    """Everything written to the file system holding ``path`` on the disk, renames included, in one
    flush (``syncfs``: one commit of the file system's journal instead of an fsync per file and
    folder); ``os.sync`` where the C library has no ``syncfs``."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    fn = getattr(libc, "syncfs", None)
    if fn is None:
        os.sync()
        return
    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    try:
        if fn(fd) != 0:  # a write-back error of the file system (Linux 5.8+ reports it here)
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err), str(path))
    finally:
        os.close(fd)


def write_parquet(path: Path, columns: dict[str, Any] | Any, row_group_rows: int | None = None) -> None:
    """One Parquet file, written under a hidden temporary name and renamed."""
    import pyarrow as pa

    table = columns if isinstance(columns, pa.Table) else _table(columns)
    with writing("write", path):
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
        try:
            _write_table(table, tmp, row_group_rows)
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


def write_record(path: Path, row: dict[str, Any]) -> None:
    """A one-row record with the hash of its own values (as they read back)."""
    t = _table({k: [v] for k, v in row.items()})
    values = t.to_pylist()[0]
    write_parquet(path, {**{k: [v] for k, v in values.items()}, RECORD_HASH: [record_hash(values)]})


# Types of the summary's columns that can be NULL in a log's row (a NULL alone has no type).
NULLABLE_TYPES = {
    "cut_line": "int64",
    "motor_disp_cc": "double",
    "carried_from": "string",
    "fit": "string",
    "fit_median_pct": "double",
    "fit_points": "int64",
}


class LogWriter:
    """A log's rows, staged file by file, then committed at once (see the module's notes). Every
    OSError of the data set becomes a :class:`DatasetError` naming the file."""

    ROW_GROUP = 65536

    def __init__(self, root: Path, machine: str, prov: Provenance) -> None:
        self.root = root
        self.machine = machine
        self.prov = prov
        self.stage = root / STAGING / f"{prov.key}.{uuid.uuid4().hex[:8]}"
        with writing("create a staging folder", self.stage):
            self._lock: int | None = hold_stage(self.stage)  # before the folder: a cleanup leaves it alone
            self.stage.mkdir()
        self._writers: dict[tuple[str, str], Any] = {}
        self._written: set[tuple[str, str]] = set()  # the (table, day) files staged: what the commit lists
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

        parts = self._buffers.pop(key, [])
        self._buffered.pop(key, None)
        if not parts:
            return
        t = pa.concat_tables(parts, promote_options="permissive")
        path = self._staged(*key)
        with writing("write", path):
            w = self._writers.get(key)
            if w is None:
                path.parent.mkdir(parents=True, exist_ok=True)
                w = parquet_writer(path, t.schema)
                self._writers[key] = w
                self._written.add(key)
            w.write_table(t.cast(w.schema))

    def commit(
        self, summary: dict[str, Any], day: str, move_from: tuple[str, ...] = (), path_keys: tuple[str, ...] = ()
    ) -> None:
        """The commit record (listing each staged file's size and hash, every one checked there first)
        into the staging folder; then, under the commit lock, old results of this log out (summary
        first; on this machine and the ``move_from`` ones), the new data files in, the new summary
        last; then the log's quarantine rows go (``path_keys``: those written before its hash was
        known)."""
        for key in list(self._buffers):
            self._flush(key)
        with writing("write", self.stage):
            for w in self._writers.values():
                w.close()
        self._writers.clear()
        files = [self._listed(*key) for key in sorted(self._written)]
        record = self.stage / SUMMARY_TABLE / f"day={day}" / f"{self.prov.key}.parquet"
        write_record(record, {**summary, FILES: json.dumps(files), **self.prov.columns()})
        hash16 = self.prov.log_hash[:16]
        with writing("commit", partition(self.root, SUMMARY_TABLE, self.machine)), commit_lock(self.root):
            for other in move_from:
                if other != self.machine:
                    remove_log(self.root, other, hash16)
            remove_log(self.root, self.machine, hash16, keep_key=self.prov.key)
            for f in [*(self._staged(x["table"], x["day"]) for x in files), record]:  # the summary last
                dest = partition(self.root, f.parts[-3], self.machine) / f.parts[-2] / f.name
                dest.parent.mkdir(parents=True, exist_ok=True)
                os.replace(f, dest)
        for m in {self.machine, *move_from}:
            remove_quarantine(self.root, m, list(path_keys), hash16)
        self._drop_stage()

    def _listed(self, table: str, day: str) -> dict[str, Any]:
        """A staged file as the commit record lists it; a file that is gone fails the commit."""
        f = self._staged(table, day)
        try:
            size = f.stat().st_size
            digest = sha256_file(f)
        except FileNotFoundError:
            raise DatasetError(
                f"{f}: a staged file of the log is gone (its staging folder was removed): nothing of the log is "
                "committed",
                Kind.TEMPFAIL,
            ) from None
        except OSError as exc:
            raise dataset_error(exc, "check a staged file", f) from None
        return {"table": table, "day": day, "name": f.name, "bytes": size, "sha256": digest}

    def _drop_stage(self) -> None:
        """The staging folder removed, then its lock."""
        shutil.rmtree(self.stage, ignore_errors=True)
        if self._lock is not None:
            self.stage.with_name(self.stage.name + ".lock").unlink(missing_ok=True)
            os.close(self._lock)
            self._lock = None

    def abort(self) -> None:
        for w in self._writers.values():
            with contextlib.suppress(Exception):
                w.close()
        self._writers.clear()
        self._drop_stage()


def write_quarantine(root: Path, machine: str, key: str, row: dict[str, Any]) -> None:
    write_record(partition(root, QUARANTINE, machine) / f"{key}.parquet", row)


def quarantine_row(root: Path, machine: str, key: str) -> dict[str, Any] | None:
    """A log's quarantine row, if it is there and whole (a damaged one is removed: the log is tried
    again)."""
    p = partition(root, QUARANTINE, machine) / f"{key}.parquet"
    if not p.exists():
        return None
    try:
        return read_record(p)
    except Damaged:
        with writing("remove a damaged quarantine row", p):
            p.unlink(missing_ok=True)
        return None
