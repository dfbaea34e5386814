"""``cmcan fleet ingest``: the gateways' uplink, received over MQTT into the fleet data set.

A subscriber to ``<prefix>/+/event|summary|dropped|status`` with a persistent session (clean start
off, a stable client id, QoS 1) and manual acknowledgement. What arrives is sorted into a batch
(:class:`cmcan.fleet.uplinkrows.Batch`: new rows, duplicates by ``id``, quarantine rows); a batch is
committed (:func:`commit_batch`) and only then are its messages acknowledged to the broker. So a
kill -9 or a power cut before the commit leaves the messages unacknowledged (the broker delivers
them again), and one after it leaves their ids in the commit record (the copies the broker delivers
again are duplicates): nothing lost, nothing doubled.

**A batch's commit** (under the data set's commit lock, shared with ``fleet replay``): every file is
written into the batch's own staging folder (one Parquet file per table, machine and day; the
quarantine rows in one file), then the commit record, listing each file with its size and SHA-256
and the batch's ids (ranges of ``seq`` per stream), with its own ``record_sha256``; the file system
is synced (``syncfs``: one flush for the whole batch, not an fsync per file); then the files are
renamed into place and synced, the record last and synced. A batch is in the data set
exactly when its record is; a file of an uplink table no record lists is a commit that was cut
short and is removed when the ingest starts (one ingest per data set: ``_ingest.lock``).

Paths come from checked names only (the machine id a safe partition name, the day from a time
between 1970 and 9999, the file name the batch's key), so nothing a gateway sends can name a path
outside the data set.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import random
import shutil
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cmcan.errors import CmcanError, Kind
from cmcan.fleet import dataset as ds
from cmcan.fleet.uplinkrows import (
    COLUMNS,
    INGEST_KINDS,
    UPLINK_COMMITS,
    UPLINK_QUARANTINE,
    UPLINK_TABLES,
    Batch,
    Refusal,
    Seen,
    ids_record,
    parse,
)
from cmcan.service.ratelog import RateLimitedLog
from cmcan.service.sdnotify import Notifier
from cmcan.uplink.config import MqttSettings

log = logging.getLogger("cmcan.ingest")
QOS = 1
INGEST_LOCK = "_ingest.lock"
SESSION_EXPIRY_S = 7 * 86400  # MQTT 5: how long the broker keeps the session (and queues) while we are away
STATUS_EVERY_S = 10.0
IDLE_FLUSH_S = 0.1  # nothing arrived for this long: the broker's window is full or the stream paused


# -- the data set's side ----------------------------------------------------------------------------


def _arrow(table: str, rows: list[dict[str, Any]]) -> Any:
    import pyarrow as pa

    cols = COLUMNS[table]
    schema = pa.schema([pa.field(k, pa.type_for_alias(t)) for k, t in cols.items()])
    return pa.Table.from_pylist([{k: r.get(k) for k in cols} for r in rows], schema=schema)


def _listed(path: Path, table: str, machine: str | None, day: str | None) -> dict[str, Any]:
    return {
        "table": table,
        "machine": machine,
        "day": day,
        "name": path.name,
        "bytes": path.stat().st_size,
        "sha256": ds.sha256_file(path),
    }


def place_of(root: Path, f: dict[str, Any]) -> Path:
    """Where a file a commit record lists lies in the data set."""
    if f["machine"] is None:
        return root / f["table"] / f["name"]
    return ds.partition(root, f["table"], f["machine"], f["day"]) / f["name"]


def batch_key(now_ns: int) -> str:
    """Sortable by commit time, unique."""
    return f"{now_ns:020d}-{uuid.uuid4().hex[:8]}"


def commit_batch(root: Path, batch: Batch, key: str, now_s: float) -> dict[str, Any] | None:
    """The batch's rows and quarantine rows, and its commit record, into the data set (see the
    module's notes); returns the record (None when the batch had nothing new to write)."""
    if not batch.rows and not batch.quarantine:
        return None
    stage = root / ds.STAGING / f"ingest-{key}"
    with ds.writing("create a staging folder", stage):
        lock = ds.hold_stage(stage)
        stage.mkdir()
    try:
        with ds.writing("write a batch", stage):
            return _commit(root, batch, key, now_s, stage)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        stage.with_name(stage.name + ".lock").unlink(missing_ok=True)
        os.close(lock)


def _commit(root: Path, batch: Batch, key: str, now_s: float, stage: Path) -> dict[str, Any]:
    """Staged and listed in the record, synced; then moved into place, the record last, each step synced."""
    files, staged = [], []  # staged flat (numbered), so no folder per machine is made and removed
    parts = [(t, m, d, rows) for (t, m, d), rows in sorted(batch.rows.items())]
    if batch.quarantine:
        parts.append((UPLINK_QUARANTINE, None, None, batch.quarantine))
    for n, (table, machine, day, rows) in enumerate(parts):
        p = stage / f"{n}.parquet"
        ds.write_parquet(p, _arrow(table, rows))
        files.append({**_listed(p, table, machine, day), "name": f"{key}.parquet"})
        staged.append(p)
    day = ds.day_of(now_s)
    record = {
        "batch": key,
        "committed_s": now_s,
        "messages": len(batch),
        "rows": sum(len(r) for r in batch.rows.values()),
        "quarantined": len(batch.quarantine),
        "duplicates": batch.duplicates,
        ds.FILES: json.dumps(files),
        "ids": json.dumps(ids_record(batch.dedups)),
    }
    staged_record = stage / "record.parquet"
    ds.write_record(staged_record, record)
    ds.sync_filesystem(stage)  # every staged file on the disk
    with ds.writing("commit a batch", root / UPLINK_COMMITS), ds.commit_lock(root):
        for p, f in zip(staged, files, strict=True):  # the data files first, on the disk before the record
            _move(p, place_of(root, f))
        ds.sync_filesystem(root)
        _move(staged_record, root / UPLINK_COMMITS / f"day={day}" / f"{key}.parquet")
        ds.sync_filesystem(root)  # the record in place: the batch is committed
    return record


def _move(src: Path, dest: Path) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    os.replace(src, dest)


def committed_files(root: Path, verify: bool = False) -> tuple[dict[str, list[tuple[str | None, Path]]], list[str]]:
    """The files of each uplink table (and its quarantine) that the commit records list, with their
    machine (None for the quarantine), and what is wrong with them: a damaged record, a listed file
    missing or of another size, and (``verify``) of other content than its SHA-256 says."""
    out: dict[str, list[tuple[str | None, Path]]] = {t: [] for t in (*UPLINK_TABLES, UPLINK_QUARANTINE)}
    problems: list[str] = []
    for p in commit_records(root):
        try:
            files = json.loads(ds.read_record(p)[ds.FILES])
        except ds.Damaged as exc:
            problems += exc.problems
            continue
        for f in files:
            path = place_of(root, f)
            out[f["table"]].append((f["machine"], path))
            problem = ds.file_problem(path, f, verify)
            if problem:
                problems.append(problem)
    return out, problems


def commit_records(root: Path) -> list[Path]:
    base = root / UPLINK_COMMITS
    return sorted(p for p in base.glob("day=*/*.parquet") if not p.name.startswith(".")) if base.is_dir() else []


def load_seen(root: Path) -> tuple[Seen, int]:
    """The ids of every committed batch, and the number of batches; a damaged commit record is named
    (:class:`cmcan.fleet.dataset.Damaged`): which ids it held is unknown."""
    seen = Seen()
    n = 0
    for p in commit_records(root):
        row = ds.read_record(p)
        try:
            seen.merge(json.loads(row["ids"]))
        except (KeyError, TypeError, ValueError):
            raise ds.Damaged([f"{p}: its ids are not readable"]) from None
        n += 1
    return seen, n


def remove_uplink_orphans(root: Path) -> int:
    """Files of the uplink tables that no commit record lists (a commit cut short), and temporaries."""
    listed: set[Path] = set()
    for p in commit_records(root):
        listed |= {place_of(root, f) for f in json.loads(ds.read_record(p)[ds.FILES])}
    n = 0
    for table in (*UPLINK_TABLES, UPLINK_QUARANTINE, UPLINK_COMMITS):
        base = root / table
        if not base.is_dir():
            continue
        for f in base.rglob("*"):
            is_tmp = f.name.startswith(".") and f.name.endswith(".tmp")
            if f.is_file() and (is_tmp or (table != UPLINK_COMMITS and f.suffix == ".parquet" and f not in listed)):
                f.unlink(missing_ok=True)
                n += 1
    return n


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
    connects: int = 0
    connections_lost: int = 0

    def text(self) -> str:
        return ", ".join(f"{k} {v}" for k, v in self.__dict__.items())


def subscriptions(prefix: str) -> list[tuple[str, int]]:
    return [(f"{prefix}/+/{kind}", QOS) for kind in INGEST_KINDS]


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
        commit_batch(self.root, b, batch_key(time.time_ns()), self.wall())
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
            if self.client is not None:
                with contextlib.suppress(Exception):
                    self.client.disconnect()
                    self.client.loop(timeout=0.1)
