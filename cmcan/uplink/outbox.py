"""The durable outbox: a SQLite file in the daemon's state directory, shared by daemon and uplink.

The daemon appends entries (WAL, ``synchronous=FULL``: every commit is fsync'd before it returns);
the uplink reads them in sequence order and deletes each one after the broker's PUBACK. Both sides
open the file through ``Outbox``; either may create it (the schema is made in one transaction). The
outbox is bounded by size and by age: the writer prunes summaries before warning events, oldest
first, and writes what it pruned as a ``dropped`` entry in the same transaction, so the loss itself
is published later. A file that SQLite reports as corrupt is kept aside as ``<name>.corrupt-N``,
never deleted.

Age (the bound, and whether an entry is ``late`` when it is published) is measured on the outbox's
own clock, never on the wall clock, which NTP or a GPS fix steps by hours or years: a step forward
would drop waiting warnings as old, a step back would hide that they waited. The outbox clock runs
with the gateway's boot clock (``CLOCK_BOOTTIME``: it counts suspend, never steps, and is the same for
the daemon and the uplink) and goes on across restarts: the file keeps an anchor (the clock's reading
at a boot-clock time, moved on at every write), and a boot clock below the anchor's means the gateway
restarted, so the clock goes on from the anchor's reading and its epoch counts up. The clock
therefore counts the time the gateway was up, not the time it was off; an entry written before a
restart of the gateway (an earlier epoch) is always ``late``. A restart is recognised when the new
boot clock is below the last anchor's, i.e. unless the gateway was up for less time before the
restart than after it when the outbox is next written: then the clock undercounts by at most that
short time, which only makes entries look younger (kept longer, not dropped).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import secrets
import sqlite3
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cmcan.uplink.records import DROPPED, Dropped

log = logging.getLogger("cmcan.uplink.outbox")

FORMAT_VERSION = 2  # 2: the outbox clock (entries.queued_s and epoch, the anchor in meta)
ROW_OVERHEAD_BYTES = 48  # what SQLite stores besides the body, roughly: counted against the size bound
PRUNE_TO = 0.9  # a full outbox is pruned to this share of its bound, so pruning is rare and batched
FILE_MODE = 0o640  # as the state file and its lock: the owner reads and writes, the group reads, others nothing

_SCHEMA = f"""
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE entries (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,  -- never reused, even when the table runs empty
    kind TEXT NOT NULL,                     -- event | summary | dropped
    t_s REAL NOT NULL,                      -- frame time, epoch seconds (UTC)
    created_s REAL NOT NULL,                -- wall clock at the write (information only: it steps)
    body TEXT NOT NULL,                     -- a JSON object
    nbytes INTEGER NOT NULL,
    queued_s REAL NOT NULL DEFAULT 0,       -- the outbox clock at the write: age bound and 'late'
    epoch INTEGER NOT NULL DEFAULT 0        -- the outbox clock's epoch at the write (+1 per restart)
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

# From format 1: the columns and the anchor (old entries count as queued at the upgrade, epoch 0).
_UPGRADE_1 = [
    "ALTER TABLE entries ADD COLUMN queued_s REAL NOT NULL DEFAULT 0",
    "ALTER TABLE entries ADD COLUMN epoch INTEGER NOT NULL DEFAULT 0",
    f"PRAGMA user_version = {FORMAT_VERSION}",
]

_CORRUPT_HINTS = ("malformed", "not a database", "disk image", "encrypted")
# SQLite's primary result codes (the low byte of an extended code) that say what kind of problem it is.
_SQLITE_KINDS = {5: "busy", 6: "busy", 13: "full", 10: "io", 14: "cantopen", 8: "denied", 3: "denied", 23: "denied"}
_ERRNO_KINDS = {errno.ENOSPC: "full", errno.EDQUOT: "full", errno.EACCES: "denied", errno.EPERM: "denied",
                errno.EROFS: "denied", errno.EIO: "io"}  # fmt: skip


class OutboxError(Exception):
    """The outbox cannot be used; ``str()`` names the file. ``kind``: 'corrupt' (SQLite says so, or
    not a cmcan outbox), 'version' (a newer format), 'busy' (another process holds a lock on the file
    beyond the busy timeout), 'full' (no space left, or over a quota), 'denied' (permissions, a read-only
    file system), 'io' (an I/O error), 'cantopen' (the file or its folder cannot be opened or made)."""

    def __init__(self, path: Path, kind: str, detail: str) -> None:
        super().__init__(f"{path}: {detail}")
        self.path = path
        self.kind = kind


def is_corruption(exc: BaseException) -> bool:
    return isinstance(exc, sqlite3.DatabaseError) and any(h in str(exc).lower() for h in _CORRUPT_HINTS)


def problem_kind(exc: BaseException, default: str = "io") -> str:
    """The OutboxError kind of an exception from SQLite or the operating system."""
    if is_corruption(exc):
        return "corrupt"
    code = getattr(exc, "sqlite_errorcode", None)
    if isinstance(code, int) and (code & 0xFF) in _SQLITE_KINDS:
        return _SQLITE_KINDS[code & 0xFF]
    if isinstance(exc, OSError) and exc.errno in _ERRNO_KINDS:
        return _ERRNO_KINDS[exc.errno]
    return default


def boot_clock() -> float:
    """The gateway's boot clock: seconds since boot, suspend included; NTP never steps it."""
    return time.clock_gettime(time.CLOCK_BOOTTIME)


@dataclass(frozen=True)
class Clock:
    """A reading of the outbox clock: seconds (see the module's docstring) and the epoch."""

    now_s: float
    epoch: int

    def age_s(self, queued_s: float) -> float:
        return max(0.0, self.now_s - queued_s)


@dataclass(frozen=True)
class Row:
    seq: int
    kind: str
    t_s: float
    created_s: float
    body: str
    queued_s: float = 0.0  # the outbox clock at the write
    epoch: int = 0

    def late(self, clock: Clock, after_s: float) -> bool:
        """Waited longer than ``after_s`` on the outbox clock, or across a restart of the gateway."""
        return self.epoch != clock.epoch or clock.age_s(self.queued_s) > after_s


@dataclass
class Usage:
    entries: int
    bytes: int
    oldest_created_s: float | None
    oldest_t_s: float | None
    by_kind: dict[str, int] = field(default_factory=dict)
    oldest_queued_s: float | None = None  # the outbox clock at the oldest entry's write


class Outbox:
    """One connection to the outbox file. Not thread-safe: one per thread."""

    def __init__(
        self,
        path: str | Path,
        *,
        durable: bool = True,
        busy_timeout_s: float = 5.0,
        check: bool = True,
        clock: Callable[[], float] = boot_clock,
    ):
        self.path = Path(path)
        self.durable = durable
        self.busy_timeout_s = busy_timeout_s
        self.boot_clock = clock
        self.con: sqlite3.Connection | None = None
        self.inode: int | None = None
        self.stream_id = ""
        self.kept_aside: Path | None = None  # set by open_outbox when a corrupt file was kept aside
        self._open(check)

    # -- opening -------------------------------------------------------------------------------------

    def _open(self, check: bool) -> None:
        if not self.path.parent.is_dir():
            raise OutboxError(self.path, "cantopen", f"folder {self.path.parent} does not exist")
        _create(self.path)
        try:
            con = sqlite3.connect(self.path, timeout=self.busy_timeout_s, isolation_level=None)
        except sqlite3.Error as exc:
            raise OutboxError(self.path, problem_kind(exc, "cantopen"), f"cannot open the outbox: {exc}") from None
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
            kind = problem_kind(exc)
            if kind == "io" and _no_space(self.path.parent):  # SQLite says I/O error for a full disk's -shm
                kind = "full"
            hint = {"busy": " (another process holds a lock on it)", "full": " (the file system is full)"}.get(kind, "")
            raise OutboxError(self.path, kind, f"cannot use the outbox: {exc}{hint}") from None
        self.con = con
        self.inode = _inode(self.path)

    def _ensure_schema(self, con: sqlite3.Connection) -> None:
        version = con.execute("PRAGMA user_version").fetchone()[0]
        if version == FORMAT_VERSION:
            return
        if version not in (0, 1):
            raise OutboxError(self.path, "version", f"outbox format {version}, this cmcan reads {FORMAT_VERSION}")
        con.execute("BEGIN IMMEDIATE")  # the other process may be creating it at the same moment
        try:
            version = con.execute("PRAGMA user_version").fetchone()[0]
            if version == 0:
                if con.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]:
                    raise OutboxError(self.path, "corrupt", "not a cmcan outbox (it has other tables)")
                for stmt in _statements(_SCHEMA):
                    con.execute(stmt)
                con.execute(
                    "INSERT INTO meta VALUES ('stream_id', ?), ('created_s', ?)",
                    (secrets.token_hex(6), repr(time.time())),
                )
            elif version == 1:
                for stmt in _UPGRADE_1:
                    con.execute(stmt)
            if version in (0, 1):
                self._set_anchor(con, Clock(0.0, 1), self.boot_clock())
            con.execute("COMMIT")
        except BaseException:
            con.execute("ROLLBACK")
            raise

    # -- the outbox clock ----------------------------------------------------------------------------

    def clock(self) -> Clock:
        """The outbox clock now, read without writing (see the module's docstring)."""
        return self._read_clock(self._con())[0]

    def tick(self) -> Clock:
        """Move the clock's anchor to now (a restart of the gateway is recorded): in a transaction."""
        con = self._con()
        con.execute("BEGIN IMMEDIATE")
        try:
            c = self._tick(con)
            con.execute("COMMIT")
            return c
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                con.execute("ROLLBACK")
            raise

    def note_restart(self) -> bool:
        """Record a restart of the gateway now if there was one since the anchor (a write only then):
        at a process's start, so an early restart is seen before the boot clock passes the anchor."""
        con = self._con()
        meta = dict(con.execute("SELECT key, value FROM meta WHERE key = 'clock_boot_s'").fetchall())
        try:
            restarted = self.boot_clock() < float(meta["clock_boot_s"])
        except (KeyError, ValueError):
            restarted = True
        if restarted:
            self.tick()
        return restarted

    def _read_clock(self, con: sqlite3.Connection) -> tuple[Clock, float]:
        """(the clock, the boot clock it was read at). The anchor is read first and the boot clock
        after it: an anchor the other process wrote meanwhile is never ahead of this reading."""
        meta = dict(con.execute("SELECT key, value FROM meta WHERE key LIKE 'clock_%'").fetchall())
        boot_s = self.boot_clock()
        try:
            at_s, at_boot_s, epoch = float(meta["clock_s"]), float(meta["clock_boot_s"]), int(meta["clock_epoch"])
        except (KeyError, ValueError):  # an anchor lost or mangled: the clock begins again, nothing is old
            return Clock(0.0, 1), boot_s
        if boot_s >= at_boot_s:
            return Clock(at_s + (boot_s - at_boot_s), epoch), boot_s
        return Clock(at_s, epoch + 1), boot_s  # the boot clock went back: the gateway restarted

    def _tick(self, con: sqlite3.Connection) -> Clock:
        """In a write transaction: the clock now, and the anchor moved to it."""
        c, boot_s = self._read_clock(con)
        self._set_anchor(con, c, boot_s)
        return c

    @staticmethod
    def _set_anchor(con: sqlite3.Connection, c: Clock, boot_s: float) -> None:
        con.executemany(
            "INSERT OR REPLACE INTO meta VALUES (?, ?)",
            [("clock_s", repr(c.now_s)), ("clock_boot_s", repr(boot_s)), ("clock_epoch", str(c.epoch))],
        )

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
            now = self._tick(con)
            con.executemany(
                "INSERT INTO entries (kind, t_s, created_s, body, nbytes, queued_s, epoch)"
                " VALUES (?, ?, ?, ?, ?, ?, ?)",
                [(k, t, c, b, _nbytes(b), now.now_s, now.epoch) for k, t, c, b in rows],
            )
            con.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                con.execute("ROLLBACK")
            raise
        return len(rows)

    def prune(self, max_bytes: int, max_age_s: float, now_s: float, t_now_s: float) -> list[Dropped]:
        """Enforce the bounds; each pruning is recorded as a ``dropped`` entry in the same transaction.

        Age first (entries written more than ``max_age_s`` ago on the outbox clock), then size:
        summaries before warning events, oldest first, down to ``PRUNE_TO`` of ``max_bytes``.
        ``dropped`` entries are never pruned. ``t_now_s`` (frame time) and ``now_s`` (the wall clock,
        for information) stamp the record."""
        con = self._con()
        con.execute("BEGIN IMMEDIATE")
        try:
            out: list[Dropped] = []
            clock = self._tick(con)
            old = con.execute(
                "SELECT seq, kind, t_s, nbytes FROM entries WHERE kind != ? AND queued_s < ? ORDER BY seq",
                (DROPPED, clock.now_s - max_age_s),
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
                    "INSERT INTO entries (kind, t_s, created_s, body, nbytes, queued_s, epoch)"
                    " VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (DROPPED, t_now_s, now_s, body, _nbytes(body), clock.now_s, clock.epoch),
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
            "SELECT seq, kind, t_s, created_s, body, queued_s, epoch FROM entries WHERE seq > ? ORDER BY seq LIMIT ?",
            (seq, limit),
        )
        return [Row(*r) for r in rows]

    def delete(self, seqs: Iterable[int]) -> None:
        con = self._con()
        con.execute("BEGIN IMMEDIATE")
        try:
            self._tick(con)
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
        first = con.execute("SELECT created_s, t_s, queued_s FROM entries ORDER BY seq LIMIT 1").fetchone()
        kinds = dict(con.execute("SELECT kind, count(*) FROM entries GROUP BY kind").fetchall())
        if first is None:
            return Usage(n, b, None, None, kinds)
        return Usage(n, b, first[0], first[1], kinds, first[2])

    def _con(self) -> sqlite3.Connection:
        if self.con is None:
            raise OutboxError(self.path, "io", "outbox is closed")
        return self.con


def _no_space(folder: Path) -> bool:
    """The file system holding ``folder`` has no block or no inode left for this user."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    return st.f_bavail == 0 or (st.f_files > 0 and st.f_favail == 0)


def _nbytes(body: str) -> int:
    """What an entry counts against the size bound."""
    return len(body.encode("utf-8")) + ROW_OVERHEAD_BYTES


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
        raise OutboxError(path, problem_kind(exc, "cantopen"), f"cannot create the outbox: {exc.strerror}") from None
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


def open_outbox(
    path: str | Path,
    *,
    durable: bool,
    check: bool = True,
    keep_aside: bool = True,
    clock: Callable[[], float] = boot_clock,
) -> Outbox:
    """Open (or create) the outbox; a corrupt one is kept aside and a fresh one started when
    ``keep_aside`` is set, else the OutboxError is raised."""
    try:
        return Outbox(path, durable=durable, check=check, clock=clock)
    except OutboxError as exc:
        if exc.kind != "corrupt" or not keep_aside:
            raise
        aside = set_aside(Path(path))
        log.error("%s; kept as %s, starting a new outbox", exc, aside)
        box = Outbox(path, durable=durable, check=check, clock=clock)
        box.kept_aside = aside
        return box


def record_corrupt(box: Outbox, aside: Path, t_s: float, now_s: float) -> None:
    """Note in a new outbox that the previous one was corrupt and kept aside (entries it held are not
    sent; how many is unknown), so the loss is published too."""
    d = Dropped("corrupt_outbox", kept_as=aside.name)
    box.append([(DROPPED, t_s, now_s, d.to_json())])


def describe(usage: Usage, clock: Clock | None) -> dict[str, Any]:
    """The outbox's fill level as a JSON-ready mapping (for health messages and ``--status``); the
    oldest entry's age on the outbox clock."""
    age = None if usage.oldest_queued_s is None or clock is None else round(clock.age_s(usage.oldest_queued_s), 1)
    return {
        "entries": usage.entries,
        "bytes": usage.bytes,
        "by_kind": usage.by_kind,
        "oldest_age_s": age,
        "oldest_t_s": usage.oldest_t_s,
    }
