"""The uplink: publishes the outbox to the MQTT broker with QoS 1, deleting an entry only on its PUBACK.

One paho-mqtt client per connection, driven by this loop in a single thread (``client.loop``), no
paho background thread, no paho auto-reconnect. When a connection ends, for whatever reason (broker
gone, link down, no PUBACK in time, a refusal), its client and everything it had in flight are
discarded; the next connection publishes again from the oldest entry still in the outbox. This is
the same path as a restart after a crash or SIGKILL, so there is one recovery path: entries are
published in outbox order (order per topic kept), an entry leaves the outbox only after its PUBACK,
and an entry may be published twice (with the same ``id``) only when its PUBACK was not seen.

Connections are retried with exponential back-off and full jitter. On connect a retained ``online``
status is published (the birth message); the broker publishes the retained ``offline`` last will
when the uplink vanishes without a clean disconnect. Health (backlog, counters) is published every
``health_every_s``. Under systemd: READY, WATCHDOG and STATUS.
"""

from __future__ import annotations

import logging
import random
import ssl
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from cmcan import __version__
from cmcan.service.ratelog import RateLimitedLog
from cmcan.service.sdnotify import Notifier
from cmcan.service.statefile import read_node_status
from cmcan.uplink.config import UplinkSettings
from cmcan.uplink.outbox import Outbox, OutboxError, describe, is_corruption, open_outbox, record_corrupt, set_aside
from cmcan.uplink.records import SCHEMA_VERSION, dumps, envelope, iso_utc
from cmcan.uplink.setup import SetupError, describe_connect_error

log = logging.getLogger("cmcan.uplink")
mqtt_log = logging.getLogger("cmcan.uplink.mqtt")

QOS = 1
DELETE_EVERY_S = 0.05  # acknowledged entries are deleted in batches, at most this late
IDLE_POLL_S = 0.25  # how often an idle uplink looks for new entries
STOP_WAIT_S = 2.0  # at a clean stop: how long to wait for the offline status's PUBACK


# -- the connection -------------------------------------------------------------------------------


@dataclass
class _Session:
    client: mqtt.Client
    started: float
    connected: bool = False
    connected_at: float = 0.0
    birth_sent: bool = False
    ended: str = ""  # why the connection ended ('' while it lives)
    refused_auth: bool = False
    inflight: OrderedDict[int, tuple[int, float]] = field(default_factory=OrderedDict)  # mid -> (seq, sent)
    cursor: int = 0  # the highest seq published on this connection


@dataclass
class UplinkStats:
    published: int = 0  # PUBLISH packets of outbox entries
    acked: int = 0
    republished: int = 0  # entries published again after a connection or the process ended
    late: int = 0
    connects: int = 0  # connections established (CONNACK accepted)
    connect_failures: int = 0
    connections_lost: int = 0
    ack_timeouts: int = 0
    refused: int = 0  # PUBACKs with an MQTT 5 failure reason
    outbox_errors: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class Publisher:
    def __init__(
        self,
        settings: UplinkSettings,
        outbox: Outbox,
        *,
        password: str | None = None,
        tls: ssl.SSLContext | None = None,
        notifier: Notifier | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
        rng: Callable[[], float] = random.random,
        client_factory: Callable[[], mqtt.Client] | None = None,
        sleep: Callable[[float], object] | None = None,
    ) -> None:
        self.s = settings
        self.m = settings.mqtt
        self.box = outbox
        self.password = password
        self.tls = tls
        self.notifier = notifier or Notifier(env={})
        self.clock = clock
        self.wall = wall
        self.rng = rng
        self.stats = UplinkStats()
        self.ratelog = RateLimitedLog(clock=clock, logger=log)
        self.session: _Session | None = None
        self.acked: list[int] = []
        self.highest_published = 0
        self.last_t_s = 0.0  # frame time of the newest entry published (stamps a corrupt-outbox note)
        self.failures = 0  # consecutive failed connection attempts: the back-off's exponent
        self.next_attempt = 0.0
        self.last_problem = ""
        self.started = clock()
        self.stop_event = threading.Event()
        self.sleep = sleep or self.stop_event.wait
        self.client_factory = client_factory or self._client
        self.next_watchdog = self.next_status = self.next_health = self.next_delete = self.started
        self.node_dir: Path | None = None  # the daemon's state directory: its J1939 node file goes into health

    # -- the client ----------------------------------------------------------------------------------

    def _client(self) -> mqtt.Client:
        m = self.m
        v5 = m.protocol == "5"
        kw: dict[str, Any] = {} if v5 else {"clean_session": True}
        c = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=m.client_id,
            protocol=mqtt.MQTTv5 if v5 else mqtt.MQTTv311,
            reconnect_on_failure=False,
            **kw,
        )
        c.connect_timeout = m.connect_timeout_s
        c.max_inflight_messages_set(m.max_inflight + 4)  # our window, plus status and health
        c.max_queued_messages_set(0)
        c.will_set(self.s.topic("status"), self._status_payload("offline", "connection lost"), qos=QOS, retain=True)
        if m.username is not None:
            c.username_pw_set(m.username, self.password)
        if self.tls is not None:
            c.tls_set_context(self.tls)
        # paho's own messages at debug level: what matters is logged by this loop, with a rate limit.
        c.on_log = lambda _c, _u, _level, buf: mqtt_log.debug("%s", buf)
        return c

    def _new_client(self) -> mqtt.Client:
        c = self.client_factory()
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        c.on_publish = self._on_publish
        return c

    def _on_connect(self, client: mqtt.Client, _ud: Any, _flags: Any, reason: Any, _props: Any) -> None:
        s = self.session
        if s is None or s.client is not client:
            return
        if getattr(reason, "is_failure", False):
            s.ended = f"broker refused the connection: {reason}"
            s.refused_auth = _is_auth_refusal(reason)
            return
        s.connected = True
        s.connected_at = self.clock()
        self.stats.connects += 1
        try:
            backlog = f"{self.box.count()} entries to publish"
        except Exception:  # a callback must not raise into paho
            backlog = "outbox unreadable"
        log.info("uplink connected to %s:%d; %s", self.m.host, self.m.port, backlog)

    def _on_disconnect(self, client: mqtt.Client, _ud: Any, _flags: Any, reason: Any, _props: Any) -> None:
        s = self.session
        if s is not None and s.client is client and not s.ended:
            lost = getattr(reason, "is_failure", True)
            s.ended = "connection lost" if lost else f"disconnected by the broker ({reason})"

    def _on_publish(self, client: mqtt.Client, _ud: Any, mid: int, reason: Any, _props: Any) -> None:
        s = self.session
        if s is None or s.client is not client:
            return
        item = s.inflight.pop(mid, None)
        if item is None:
            return  # status or health
        if getattr(reason, "is_failure", False):
            self.stats.refused += 1
            s.ended = f"broker refused entry {item[0]}: {reason}"
            return
        self.acked.append(item[0])
        self.stats.acked += 1

    # -- payloads ------------------------------------------------------------------------------------

    def _status_payload(self, state: str, reason: str) -> str:
        body: dict[str, Any] = {
            "schema": SCHEMA_VERSION,
            "kind": "status",
            "machine_id": self.s.machine_id,
            "state": state,
            "reason": reason,
            "client_id": self.m.client_id,
            "version": __version__,
        }
        if state == "online":
            body["uplink_time_utc"] = iso_utc(self.wall())  # the gateway's clock, not frame time
        return dumps(body)

    def health(self) -> dict[str, Any]:
        now = self.clock()
        s = self.session
        try:
            backlog: dict[str, Any] | None = describe(self.box.usage(), self.box.clock())
        except Exception as exc:  # health must not fail because the outbox does
            backlog = {"error": str(exc)}
        return {
            "schema": SCHEMA_VERSION,
            "kind": "health",
            "machine_id": self.s.machine_id,
            "uplink_time_utc": iso_utc(self.wall()),
            "uptime_s": round(now - self.started, 1),
            "connected_s": round(now - s.connected_at, 1) if s is not None and s.connected else None,
            "inflight": len(s.inflight) if s is not None else 0,
            "outbox": backlog,
            "stream_id": self.box.stream_id,
            "counters": self.stats.as_dict(),
            "version": __version__,
            # the daemon's J1939 address claim (state, address, NAME) as it last wrote it; None: no file
            "j1939_node": read_node_status(self.node_dir) if self.node_dir is not None else None,
        }

    # -- the loop ------------------------------------------------------------------------------------

    def stop(self) -> None:
        self.stop_event.set()

    def run(self, drain: bool = False, timeout_s: float | None = None) -> bool:
        """Publish until stopped (True), or with ``drain`` until the outbox is empty (True) or
        ``timeout_s`` has passed (False)."""
        deadline = None if timeout_s is None else self.clock() + timeout_s
        self.notifier.ready(self._status_text())
        log.info("uplink for %s to %s:%d (outbox %s)", self.s.machine_id, self.m.host, self.m.port, self.box.path)
        drained = False
        while not self.stop_event.is_set():
            if deadline is not None and self.clock() >= deadline:
                break
            if self.iterate(drain):
                drained = True
                break
        self._shutdown()
        return drained or deadline is None

    def iterate(self, drain: bool = False) -> bool:
        """One pass of the loop; True when ``drain`` is set and the outbox is empty and acknowledged."""
        now = self.clock()
        if self.notifier.watchdog_interval_s is not None and now >= self.next_watchdog:
            self.notifier.watchdog()
            self.next_watchdog = now + self.notifier.watchdog_interval_s
        if now >= self.next_status:
            self.notifier.status(self._status_text())
            self.next_status = now + 2.0
        self._check_outbox_file()
        s = self.session
        if s is None:
            if now < self.next_attempt:
                self.sleep(min(self.next_attempt - now, 0.5))
            else:
                self._connect()
            return False
        busy = self._step(s, now)
        if s.ended:
            self._end_session(s)
            return False
        if s.connected:
            if self.acked and now >= self.next_delete:
                self._delete_acked()
                self.next_delete = now + DELETE_EVERY_S
            if now >= self.next_health:
                self._publish_health(s)
                self.next_health = now + self.m.health_every_s
            if drain and not s.inflight and not self.acked and self._empty():
                return True
        if not busy:
            s.client.loop(timeout=IDLE_POLL_S)  # wait for network traffic (PUBACKs) or new entries
        return False

    def _step(self, s: _Session, now: float) -> bool:
        """One pass over a live connection: network I/O, then fill the window. True when more work
        is waiting right now (so the loop should not sleep)."""
        if s.ended:  # ended inside the previous loop() call
            return True
        rc = s.client.loop(timeout=0.0)
        if rc != mqtt.MQTT_ERR_SUCCESS and not s.ended:
            s.ended = f"connection lost ({mqtt.error_string(rc)})"
        if s.ended:
            return True
        if not s.connected:
            if now - s.started > self.m.connect_timeout_s:
                s.ended = f"no CONNACK within {self.m.connect_timeout_s:g} s"
            return False
        if not s.birth_sent:
            s.client.publish(self.s.topic("status"), self._status_payload("online", "connected"), qos=QOS, retain=True)
            s.birth_sent = True
        if s.inflight:
            oldest = next(iter(s.inflight.values()))[1]
            if now - oldest > self.m.ack_timeout_s:
                self.stats.ack_timeouts += 1
                s.ended = f"no PUBACK within {self.m.ack_timeout_s:g} s"
                return True
        room = self.m.max_inflight - len(s.inflight)
        if room <= 0:
            return False
        try:
            rows = self.box.fetch_after(s.cursor, room)
        except Exception as exc:
            self._outbox_failed(exc)
            return False
        try:
            clock = self.box.clock()  # ages on the outbox clock: the wall clock steps
        except Exception as exc:
            self._outbox_failed(exc)
            return False
        for r in rows:
            late = r.late(clock, self.m.late_after_s)
            payload = envelope(self.s.machine_id, self.box.stream_id, r.seq, r.kind, r.t_s, late, r.body)
            info = s.client.publish(self.s.topic(r.kind), payload, qos=QOS)
            if info.rc != mqtt.MQTT_ERR_SUCCESS:
                s.ended = f"publish failed ({mqtt.error_string(info.rc)})"
                return True
            s.inflight[info.mid] = (r.seq, now)
            s.cursor = r.seq
            self.last_t_s = r.t_s
            self.stats.published += 1
            self.stats.late += late
            if r.seq <= self.highest_published:
                self.stats.republished += 1
            else:
                self.highest_published = r.seq
        return len(rows) == room

    def _connect(self) -> None:
        m = self.m
        client = self._new_client()
        self.session = s = _Session(client, self.clock())
        try:
            client.connect(m.host, m.port, keepalive=m.keepalive_s)
        except (OSError, ValueError) as exc:  # DNS, refused, unreachable, timeout, TLS
            s.ended = describe_connect_error(exc, m)
            self._end_session(s)

    def _end_session(self, s: _Session) -> None:
        was_connected = s.connected
        _close_client(s.client, polite=s.connected and not s.ended.startswith("connection lost"))
        self.session = None
        if self.acked:
            self._delete_acked()
        if was_connected:
            self.stats.connections_lost += 1
            self.failures = 0
            level = logging.WARNING
        else:
            self.stats.connect_failures += 1
            self.failures += 1
            level = logging.ERROR if s.refused_auth else logging.WARNING
        # Jitter: a fleet that lost its broker at the same moment does not come back in lockstep.
        cap = min(self.m.reconnect_max_s, self.m.reconnect_min_s * 2 ** min(self.failures, 30))
        delay = self.m.reconnect_min_s + self.rng() * max(0.0, cap - self.m.reconnect_min_s)
        self.next_attempt = self.clock() + delay
        where = f"{self.m.host}:{self.m.port}"
        self.last_problem = s.ended if s.ended.startswith(where) else f"{where}: {s.ended}"
        self.ratelog(level, "uplink-conn", "uplink: %s; retrying in %.1f s", self.last_problem, delay)

    def _publish_health(self, s: _Session) -> None:
        s.client.publish(self.s.topic("health"), dumps(self.health()), qos=QOS)

    def _delete_acked(self) -> None:
        try:
            self.box.delete(self.acked)
            self.acked = []
        except Exception as exc:
            self._outbox_failed(exc)

    def _empty(self) -> bool:
        try:
            return not self.box.fetch_after(0, 1)
        except Exception as exc:
            self._outbox_failed(exc)
            return False

    def _check_outbox_file(self) -> None:
        if self.box.replaced():
            log.warning("%s was replaced (a corrupt outbox kept aside?); opening the new one", self.box.path)
            self._reopen_outbox()

    def _reopen_outbox(self) -> None:
        if self.session is not None:  # in-flight sequence numbers belonged to the old file
            self.session.ended = "outbox replaced"
            self._end_session(self.session)
            self.next_attempt = 0.0
        self.acked = []
        self.highest_published = 0
        self.box.close()
        try:
            self.box = open_outbox(self.box.path, durable=False, clock=self.box.boot_clock)
        except OutboxError as exc:
            self.stats.outbox_errors += 1
            self.ratelog(logging.ERROR, "uplink-outbox", "uplink: %s", exc)
            self.sleep(0.5)

    def _outbox_failed(self, exc: BaseException) -> None:
        self.stats.outbox_errors += 1
        self.ratelog(logging.ERROR, "uplink-outbox", "uplink: outbox %s: %s", self.box.path, exc)
        if is_corruption(exc):
            try:
                aside = set_aside(self.box.path)
                log.error("%s: corrupt outbox kept as %s; starting a new one", self.box.path, aside)
            except OSError as err:
                log.error("%s: cannot keep the corrupt outbox aside: %s", self.box.path, err)
                return
            self._reopen_outbox()
            try:
                record_corrupt(self.box, aside, self.last_t_s or self.wall(), self.wall())
            except Exception as err:
                log.error("%s: cannot note the corrupt outbox in the new one: %s", self.box.path, err)

    def _shutdown(self) -> None:
        self.notifier.stopping()
        s = self.session
        if s is not None and s.connected and not s.ended:
            # A clean stop: say so on the status topic (the will is only for a vanished client).
            status = self._status_payload("offline", "shutdown")
            info = s.client.publish(self.s.topic("status"), status, qos=QOS, retain=True)
            end = self.clock() + STOP_WAIT_S
            while self.clock() < end and not info.is_published() and not s.ended:
                if s.client.loop(timeout=0.05) != mqtt.MQTT_ERR_SUCCESS:
                    break
        if self.acked:
            self._delete_acked()
        if s is not None:
            _close_client(s.client, polite=s.connected and not s.ended)
        self.session = None
        log.info(
            "uplink stopped: %d published (%d again after a lost connection), %d acknowledged",
            self.stats.published,
            self.stats.republished,
            self.stats.acked,
        )

    def _status_text(self) -> str:
        s = self.session
        try:
            backlog = f"backlog {self.box.count()} entries"
        except Exception:
            backlog = "outbox unreadable"
        if s is not None and s.connected:
            conn = f"connected to {self.m.host}:{self.m.port}"
        else:
            conn = f"not connected ({self.last_problem or 'connecting'})"
        return f"{conn}; {backlog}; published {self.stats.published}, acknowledged {self.stats.acked}"

    # -- a one-off check -------------------------------------------------------------------------------

    def check_connection(self) -> str:
        """Connect once and wait for the CONNACK; raises SetupError saying what failed."""
        m = self.m
        client = self._new_client()
        self.session = s = _Session(client, self.clock())
        try:
            client.connect(m.host, m.port, keepalive=m.keepalive_s)
        except (OSError, ValueError) as exc:
            self.session = None
            kind = "config" if isinstance(exc, ssl.SSLCertVerificationError) else "unavailable"
            raise SetupError(describe_connect_error(exc, m), kind) from None
        end = self.clock() + m.connect_timeout_s
        while not s.connected and not s.ended and self.clock() < end:
            rc = client.loop(timeout=0.1)
            if rc != mqtt.MQTT_ERR_SUCCESS and not s.ended:
                s.ended = f"connection closed before the CONNACK ({mqtt.error_string(rc)})"
        self.session = None
        _close_client(client, polite=s.connected)
        if s.connected:
            return f"connected to {m.host}:{m.port} as {m.client_id}"
        if s.refused_auth:
            raise SetupError(f"{m.host}:{m.port}: {s.ended}", "config")
        if not s.ended:
            raise SetupError(f"{m.host}:{m.port}: no CONNACK within {m.connect_timeout_s:g} s", "unavailable")
        if s.ended.startswith("connection lost"):
            hint = ""
            if m.tls.enabled and m.tls.cert_file is None:
                hint = " (does it require a client certificate? see uplink.mqtt.tls.cert_file)"
            elif m.tls.enabled:
                hint = " (does it accept this client certificate?)"
            raise SetupError(
                f"{m.host}:{m.port}: the broker closed the connection before accepting it{hint}", "unavailable"
            )
        raise SetupError(f"{m.host}:{m.port}: {s.ended}", "unavailable")


def _close_client(client: mqtt.Client, polite: bool) -> None:
    """End a client for good: DISCONNECT when the connection still works (so the broker does not
    publish the will), then close its socket and its wake-up socket pair (paho keeps both open until
    garbage collection otherwise; ``reinitialise`` closes them, leaving a client with no sockets)."""
    try:
        if polite and client.socket() is not None:
            client.disconnect()  # written at once; paho closes the socket after it
            if client.socket() is not None:
                client.loop(timeout=0.0)
    except Exception as exc:  # the socket may already be gone
        log.debug("disconnect: %s", exc)
    try:
        client.reinitialise()
    except Exception as exc:
        log.debug("closing the client's sockets: %s", exc)


def _is_auth_refusal(reason: Any) -> bool:
    # MQTT 3.1.1 CONNACK 4 and 5, MQTT 5 0x86 and 0x87: bad credentials, not authorized.
    return getattr(reason, "value", None) in (4, 5, 0x86, 0x87)
