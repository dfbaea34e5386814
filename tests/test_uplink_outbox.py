"""The outbox file and the daemon's writer: durability, bounds, loss accounting, corruption, no blocking."""

from __future__ import annotations

import json
import os
import sqlite3
import stat
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from cmcan.uplink import outbox as outbox_mod
from cmcan.uplink.outbox import Clock, Outbox, OutboxError, describe, open_outbox
from cmcan.uplink.records import Entry, dumps
from cmcan.uplink.writer import BATCH_MAX, OutboxWriter

T0 = 1_700_000_000.0


def rows(box: Outbox) -> list[tuple[int, str, dict]]:
    return [(r.seq, r.kind, json.loads(r.body)) for r in box.fetch_after(0, 10**6)]


def entry(i: int, kind: str = "summary", size: int = 0) -> Entry:
    return Entry(kind, T0 + i, {"i": i, "pad": "x" * size})


def test_append_fetch_delete_and_usage(tmp_path):
    box = Outbox(tmp_path / "o.sqlite")
    assert box.con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert box.con.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL: fsync at each commit
    box.append([("event", T0, 1.0, '{"a":1}'), ("summary", T0 + 1, 2.0, '{"b":2}'), ("event", T0 + 2, 3.0, "{}")])
    assert [r.seq for r in box.fetch_after(0, 10)] == [1, 2, 3]
    assert [r.seq for r in box.fetch_after(1, 1)] == [2]
    u = box.usage()
    assert (u.entries, u.by_kind, u.oldest_created_s, u.oldest_t_s) == (3, {"event": 2, "summary": 1}, 1.0, T0)
    assert u.bytes == 7 + 7 + 2 + 3 * outbox_mod.ROW_OVERHEAD_BYTES
    box.delete([1, 2, 3])
    assert box.usage().entries == 0 and box.usage().bytes == 0
    stream = box.stream_id
    box.close()
    again = Outbox(tmp_path / "o.sqlite", durable=False)
    again.append([("event", T0, 4.0, "{}")])
    assert [r.seq for r in again.fetch_after(0, 10)] == [4]  # never reused, ids stay unique
    assert again.stream_id == stream and len(stream) == 12


def test_concurrent_creation_gives_one_outbox(tmp_path):
    path = tmp_path / "o.sqlite"

    def open_append_close(i: int) -> str:
        box = Outbox(path, durable=False)  # each its own connection, as daemon and uplink have
        box.append([("event", T0 + i, 1.0, "{}")])
        box.close()
        return box.stream_id

    with ThreadPoolExecutor(6) as ex:
        streams = set(ex.map(open_append_close, range(6)))
    assert len(streams) == 1
    assert Outbox(path).usage().entries == 6


def test_prune_by_size_drops_summaries_first_and_records_it(tmp_path):
    box = Outbox(tmp_path / "o.sqlite")
    body = dumps({"pad": "x" * 952})  # 1000 bytes with the row overhead
    box.append([("summary" if i % 4 else "event", T0 + i, 1.0, body) for i in range(40)])  # 30 summaries, 10 events
    dropped = box.prune(max_bytes=25_000, max_age_s=1e9, now_s=2.0, t_now_s=T0 + 40)
    assert [d.reason for d in dropped] == ["size"]
    d = dropped[0]
    assert d.by_kind == {"summary": 18} and d.entries == 18  # down to 90 % of the bound: 22 entries left
    left = rows(box)
    kinds = [k for _, k, _ in left]
    assert kinds.count("event") == 10 and kinds.count("summary") == 12 and kinds[-1] == "dropped"
    note = left[-1][2]
    assert note["reason"] == "size" and note["first_seq"] == 2 and note["last_seq"] == d.last_seq
    assert min(s for s, k, _ in left if k == "summary") > d.last_seq  # the oldest went first
    # Nothing but events left to drop: the oldest events go.
    dropped = box.prune(max_bytes=5_000, max_age_s=1e9, now_s=3.0, t_now_s=T0 + 41)
    assert dropped[0].by_kind == {"summary": 12, "event": 6}
    assert [k for _, k, _ in rows(box)].count("dropped") == 2  # drop notices are never dropped


class BootClock:
    """A boot clock the test moves: forward as time passes, back to near 0 when the gateway restarts."""

    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_prune_by_age_on_the_outbox_clock(tmp_path):
    boot = BootClock(100.0)
    box = Outbox(tmp_path / "o.sqlite", clock=boot)
    for i in range(10):  # one entry a second; the wall clock stamps say nothing about age
        boot.t = 100.0 + i
        box.append([("summary", T0 + i, 5.0, "{}")])
    boot.t = 155.5
    dropped = box.prune(max_bytes=10**9, max_age_s=50.0, now_s=T0 + 155.5, t_now_s=T0 + 10)
    assert [(d.reason, d.entries, d.first_seq, d.last_seq) for d in dropped] == [("age", 6, 1, 6)]
    assert [s for s, k, _ in rows(box) if k == "summary"] == [7, 8, 9, 10]
    assert box.count() == 5  # four summaries and the note


@pytest.mark.parametrize("step_s", [-86400 * 365 * 3, 86400 * 200], ids=["back-3-years", "ahead-200-days"])
def test_a_step_of_the_wall_clock_neither_drops_nor_hides_anything(tmp_path, step_s):
    """A GPS fix or NTP sets the wall clock years back or months ahead between the writes: the age
    bound and the late flag run on the outbox clock, so nothing is dropped as old and what waited is
    still late."""
    boot = BootClock(5000.0)
    wall = {"t": T0}
    w = OutboxWriter(str(tmp_path / "o.sqlite"), 10**9, max_age_s=86400 * 90, wall=lambda: wall["t"], clock=boot)
    w.start()
    for i in range(3):
        w.submit(entry(i, "event"))
    w.close()
    wall["t"] += step_s
    boot.t += 120.0  # two minutes later
    w = OutboxWriter(str(tmp_path / "o.sqlite"), 10**9, max_age_s=86400 * 90, wall=lambda: wall["t"], clock=boot)
    w.start()
    w.submit(entry(3, "event"))
    w.close()
    box = Outbox(tmp_path / "o.sqlite", clock=boot)
    assert [b["i"] for _, k, b in rows(box) if k == "event"] == [0, 1, 2, 3] and w.stats.pruned == 0
    clock = box.clock()
    got = box.fetch_after(0, 10)
    assert [r.late(clock, after_s=60.0) for r in got] == [True, True, True, False]
    assert describe(box.usage(), clock)["oldest_age_s"] == 120.0


def test_the_outbox_clock_goes_on_across_a_restart_of_the_gateway(tmp_path):
    boot = BootClock(3600.0)
    box = Outbox(tmp_path / "o.sqlite", clock=boot)
    box.append([("event", T0, T0, "{}")])
    boot.t = 3660.0
    box.append([("event", T0 + 60, T0 + 60, "{}")])
    before = box.clock()
    assert before.now_s == 60.0 and before.epoch == 1
    box.close()
    boot.t = 20.0  # the gateway restarted: its boot clock begins again
    box = Outbox(tmp_path / "o.sqlite", clock=boot)
    after = box.clock()
    assert after.epoch == 2 and after.now_s == 60.0  # goes on from where it was; the time off is not counted
    assert [r.late(after, after_s=3600.0) for r in box.fetch_after(0, 10)] == [True, True]  # waited across it
    assert box.note_restart() is True and box.note_restart() is False  # recorded once, at a start
    boot.t = 50.0
    assert box.clock() == Clock(90.0, 2)
    box.append([("event", T0 + 90, T0, "{}")])
    assert [r.late(box.clock(), 3600.0) for r in box.fetch_after(0, 10)] == [True, True, False]
    boot.t = 50.0 + 86400 * 2
    assert box.prune(10**9, 86400.0, T0, T0)[0].entries == 3  # the age bound still holds, on that clock


FORMAT_1 = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE entries (seq INTEGER PRIMARY KEY AUTOINCREMENT, kind TEXT NOT NULL, t_s REAL NOT NULL,
                      created_s REAL NOT NULL, body TEXT NOT NULL, nbytes INTEGER NOT NULL);
CREATE INDEX entries_kind_seq ON entries (kind, seq);
CREATE TABLE usage (k INTEGER PRIMARY KEY CHECK (k = 0), entries INTEGER NOT NULL, bytes INTEGER NOT NULL);
INSERT INTO usage VALUES (0, 0, 0);
CREATE TRIGGER entries_ins AFTER INSERT ON entries BEGIN
    UPDATE usage SET entries = entries + 1, bytes = bytes + NEW.nbytes WHERE k = 0;
END;
CREATE TRIGGER entries_del AFTER DELETE ON entries BEGIN
    UPDATE usage SET entries = entries - 1, bytes = bytes - OLD.nbytes WHERE k = 0;
END;
PRAGMA user_version = 1;
"""


def test_an_outbox_of_format_1_is_upgraded_in_place(tmp_path):
    """The entries a previous cmcan wrote stay, counted as queued at the upgrade and late (their
    wait cannot be measured on the new clock)."""
    path = tmp_path / "o.sqlite"
    con = sqlite3.connect(path, isolation_level=None)
    con.executescript(FORMAT_1)
    con.execute("INSERT INTO meta VALUES ('stream_id', 'abc'), ('created_s', '1.0')")
    con.execute("INSERT INTO entries (kind, t_s, created_s, body, nbytes) VALUES ('event', 1.0, 2.0, '{}', 50)")
    con.close()
    boot = BootClock(10.0)
    box = Outbox(path, clock=boot)
    assert box.con.execute("PRAGMA user_version").fetchone()[0] == outbox_mod.FORMAT_VERSION
    box.append([("event", 3.0, 4.0, "{}")])
    got = box.fetch_after(0, 10)
    assert [(r.seq, r.queued_s, r.epoch) for r in got] == [(1, 0.0, 0), (2, 0.0, 1)]
    assert [r.late(box.clock(), 60.0) for r in got] == [True, False] and box.stream_id == "abc"


def test_corrupt_outbox_is_kept_aside_never_deleted(tmp_path):
    path = tmp_path / "outbox.sqlite"
    path.write_bytes(b"this is not a database, but someone's data" * 100)
    with pytest.raises(OutboxError) as err:
        Outbox(path)
    assert err.value.kind == "corrupt" and str(path) in str(err.value)
    box = open_outbox(path, durable=True)
    assert box.kept_aside == tmp_path / "outbox.sqlite.corrupt-1"
    assert box.kept_aside.read_bytes().startswith(b"this is not a database")
    assert box.usage().entries == 0


def test_foreign_database_and_newer_format_are_refused(tmp_path):
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE mine (x)")
    con.commit()
    con.close()
    with pytest.raises(OutboxError, match="not a cmcan outbox"):
        Outbox(other)
    newer = tmp_path / "newer.sqlite"
    Outbox(newer).close()
    con = sqlite3.connect(newer)
    con.execute("PRAGMA user_version = 99")
    con.close()
    with pytest.raises(OutboxError, match="format 99") as err:
        Outbox(newer)
    assert err.value.kind == "version"


@pytest.fixture
def umask_022():
    """The usual umask of a shell or a non-systemd service manager (systemd's unit sets 0077)."""
    old = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(old)


def modes(folder) -> dict[str, int]:
    return {p.name: stat.S_IMODE(p.stat().st_mode) for p in sorted(folder.iterdir())}


def test_the_outbox_and_its_sqlite_files_are_0640_like_the_state(tmp_path, umask_022):
    """Not 0644 (SQLite's own default): the outbox holds what the state file holds."""
    box = Outbox(tmp_path / "outbox.sqlite")
    box.append([("summary", T0, T0, "{}")])
    assert modes(tmp_path) == {"outbox.sqlite": 0o640, "outbox.sqlite-shm": 0o640, "outbox.sqlite-wal": 0o640}
    box.close()
    (tmp_path / "outbox.sqlite").write_bytes(b"this is not a database" * 100)
    again = open_outbox(tmp_path / "outbox.sqlite", durable=True)  # the new one after a corrupt one too
    again.append([("summary", T0, T0, "{}")])
    assert {k: v for k, v in modes(tmp_path).items() if ".corrupt-" not in k} == {
        "outbox.sqlite": 0o640,
        "outbox.sqlite-shm": 0o640,
        "outbox.sqlite-wal": 0o640,
    }
    again.close()


def test_an_existing_outbox_keeps_its_mode(tmp_path, umask_022):
    Outbox(tmp_path / "outbox.sqlite").close()
    (tmp_path / "outbox.sqlite").chmod(0o600)
    Outbox(tmp_path / "outbox.sqlite").close()
    assert modes(tmp_path)["outbox.sqlite"] == 0o600


# -- the writer --------------------------------------------------------------------------------------


def test_writer_keeps_order_and_writes_everything_on_close(tmp_path):
    w = OutboxWriter(str(tmp_path / "o.sqlite"), 10**9, 1e9).start()
    for i in range(3000):
        assert w.submit(entry(i, "event" if i % 7 == 0 else "summary"))
    w.close()
    got = rows(Outbox(tmp_path / "o.sqlite"))
    assert [b["i"] for _, _, b in got] == list(range(3000))
    assert w.stats.written == 3000 and w.stats.commits < 3000  # batched
    assert not w.alive


def test_a_full_queue_drops_counts_and_records(tmp_path, monkeypatch):
    gate = threading.Event()
    real = Outbox.append

    def slow_append(self, r):
        gate.wait(10)
        return real(self, r)

    monkeypatch.setattr(Outbox, "append", slow_append)
    w = OutboxWriter(str(tmp_path / "o.sqlite"), 10**9, 1e9, queue_size=100).start()
    results = [w.submit(entry(i)) for i in range(1000)]
    gate.set()
    w.close()
    kept = sum(results)
    # submit did not wait for the stuck writer: only the queue's 100 and the batch the writer holds
    assert kept <= 100 + BATCH_MAX and w.stats.queue_full == 1000 - kept > 0
    got = rows(Outbox(tmp_path / "o.sqlite"))
    notes = [b for _, k, b in got if k == "dropped"]
    assert len(notes) == 1 and notes[0]["reason"] == "queue_full" and notes[0]["entries"] == 1000 - kept
    assert notes[0]["by_kind"] == {"summary": 1000 - kept}
    assert len([1 for _, k, _ in got if k == "summary"]) == kept


def test_write_failures_are_retried_counted_and_never_lose_order(tmp_path, monkeypatch, caplog):
    fails = {"n": 0}
    real = Outbox.append

    def flaky_append(self, r):
        if fails["n"] < 5:
            fails["n"] += 1
            raise sqlite3.OperationalError("disk I/O error")
        return real(self, r)

    monkeypatch.setattr(Outbox, "append", flaky_append)
    w = OutboxWriter(str(tmp_path / "o.sqlite"), 10**9, 1e9, backoff_min_s=0.001, backoff_max_s=0.01).start()
    for i in range(50):
        w.submit(entry(i))
        time.sleep(0.001)
    w.close()
    assert w.stats.write_failures == 5 and w.stats.written == 50 and w.stats.lost == 0
    assert [b["i"] for _, k, b in rows(Outbox(tmp_path / "o.sqlite"))] == list(range(50))
    logged = [r for r in caplog.records if "cannot write the outbox" in r.getMessage()]
    assert len(logged) == 1  # rate-limited: the first failure, then a summary line at most every 30 s


def test_writer_prunes_to_its_bound(tmp_path):
    w = OutboxWriter(str(tmp_path / "o.sqlite"), max_bytes=20_000, max_age_s=1e9).start()
    for i in range(200):
        w.submit(entry(i, size=400))
    w.close()
    box = Outbox(tmp_path / "o.sqlite")
    assert box.usage().bytes <= 20_000
    got = rows(box)
    notes = [b for _, k, b in got if k == "dropped"]
    assert notes and sum(n["entries"] for n in notes) == w.stats.pruned
    assert sum(1 for _, k, _ in got if k == "summary") + w.stats.pruned == 200


def test_corruption_found_while_writing_keeps_the_file_aside_and_notes_it(tmp_path, monkeypatch):
    path = tmp_path / "o.sqlite"
    real = Outbox.append
    hit = {"n": 0}

    def append(self, r):
        if any(json.loads(b).get("i") == 3 for _, _, _, b in r) and not hit["n"]:
            hit["n"] += 1  # what SQLite raises when it meets a damaged page
            raise sqlite3.DatabaseError("database disk image is malformed")
        return real(self, r)

    monkeypatch.setattr(Outbox, "append", append)
    w = OutboxWriter(str(path), 10**9, 1e9, backoff_min_s=0.01).start()
    for i in range(3):
        w.submit(entry(i))
    deadline = time.monotonic() + 10
    while w.stats.written < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    for i in range(3, 6):
        w.submit(entry(i))
    w.close()
    aside = tmp_path / "o.sqlite.corrupt-1"
    assert [b["i"] for _, _, b in rows(Outbox(aside))] == [0, 1, 2]  # kept, not deleted
    got = rows(Outbox(path))
    notes = [b for _, k, b in got if k == "dropped"]
    assert len(notes) == 1 and notes[0]["reason"] == "corrupt_outbox" and notes[0]["kept_as"] == aside.name
    assert [b["i"] for _, k, b in got if k == "summary"] == [3, 4, 5]
    assert w.stats.write_failures == 1 and w.stats.lost == 0
