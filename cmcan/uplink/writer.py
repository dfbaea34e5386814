"""The daemon's side of the outbox: a bounded queue on the receive path, a writer thread behind it.

``submit`` never blocks and never raises: it puts the entry on a bounded in-memory queue (a full queue
drops it, counted and recorded). The writer thread takes what is queued in batches, serialises it and
commits each batch in one fsync'd transaction; a failing write is retried with a growing back-off,
counted and logged with a rate limit, never fatal. What could not be kept is written as a ``dropped``
entry once writing works again, so the loss is published too.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from cmcan.service.ratelog import RateLimitedLog
from cmcan.uplink.outbox import Outbox, OutboxError, boot_clock, is_corruption, open_outbox, set_aside
from cmcan.uplink.records import DROPPED, Dropped, Entry

log = logging.getLogger("cmcan.uplink.writer")

BATCH_MAX = 512
SHUTDOWN_ATTEMPTS = 3  # at close: a failed write is tried this often before the entries are given up
PRUNE_EVERY_S = 60.0  # age bound checked this often (the size bound after every batch, it is cheap)


@dataclass
class WriterStats:
    """Counters of the writer, read by the daemon thread (plain ints: reads need no lock)."""

    submitted: int = 0
    written: int = 0
    commits: int = 0
    write_failures: int = 0  # failed attempts (a batch is retried until it is written or stops)
    queue_full: int = 0  # entries dropped because the queue was full
    lost: int = 0  # entries given up at shutdown because the file could not take them
    pruned: int = 0  # entries dropped by the size or age bound
    reopened: int = 0

    def as_counters(self) -> dict[str, int]:
        return {
            "outbox_written": self.written,
            "outbox_write_failures": self.write_failures,
            "outbox_queue_full": self.queue_full,
            "outbox_pruned": self.pruned,
        }


@dataclass
class _Lost:
    by_reason: dict[str, Dropped] = field(default_factory=dict)

    def add(self, reason: str, e: Entry) -> None:
        d = self.by_reason.get(reason)
        if d is None:
            d = self.by_reason[reason] = Dropped(reason)
        d.add(e.kind, e.t_s)


class OutboxWriter:
    def __init__(
        self,
        path: str,
        max_bytes: int,
        max_age_s: float,
        queue_size: int = 4096,
        log_every_s: float = 30.0,
        wall: Callable[[], float] = time.time,
        backoff_min_s: float = 0.2,
        backoff_max_s: float = 10.0,
        clock: Callable[[], float] = boot_clock,
    ) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self.max_age_s = max_age_s
        self.wall = wall  # stamps created_s (information); ages run on the outbox clock
        self.clock = clock  # the outbox clock's source (the boot clock) and the prune schedule
        self.backoff_min_s = backoff_min_s
        self.backoff_max_s = backoff_max_s
        self.q: queue.Queue[Entry | None] = queue.Queue(maxsize=queue_size)
        self.stats = WriterStats()
        self._lost = _Lost()
        self._lost_lock = threading.Lock()
        self._box: Outbox | None = None
        self._stop = threading.Event()
        # Two limiters: the receive path and the writer thread each log through their own.
        self._ratelog_rx = RateLimitedLog(log_every_s, logger=log)
        self._ratelog = RateLimitedLog(log_every_s, logger=log)
        self._newest_t_s = 0.0
        self._thread = threading.Thread(target=self._run, name="cmcan-outbox", daemon=True)

    # -- the receive path ----------------------------------------------------------------------------

    def submit(self, entry: Entry) -> bool:
        """Queue an entry for the outbox; False (counted, recorded) when the queue is full."""
        try:
            self.q.put_nowait(entry)
        except queue.Full:
            self.stats.queue_full += 1
            with self._lost_lock:
                self._lost.add("queue_full", entry)
            self._ratelog_rx(logging.WARNING, "outbox-full", "outbox queue full (%d); entry dropped", self.q.maxsize)
            return False
        self.stats.submitted += 1
        return True

    # -- life cycle ----------------------------------------------------------------------------------

    def start(self) -> OutboxWriter:
        self._thread.start()
        return self

    def close(self, timeout_s: float = 3.0) -> None:
        """Write what is queued (within ``timeout_s``), then stop the thread."""
        end = time.monotonic() + timeout_s
        self._stop.set()
        with contextlib.suppress(queue.Full):
            self.q.put(None, timeout=timeout_s)  # wakes the thread; it drains the queue first
        self._thread.join(max(0.0, end - time.monotonic()))
        if self._thread.is_alive():
            log.error("outbox writer did not finish within %.1f s; %d entries not written", timeout_s, self.q.qsize())

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    # -- the writer thread ---------------------------------------------------------------------------

    def _run(self) -> None:
        pending: list[Entry] = []
        backoff = self.backoff_min_s
        next_prune = 0.0
        stopping = False
        last_tries = 0
        try:  # open at once, so the file exists and a problem is logged at start, not at the first event
            self._open()
        except (sqlite3.Error, OSError, OutboxError) as exc:
            self._failed(exc)
        while True:
            if not pending and not stopping:
                item = self.q.get()
                if item is None:
                    stopping = True
                else:
                    pending.append(item)
            while len(pending) < BATCH_MAX:  # what else is queued joins the batch
                try:
                    item = self.q.get_nowait()
                except queue.Empty:
                    break
                if item is None:
                    stopping = True
                else:
                    pending.append(item)
            if not pending and stopping:
                break
            try:
                self._write(pending)
                pending = []
                backoff = self.backoff_min_s
                now = self.clock()
                if now >= next_prune or self._over_size():
                    self._prune()
                    next_prune = now + PRUNE_EVERY_S
            except (sqlite3.Error, OSError, OutboxError) as exc:
                self._failed(exc)
                if stopping or self._stop.is_set():  # closing: a few quick attempts, then give up
                    last_tries += 1
                    if last_tries >= SHUTDOWN_ATTEMPTS:
                        n = len(pending) + self.q.qsize()
                        self.stats.lost += n
                        log.error("outbox: %d entries could not be written before shutdown: %s", n, exc)
                        break
                    time.sleep(0.05)
                    continue
                self._stop.wait(backoff)  # close() cuts the wait short
                backoff = min(backoff * 2, self.backoff_max_s)
        if self._box is not None:
            self._box.close()
            self._box = None

    def _open(self) -> Outbox:
        if self._box is not None and self._box.replaced():
            log.warning("%s was moved away (kept aside by the uplink?); opening a new outbox", self.path)
            self._box.close()
            self._box = None
        if self._box is None:
            self._box = open_outbox(self.path, durable=True, clock=self.clock)
            self._box.note_restart()  # a restart of the gateway is recorded now, not at the first entry
            self.stats.reopened += 1
            if self._box.kept_aside is not None:
                self._note_corrupt(self._box.kept_aside)
        return self._box

    def _write(self, entries: list[Entry]) -> None:
        box = self._open()
        now = self.wall()
        rows = []
        for e in entries:
            rows.append((e.kind, e.t_s, now, e.to_json()))
            if e.t_s > self._newest_t_s:
                self._newest_t_s = e.t_s
        with self._lost_lock:
            lost, self._lost = self._lost, _Lost()
        rows += [(DROPPED, self._newest_t_s, now, d.to_json()) for d in lost.by_reason.values()]
        try:
            box.append(rows)
        except BaseException:
            with self._lost_lock:  # not recorded yet: keep the tally for the next attempt
                for reason, d in lost.by_reason.items():
                    cur = self._lost.by_reason.get(reason)
                    self._lost.by_reason[reason] = d if cur is None else _merge(d, cur)
            raise
        self.stats.written += len(entries)
        self.stats.commits += 1

    def _note_corrupt(self, aside: Path) -> None:
        with self._lost_lock:  # written with the next batch, like the other losses
            self._lost.by_reason["corrupt_outbox"] = Dropped("corrupt_outbox", kept_as=aside.name)

    def _over_size(self) -> bool:
        box = self._box
        if box is None or box.con is None:
            return False
        return box.con.execute("SELECT bytes FROM usage").fetchone()[0] > self.max_bytes

    def _prune(self) -> None:
        box = self._open()
        for d in box.prune(self.max_bytes, self.max_age_s, self.wall(), self._newest_t_s):
            self.stats.pruned += d.entries
            log.warning(
                "outbox over its %s bound: %d entries (%d bytes) dropped, recorded for the uplink",
                d.reason,
                d.entries,
                d.bytes,
            )

    def _failed(self, exc: BaseException) -> None:
        self.stats.write_failures += 1
        self._ratelog(logging.ERROR, "outbox-write", "cannot write the outbox %s: %s; retrying", self.path, exc)
        box, self._box = self._box, None
        if box is not None:
            box.close()
        if is_corruption(exc) or (isinstance(exc, OutboxError) and exc.kind == "corrupt"):
            try:
                aside = set_aside(Path(self.path))
                log.error("%s: corrupt outbox kept as %s; starting a new one", self.path, aside)
                self._note_corrupt(aside)
            except OSError as err:
                self._ratelog(logging.ERROR, "outbox-aside", "cannot keep the corrupt outbox aside: %s", err)


def _merge(a: Dropped, b: Dropped) -> Dropped:
    out = Dropped(a.reason, a.entries + b.entries, a.bytes + b.bytes, dict(a.by_kind), kept_as=b.kept_as or a.kept_as)
    for k, n in b.by_kind.items():
        out.by_kind[k] = out.by_kind.get(k, 0) + n
    ts = [t for t in (a.first_t_s, b.first_t_s) if t is not None]
    out.first_t_s = min(ts) if ts else None
    ts = [t for t in (a.last_t_s, b.last_t_s) if t is not None]
    out.last_t_s = max(ts) if ts else None
    return out
