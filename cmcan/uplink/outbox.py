"""The durable outbox: a SQLite file in the daemon's state directory, shared by daemon and uplink.

The daemon appends entries (WAL, ``synchronous=FULL``: every commit is fsync'd before it returns);
the uplink reads them in sequence order and deletes each one after the broker's PUBACK. Both sides
open the file through ``Outbox``; either may create it (the schema is made in one transaction). The
outbox is bounded by size and by age: the writer prunes summaries before warning events, oldest
first, and writes what it pruned as a ``dropped`` entry in the same transaction, so the loss itself
is published later. A file that SQLite reports as corrupt is kept aside as ``<name>.corrupt-N``,
never deleted.
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import sqlite3
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cmcan.uplink.records import DROPPED, Dropped

log = logging.getLogger("cmcan.uplink.outbox")

FORMAT_VERSION = 1
ROW_OVERHEAD_BYTES = 48  # what SQLite stores besides the body, roughly: counted against the size bound
PRUNE_TO = 0.9  # a full outbox is pruned to this share of its bound, so pruning is rare and batched
# A gateway without a battery-backed clock may write entries before its clock is set (1970) and then
# jump years ahead: such entries are not "old". The size bound still holds for them.
PLAUSIBLE_WALL_S = 1_577_836_800.0  # 2020-01-01
FILE_MODE = 0o640  # as the state file and its lock: the owner reads and writes, the group reads, others nothing

_SCHEMA = f"""
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE entries (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,  -- never reused, even when the table runs empty
    kind TEXT NOT NULL,                     -- event | summary | dropped
    t_s REAL NOT NULL,                      -- frame time, epoch seconds (UTC)
    created_s REAL NOT NULL,                -- wall clock at the write: age bound and 'late'
    body TEXT NOT NULL,                     -- a JSON object
    nbytes INTEGER NOT NULL
);
CREATE INDEX entries_kind_seq ON entries (kind, seq);
CREATE TABLE usage (k INTEGER PRIMARY KEY CHECK (k = 0), entries INTEGER NOT NULL, bytes INTEGER NOT NULL);
INSERT INTO usage VALUES (0, 0, 0);
CREATE TRIGGER entries_ins AFTER INSERT ON entries BEGIN
    UPDATE usage SET entries = entries + 1, bytes = bytes + NEW.nbytes WHERE k = 0;
END;
CREATE TRIGGER entries_del AFTER DELETE ON entries BEGIN
    UPDATE usage SET entries = entries - 1, bytes = bytes - OLD.nbytes WHERE k = 0;
END;
PRAGMA user_version = {FORMAT_VERSION};
"""

_CORRUPT_HINTS = ("malformed", "not a database", "disk image", "encrypted")


class OutboxError(Exception):
    """The outbox cannot be used; ``kind`` is 'corrupt', 'version' or 'io'. ``str()`` names the file."""

    def __init__(self, path: Path, kind: str, detail: str) -> None:
        super().__init__(f"{path}: {detail}")
        self.path = path
        self.kind = kind


def is_corruption(exc: BaseException) -> bool:
    return isinstance(exc, sqlite3.DatabaseError) and any(h in str(exc).lower() for h in _CORRUPT_HINTS)


@dataclass(frozen=True)
class Row:
    seq: int
    kind: str
    t_s: float
    created_s: float
    body: str


@dataclass
class Usage:
    entries: int
    bytes: int
    oldest_created_s: float | None
    oldest_t_s: float | None
    by_kind: dict[str, int] = field(default_factory=dict)


class Outbox:
    """One connection to the outbox file. Not thread-safe: one per thread."""

    def __init__(self, path: str | Path, *, durable: bool = True, busy_timeout_s: float = 5.0, check: bool = True):
        self.path = Path(path)
        self.durable = durable
        self.busy_timeout_s = busy_timeout_s
        self.con: sqlite3.Connection | None = None
        self.inode: int | None = None
        self.stream_id = ""
        self.kept_aside: Path | None = None  # set by open_outbox when a corrupt file was kept aside
        self._open(check)

    # -- opening -------------------------------------------------------------------------------------

    def _open(self, check: bool) -> None:
        if not self.path.parent.is_dir():
            raise OutboxError(self.path, "io", f"folder {self.path.parent} does not exist")
        _create(self.path)
        try:
            con = sqlite3.connect(self.path, timeout=self.busy_timeout_s, isolation_level=None)
        except sqlite3.Error as exc:
            raise OutboxError(self.path, "io", f"cannot open the outbox: {exc}") from None
        try:
            mode = con.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise OutboxError(self.path, "io", f"cannot switch the outbox to WAL mode (got {mode})")
            # FULL: each commit is fsync'd (power cut safe); NORMAL in WAL mode may lose the last
            # commits on power loss, which for the uplink's deletes only means a duplicate later.
            con.execute(f"PRAGMA synchronous={'FULL' if self.durable else 'NORMAL'}")
            self._ensure_schema(con)
            if check:
                res = con.execute("PRAGMA quick_check").fetchone()[0]
                if res != "ok":
                    raise OutboxError(self.path, "corrupt", f"corrupt outbox ({res})")
            self.stream_id = con.execute("SELECT value FROM meta WHERE key = 'stream_id'").fetchone()[0]
        except OutboxError:
            con.close()
            raise
        except sqlite3.Error as exc:
            con.close()
            if is_corruption(exc):
                raise OutboxError(self.path, "corrupt", f"corrupt outbox ({exc})") from None
            raise OutboxError(self.path, "io", f"cannot use the outbox: {exc}") from None
        self.con = con
        self.inode = _inode(self.path)

    def _ensure_schema(self, con: sqlite3.Connection) -> None:
        version = con.execute("PRAGMA user_version").fetchone()[0]
        if version == FORMAT_VERSION:
            return
        if version != 0:
            raise OutboxError(self.path, "version", f"outbox format {version}, this cmcan reads {FORMAT_VERSION}")
        con.execute("BEGIN IMMEDIATE")  # the other process may be creating it at the same moment
        try:
            if con.execute("PRAGMA user_version").fetchone()[0] == 0:
                if con.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]:
                    raise OutboxError(self.path, "corrupt", "not a cmcan outbox (it has other tables)")
                for stmt in _statements(_SCHEMA):
                    con.execute(stmt)
                con.execute(
                    "INSERT INTO meta VALUES ('stream_id', ?), ('created_s', ?)",
                    (secrets.token_hex(6), repr(time.time())),
                )
            con.execute("COMMIT")
        except BaseException:
            con.execute("ROLLBACK")
            raise

    def replaced(self) -> bool:
        """The file was moved away or replaced since it was opened (the other side kept it aside)."""
        return _inode(self.path) != self.inode

    def close(self) -> None:
        if self.con is not None:
            with contextlib.suppress(sqlite3.Error):
                self.con.close()
            self.con = None

    # -- the writer's side ---------------------------------------------------------------------------

    def append(self, rows: Sequence[tuple[str, float, float, str]]) -> int:
        """Append (kind, t_s, created_s, body) rows in one transaction; returns the number written."""
        con = self._con()
        con.execute("BEGIN IMMEDIATE")
        try:
            con.executemany(
                "INSERT INTO entries (kind, t_s, created_s, body, nbytes) VALUES (?, ?, ?, ?, ?)",
                [(k, t, c, b, len(b.encode("utf-8")) + ROW_OVERHEAD_BYTES) for k, t, c, b in rows],
            )
            con.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                con.execute("ROLLBACK")
            raise
        return len(rows)

    def prune(self, max_bytes: int, max_age_s: float, now_s: float, t_now_s: float) -> list[Dropped]:
        """Enforce the bounds; each pruning is recorded as a ``dropped`` entry in the same transaction.

        Age first (entries written more than ``max_age_s`` ago), then size: summaries before warning
        events, oldest first, down to ``PRUNE_TO`` of ``max_bytes``. ``dropped`` entries are never
        pruned. ``t_now_s`` (frame time) stamps the record."""
        con = self._con()
        con.execute("BEGIN IMMEDIATE")
        try:
            out: list[Dropped] = []
            old = con.execute(
                "SELECT seq, kind, t_s, nbytes FROM entries WHERE kind != ? AND created_s < ? AND created_s > ?"
                " ORDER BY seq",
                (DROPPED, now_s - max_age_s, PLAUSIBLE_WALL_S),
            ).fetchall()
            if old:
                out.append(self._delete(con, "age", old))
            used = con.execute("SELECT bytes FROM usage").fetchone()[0]
            if used > max_bytes:
                target = int(max_bytes * PRUNE_TO)
                chosen: list[tuple[int, str, float, int]] = []
                for kind in ("summary", "event"):
                    for row in con.execute(
                        "SELECT seq, kind, t_s, nbytes FROM entries WHERE kind = ? ORDER BY seq", (kind,)
                    ):
                        if used <= target:
                            break
                        chosen.append(row)
                        used -= row[3]
                    if used <= target:
                        break
                if chosen:
                    out.append(self._delete(con, "size", chosen))
            for d in out:
                body = d.to_json()
                con.execute(
                    "INSERT INTO entries (kind, t_s, created_s, body, nbytes) VALUES (?, ?, ?, ?, ?)",
                    (DROPPED, t_now_s, now_s, body, len(body) + ROW_OVERHEAD_BYTES),
                )
            con.execute("COMMIT")
            return out
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                con.execute("ROLLBACK")
            raise

    @staticmethod
    def _delete(con: sqlite3.Connection, reason: str, rows: list[tuple[int, str, float, int]]) -> Dropped:
        con.executemany("DELETE FROM entries WHERE seq = ?", [(r[0],) for r in rows])
        d = Dropped(reason)
        for seq, kind, t_s, nbytes in rows:
            d.add(kind, t_s, nbytes, seq)
        return d

    # -- the uplink's side ---------------------------------------------------------------------------

    def fetch_after(self, seq: int, limit: int) -> list[Row]:
        rows = self._con().execute(
            "SELECT seq, kind, t_s, created_s, body FROM entries WHERE seq > ? ORDER BY seq LIMIT ?", (seq, limit)
        )
        return [Row(*r) for r in rows]

    def delete(self, seqs: Iterable[int]) -> None:
        con = self._con()
        con.execute("BEGIN IMMEDIATE")
        try:
            con.executemany("DELETE FROM entries WHERE seq = ?", [(s,) for s in seqs])
            con.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                con.execute("ROLLBACK")
            raise

    def count(self) -> int:
        """Entries held (cheap: a counter kept by triggers)."""
        return int(self._con().execute("SELECT entries FROM usage").fetchone()[0])

    def usage(self) -> Usage:
        con = self._con()
        n, b = con.execute("SELECT entries, bytes FROM usage").fetchone()
        first = con.execute("SELECT created_s, t_s FROM entries ORDER BY seq LIMIT 1").fetchone()
        kinds = dict(con.execute("SELECT kind, count(*) FROM entries GROUP BY kind").fetchall())
        return Usage(n, b, first[0] if first else None, first[1] if first else None, kinds)

    def _con(self) -> sqlite3.Connection:
        if self.con is None:
            raise OutboxError(self.path, "io", "outbox is closed")
        return self.con


def _statements(script: str) -> list[str]:
    """A script split into statements (triggers hold ';' inside BEGIN ... END). Not executescript():
    it would commit the transaction that keeps a concurrent creator out."""
    out, buf = [], ""
    for line in script.splitlines(keepends=True):
        buf += line
        if sqlite3.complete_statement(buf):
            out.append(buf.strip())
            buf = ""
    if buf.strip():
        out.append(buf.strip())
    return out


def _create(path: Path) -> None:
    """Create the outbox file 0640 (less under a stricter umask) like the state file, before SQLite
    would create it 0644: SQLite gives its -wal, -shm and -journal files the database file's mode.
    An empty file is an empty database to SQLite; an existing one is left as it is."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, FILE_MODE)
    except FileExistsError:
        return
    except OSError as exc:
        raise OutboxError(path, "io", f"cannot create the outbox: {exc.strerror}") from None
    os.close(fd)


def _inode(path: Path) -> int | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_ino


def set_aside(path: Path) -> Path:
    """Move a corrupt outbox (and its WAL and shared-memory files) to ``<name>.corrupt-N``."""
    n = 1
    while (aside := path.with_name(f"{path.name}.corrupt-{n}")).exists():
        n += 1
    for suffix in ("", "-wal", "-shm"):
        src = path.with_name(path.name + suffix)
        if src.exists():
            os.replace(src, aside.with_name(aside.name + suffix))
    return aside


def open_outbox(path: str | Path, *, durable: bool, check: bool = True, keep_aside: bool = True) -> Outbox:
    """Open (or create) the outbox; a corrupt one is kept aside and a fresh one started when
    ``keep_aside`` is set, else the OutboxError is raised."""
    try:
        return Outbox(path, durable=durable, check=check)
    except OutboxError as exc:
        if exc.kind != "corrupt" or not keep_aside:
            raise
        aside = set_aside(Path(path))
        log.error("%s; kept as %s, starting a new outbox", exc, aside)
        box = Outbox(path, durable=durable, check=check)
        box.kept_aside = aside
        return box


def record_corrupt(box: Outbox, aside: Path, t_s: float, now_s: float) -> None:
    """Note in a new outbox that the previous one was corrupt and kept aside (entries it held are not
    sent; how many is unknown), so the loss is published too."""
    d = Dropped("corrupt_outbox", kept_as=aside.name)
    box.append([(DROPPED, t_s, now_s, d.to_json())])


def describe(usage: Usage, now_s: float) -> dict[str, Any]:
    """The outbox's fill level as a JSON-ready mapping (for health messages and ``--status``)."""
    return {
        "entries": usage.entries,
        "bytes": usage.bytes,
        "by_kind": usage.by_kind,
        "oldest_age_s": round(now_s - usage.oldest_created_s, 1) if usage.oldest_created_s is not None else None,
        "oldest_t_s": usage.oldest_t_s,
    }
