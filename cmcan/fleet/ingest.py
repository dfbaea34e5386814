"""``cmcan fleet ingest``: the gateways' uplink, received over MQTT into the fleet data set.

A subscriber to ``<prefix>/+/event|summary|dropped|status`` with a persistent session (clean start
off, a stable client id, QoS 1) and manual acknowledgement. What arrives is sorted into a batch
(:class:`cmcan.fleet.uplinkrows.Batch`: new rows, duplicates by ``id``, quarantine rows); a batch is
committed (:func:`cmcan.fleet.uplinkstore.commit_batch`: one file per table, fsync'd, with its
commit record) and only then are its messages acknowledged to the broker. So a kill -9 or a power
cut before the commit leaves the messages unacknowledged (the broker delivers them again), and one
after it leaves their ids in the commit record (the copies the broker delivers again are
duplicates): nothing lost, nothing doubled.

Folds (:func:`cmcan.fleet.uplinkstore.fold`: the batches' rows into the machine/day partitions once
their day closes, and merged meanwhile) run in a thread beside the loop, one at a time, so the
messages keep coming while a day is folded; the flat files a fold replaced are removed
:data:`cmcan.fleet.uplinkstore.READER_GRACE_S` after it. One ingest per data set (``_ingest.lock``).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import random
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cmcan.errors import CmcanError, Kind
from cmcan.fleet import dataset as ds
from cmcan.fleet import uplinkstore as store
from cmcan.fleet.uplinkrows import INGEST_KINDS, Batch, Refusal, Seen, parse
from cmcan.service.ratelog import RateLimitedLog
from cmcan.service.sdnotify import Notifier
from cmcan.uplink.config import MqttSettings

log = logging.getLogger("cmcan.ingest")
QOS = 1
INGEST_LOCK = "_ingest.lock"
SESSION_EXPIRY_S = 7 * 86400  # MQTT 5: how long the broker keeps the session (and queues) while we are away
STATUS_EVERY_S = 10.0
IDLE_FLUSH_S = 0.1  # nothing arrived for this long: the broker's window is full or the stream paused
FOLD_EVERY = 20  # records of one level folded into one (see uplinkstore.fold_due)


# -- the data set's lock ----------------------------------------------------------------------------


@contextlib.contextmanager
def ingest_lock(root: Path) -> Iterator[None]:
    """One ingest per data set (the kernel drops the lock however the holder ends)."""
    path = root / INGEST_LOCK
    with ds.writing("open the ingest lock", path):
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise CmcanError(f"{path}: another cmcan fleet ingest writes this data set", Kind.TEMPFAIL) from None
        yield
    finally:
        os.close(fd)


# -- the subscriber ------------------------------------------------------------------------------------


@dataclass
class IngestStats:
    received: int = 0
    new: int = 0
    duplicate: int = 0
    quarantined: int = 0
    batches: int = 0
    folds: int = 0
    connects: int = 0
    connections_lost: int = 0

    def text(self) -> str:
        return ", ".join(f"{k} {v}" for k, v in self.__dict__.items())


def subscriptions(prefix: str) -> list[tuple[str, int]]:
    return [(f"{prefix}/+/{kind}", QOS) for kind in INGEST_KINDS]


class Folder:
    """The folds of the data set's uplink rows, one at a time in a thread (:mod:`cmcan.fleet.uplinkstore`):
    which records are not folded yet (those the ingest commits are added), which folds' sources
    wait for their grace to pass before their flat files go. A fold that failed raises its error in
    the loop's thread (:meth:`poll`)."""

    def __init__(self, root: Path, records: list[store.Record], every: int, wall: Callable[[], float]) -> None:
        self.root = root
        self.every = every
        self.wall = wall
        self.unfolded = store.unfolded(records)
        by_key = {r.key: r for r in records}
        # folds whose sources' flat files are still there (prepare removed those past their grace)
        self.pending = [(r, by_key) for r in records if any(by_key.get(k) and by_key[k].flat_files() for k in r.folds)]
        # One worker thread for the life of the ingest, woken for each fold: a thread per fold took
        # a fresh allocator arena (glibc's, pyarrow's) for each, and the resident memory rose in
        # steps over the hours with the number of arenas, not with the data.
        self.thread: threading.Thread | None = None
        self.job: tuple[list[store.Record], float] | None = None
        self.wake = threading.Condition()
        self.busy = False  # a fold given to the worker and not yet taken in by poll
        self.finished = threading.Event()
        self.done: store.Record | None = None
        self.sources: list[store.Record] = []
        self.error: BaseException | None = None
        self.stop_event = threading.Event()
        self.folds = 0

    def committed(self, record: store.Record) -> None:
        self.unfolded.append(record)

    def poll(self) -> None:
        """A finished fold taken in; the next one started when due; sources past their grace dropped."""
        if self.busy:
            if not self.finished.is_set():
                return
            self.busy = False
            self.finished.clear()
            if self.error is not None:
                err, self.error = self.error, None
                raise err
            if self.done is not None:
                folded = set(self.done.folds)
                self.unfolded = [r for r in self.unfolded if r.key not in folded]
                if self.done.flat_files():
                    self.unfolded.append(self.done)
                self.pending.append((self.done, {r.key: r for r in self.sources}))
                self.folds += 1
                self.done = None
        now = self.wall()
        while self.pending and self.pending[0][0].committed_s <= now - store.READER_GRACE_S:
            rec, by_key = self.pending.pop(0)
            for k in rec.folds:
                store.drop(self.root, by_key, k)
        sources = store.fold_due(self.unfolded, now, self.every)
        if sources:
            self.sources = sources
            if self.thread is None:
                self.thread = threading.Thread(target=self._work, name="fold", daemon=True)
                self.thread.start()
            with self.wake:
                self.busy = True
                self.job = (sources, now)
                self.wake.notify()

    def _work(self) -> None:
        """The worker: each fold given to it, until the ingest stops."""
        while True:
            with self.wake:
                while self.job is None and not self.stop_event.is_set():
                    self.wake.wait()
                if self.job is None:
                    return
                (sources, now_s), self.job = self.job, None
            try:
                self.done = store.fold(self.root, sources, store.key_of(time.time_ns()), now_s, self.stop_event)
            except store.Stopped:
                self.done = None
            except BaseException as exc:  # raised in the loop's thread (poll)
                self.error = exc
            self.finished.set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Until the fold given to the worker has finished (True; :meth:`poll` takes it in), or
        ``timeout_s`` has passed (False)."""
        return not self.busy or self.finished.wait(timeout_s)

    def stop(self) -> None:
        """A fold in progress given up (nothing of it committed), or let finish if it is committing;
        the worker ends."""
        with self.wake:
            self.stop_event.set()
            self.wake.notify()
        if self.thread is not None:
            self.thread.join()
            self.thread = None


class Ingest:
    """The subscriber's loop in one thread (``client.loop``): receive into the batch, commit it when
    it is full (``max_batch``, at most the broker's window of unacknowledged messages), its oldest
    message waited ``batch_wait_s`` or nothing arrived for :data:`IDLE_FLUSH_S` (the broker's window
    is full, as MQTT 3.1.1 brokers keep it small, or the stream paused), then acknowledge. A lost
    connection commits what arrived (its acknowledgements go with the connection: the broker delivers
    those messages again) and connects again with back-off."""

    def __init__(
        self,
        root: Path,
        m: MqttSettings,
        seen: Seen,
        *,
        records: list[store.Record] | None = None,
        fold_every: int = FOLD_EVERY,
        password: str | None = None,
        tls: Any = None,
        notifier: Notifier | None = None,
        batch_wait_s: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.root = root
        self.m = m
        self.seen = seen
        self.password = password
        self.tls = tls
        self.notifier = notifier or Notifier(env={})
        self.max_batch = m.max_inflight
        self.batch_wait_s = batch_wait_s
        self.clock = clock
        self.wall = wall
        self.stats = IngestStats()
        self.folder = Folder(root, records or [], fold_every, wall)
        self.ratelog = RateLimitedLog(clock=clock, logger=log)
        self.batch = Batch()
        self.batch_started = self.last_message = 0.0
        self.client: Any = None
        self.connected = False
        self.lost = False  # the connection ended (on_disconnect)
        self.connect_started = 0.0
        self.failures = 0
        self.next_attempt = 0.0
        self.stopping = False
        self.next_status = self.next_watchdog = clock()

    # -- the client ----------------------------------------------------------------------------------

    def _client(self) -> Any:
        import paho.mqtt.client as mqtt
        from paho.mqtt.enums import CallbackAPIVersion

        v5 = self.m.protocol == "5"
        kw: dict[str, Any] = {} if v5 else {"clean_session": False}
        c = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=self.m.client_id,
            protocol=mqtt.MQTTv5 if v5 else mqtt.MQTTv311,
            reconnect_on_failure=False,
            manual_ack=True,
            **kw,
        )
        c.connect_timeout = self.m.connect_timeout_s
        if self.m.username is not None:
            c.username_pw_set(self.m.username, self.password)
        if self.tls is not None:
            c.tls_set_context(self.tls)
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        c.on_message = self._on_message
        c.on_subscribe = self._on_subscribe
        return c

    def _connect(self) -> None:
        from paho.mqtt.packettypes import PacketTypes
        from paho.mqtt.properties import Properties

        from cmcan.uplink.setup import describe_connect_error

        self.client = self._client()
        kw: dict[str, Any] = {}
        if self.m.protocol == "5":
            props = Properties(PacketTypes.CONNECT)
            props.SessionExpiryInterval = SESSION_EXPIRY_S
            props.ReceiveMaximum = self.max_batch  # the broker's window: at most one batch unacknowledged
            kw = {"clean_start": False, "properties": props}
        try:
            self.client.connect(self.m.host, self.m.port, self.m.keepalive_s, **kw)
        except Exception as exc:  # any failure to connect is retried with back-off
            self._failed(describe_connect_error(exc, self.m))

    def _failed(self, why: str) -> None:
        self.client = None
        self.connected = self.lost = False
        self.failures += 1
        cap = min(self.m.reconnect_max_s, self.m.reconnect_min_s * 2 ** min(self.failures - 1, 30))
        self.next_attempt = self.clock() + random.uniform(0, cap)
        self.ratelog(logging.WARNING, "connect", "broker: %s; trying again", why)

    def _on_connect(self, client: Any, _ud: Any, flags: Any, reason: Any, _props: Any) -> None:
        if client is not self.client:
            return
        if getattr(reason, "is_failure", False):
            self._failed(f"the broker refused the connection: {reason}")
            return
        self.connected = True
        self.failures = 0
        self.stats.connects += 1
        client.subscribe(subscriptions(self.m.topic_prefix))  # also when the session is there: harmless
        present = getattr(flags, "session_present", False)
        log.info("connected to %s:%d (session %s)", self.m.host, self.m.port, "resumed" if present else "new")

    def _on_subscribe(self, client: Any, _ud: Any, _mid: int, reasons: Any, _props: Any) -> None:
        if client is not self.client:
            return
        refused = [str(r) for r in reasons if getattr(r, "is_failure", False)]
        if refused:
            log.error("the broker refused the subscription to %s/+/...: %s", self.m.topic_prefix, ", ".join(refused))
        else:
            log.info("subscribed to %s", " ".join(t for t, _q in subscriptions(self.m.topic_prefix)))

    def _on_disconnect(self, client: Any, _ud: Any, _flags: Any, reason: Any, _props: Any) -> None:
        if client is self.client and not self.lost:
            self.lost = True
            self.stats.connections_lost += 1
            log.warning("connection to the broker lost (%s)", reason)

    def _on_message(self, _client: Any, _ud: Any, msg: Any) -> None:
        now = self.wall()
        self.last_message = self.clock()
        if not len(self.batch):
            self.batch_started = self.last_message
        parsed = parse(msg.topic, msg.payload, self.m.topic_prefix, now)
        what = self.batch.add(parsed, self.seen, now, (msg.mid, msg.qos) if msg.qos > 0 else None)
        self.stats.received += 1
        if what == "quarantined" and isinstance(parsed, Refusal):
            self.ratelog(logging.WARNING, "quarantine", "quarantined a message on %s: %s", parsed.topic, parsed.reason)

    # -- the loop ------------------------------------------------------------------------------------

    def flush(self) -> None:
        """Commit the batch, then acknowledge its messages (on the connection they came on)."""
        b, self.batch = self.batch, Batch()
        if not len(b):
            return
        record = store.commit_batch(self.root, b, store.key_of(time.time_ns()), self.wall())
        if record is not None:
            self.folder.committed(record)
        b.committed_into(self.seen)
        self.stats.batches += 1
        self.stats.new += sum(len(r) for r in b.rows.values())
        self.stats.duplicate += b.duplicates
        self.stats.quarantined += len(b.quarantine)
        if self.client is not None and self.connected:
            for mid, qos in b.acks:
                self.client.ack(mid, qos)

    def stop(self) -> None:
        self.stopping = True

    def step(self) -> None:
        now = self.clock()
        if self.client is None:
            if now >= self.next_attempt:
                self.connect_started = now
                self._connect()
            else:
                time.sleep(min(0.05, self.next_attempt - now))
            return
        rc = self.client.loop(timeout=0.05)
        if self.client is None:  # refused in on_connect: already on its way to the next attempt
            return
        waited = self.clock() - self.connect_started
        if rc != 0 or self.lost or (not self.connected and waited > self.m.connect_timeout_s):
            why = "no CONNACK in time" if not (rc or self.lost) else "connection lost"
            self.connected = False  # what arrived is committed; its acknowledgements go with the connection
            self.flush()
            with contextlib.suppress(Exception):
                self.client.disconnect()
            self._failed(why)
            return
        now = self.clock()
        if len(self.batch) and (
            len(self.batch) >= self.max_batch
            or now - self.batch_started >= self.batch_wait_s
            or now - self.last_message >= IDLE_FLUSH_S
        ):
            self.flush()

    def housekeeping(self) -> None:
        self.folder.poll()
        self.stats.folds = self.folder.folds
        now = self.clock()
        if self.notifier.watchdog_interval_s and now >= self.next_watchdog:
            self.notifier.watchdog()
            self.next_watchdog = now + self.notifier.watchdog_interval_s
        if now >= self.next_status:
            self.notifier.status(self.status_text())
            self.next_status = now + STATUS_EVERY_S

    def status_text(self) -> str:
        return f"{'connected' if self.connected else 'not connected'}; {self.stats.text()}"

    def run(self) -> None:
        self.notifier.ready(self.status_text())
        try:
            while not self.stopping:
                self.step()
                self.housekeeping()
            self.flush()  # what arrived is committed and acknowledged before we go
        finally:
            self.notifier.stopping()
            self.folder.stop()
            if self.client is not None:
                with contextlib.suppress(Exception):
                    self.client.disconnect()
                    self.client.loop(timeout=0.1)
