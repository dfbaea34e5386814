"""The publisher's delivery rules, checked on a model broker under random interleavings: an entry
leaves the outbox only after its PUBACK; order kept per topic; a duplicate only with the same id;
everything arrives once the broker is back. The model stands in for paho's client at its API."""

from __future__ import annotations

import itertools
import json
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import hypothesis.strategies as st
import paho.mqtt.client as mqtt
from hypothesis import HealthCheck, settings
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule, run_state_machine_as_test
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.reasoncodes import ReasonCode

from cmcan.uplink.config import UplinkSettings
from cmcan.uplink.outbox import Outbox
from cmcan.uplink.publisher import Publisher
from cmcan.uplink.records import dumps

REACHED: Counter[str] = Counter()
RUNS = itertools.count()  # which interesting cases the random runs reached


class Info:
    def __init__(self, rc: int, mid: int) -> None:
        self.rc, self.mid = rc, mid

    def is_published(self) -> bool:
        return True


class ModelBroker:
    def __init__(self) -> None:
        self.up = True
        self.received: list[tuple[str, dict[str, Any]]] = []
        self.acked: set[int] = set()  # data entries whose PUBACK reached the publisher
        self.client: FakeClient | None = None


class FakeClient:
    """paho's Client as the publisher uses it; the broker's answers come when the test says so."""

    def __init__(self, broker: ModelBroker) -> None:
        self.broker = broker
        self.sock: bool | None = None
        self.connack_due = False
        self.outstanding: list[tuple[int, int | None]] = []  # (mid, seq) awaiting PUBACK
        self.acks_released = 0
        self.dropped = False
        self.mid = 0
        self.on_connect = self.on_disconnect = self.on_publish = None

    def connect(self, host: str, port: int, keepalive: int = 60) -> None:
        if not self.broker.up:
            raise ConnectionRefusedError(111, "Connection refused")
        self.sock = True
        self.connack_due = True
        self.broker.client = self

    def socket(self) -> bool | None:
        return self.sock

    def _reset_sockets(self) -> None:
        self.sock = None

    def disconnect(self) -> None:
        self.sock = None

    def publish(self, topic: str, payload: str, qos: int = 0, retain: bool = False) -> Info:
        self.mid += 1
        if self.sock is None:
            return Info(mqtt.MQTT_ERR_NO_CONN, self.mid)
        msg = json.loads(payload)
        self.broker.received.append((topic, msg))
        self.outstanding.append((self.mid, msg.get("seq") if msg.get("kind") in ("event", "summary") else None))
        return Info(mqtt.MQTT_ERR_SUCCESS, self.mid)

    def loop(self, timeout: float = 1.0) -> int:
        if self.sock is None:
            return mqtt.MQTT_ERR_NO_CONN
        if self.dropped or self.broker.client is not self:
            self.sock = None
            self.on_disconnect(self, None, None, ReasonCode(PacketTypes.DISCONNECT, "Unspecified error"), None)
            return mqtt.MQTT_ERR_CONN_LOST
        if self.connack_due:
            self.connack_due = False
            self.on_connect(self, None, None, ReasonCode(PacketTypes.CONNACK, "Success"), None)
        while self.acks_released and self.outstanding:
            self.acks_released -= 1
            mid, seq = self.outstanding.pop(0)
            if seq is not None:
                self.broker.acked.add(seq)
            self.on_publish(self, None, mid, ReasonCode(PacketTypes.PUBACK, "Success"), None)
        return mqtt.MQTT_ERR_SUCCESS


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def settings_for(tmp: Path, **mqtt_over: Any) -> UplinkSettings:
    raw = {
        "enabled": True,
        "machine_id": "m1",
        "mqtt": {"max_inflight": 4, "ack_timeout_s": 60, "reconnect_min_s": 1, "reconnect_max_s": 8, **mqtt_over},
    }
    return UplinkSettings.from_raw(raw, tmp)


class PublisherModel(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.tmp = TMP / f"run-{next(RUNS)}"
        self.tmp.mkdir()
        self.settings = settings_for(self.tmp)
        self.clock = Clock()
        # the daemon's side; fsync not needed here. The outbox clock (ages, late) runs on the test's clock
        self.writer = Outbox(self.settings.outbox.path, durable=False, clock=self.clock)
        self.broker = ModelBroker()
        self.written: dict[int, str] = {}  # seq -> kind
        self.pub = self._publisher()

    def _publisher(self) -> Publisher:
        box = Outbox(self.settings.outbox.path, durable=False, clock=self.clock)
        return Publisher(
            self.settings,
            box,
            clock=self.clock,
            wall=self.clock,
            rng=lambda: 0.5,
            client_factory=lambda: FakeClient(self.broker),
            sleep=lambda s: None,
        )

    @initialize()
    def start(self) -> None:
        REACHED["runs"] += 1

    @rule(kinds=st.lists(st.sampled_from(["event", "summary"]), min_size=1, max_size=6))
    def daemon_writes(self, kinds: list[str]) -> None:
        before = self.writer.con.execute("SELECT seq FROM sqlite_sequence WHERE name='entries'").fetchone()
        start = before[0] if before else 0
        self.writer.append([(k, 1.7e9 + start + i, self.clock(), dumps({"n": start + i})) for i, k in enumerate(kinds)])
        for i, k in enumerate(kinds):
            self.written[start + i + 1] = k

    @rule(n=st.integers(1, 6), acks=st.integers(0, 3), dt=st.sampled_from([0.1, 0.1, 0.1, 5.0, 90.0]))
    def step(self, n: int, acks: int, dt: float) -> None:
        """The uplink's loop runs ``n`` times, ``dt`` seconds apart; before each, the broker sends
        ``acks`` PUBACKs (90 s without one ends the connection: the ack timeout is 60 s)."""
        for _ in range(n):
            self.clock.t += dt
            if self.broker.client is not None:
                self.broker.client.acks_released += acks
            before = self.pub.stats.ack_timeouts
            self.pub.iterate()
            REACHED["ack timeouts"] += self.pub.stats.ack_timeouts - before

    @rule()
    def connection_drops(self) -> None:
        if self.broker.client is not None and self.broker.client.sock:
            self.broker.client.dropped = True
            REACHED["drops"] += 1

    @rule()
    def broker_goes_down(self) -> None:
        self.broker.up = False
        self.connection_drops()

    @rule()
    def broker_comes_back(self) -> None:
        self.broker.up = True

    @rule()
    def uplink_killed_and_restarted(self) -> None:
        # SIGKILL: no clean-up at all; acknowledged entries not yet deleted stay in the outbox.
        self.broker.client = None
        self.pub.box.close()
        self.pub = self._publisher()
        REACHED["restarts"] += 1

    @invariant()
    def only_acknowledged_entries_leave_the_outbox(self) -> None:
        left = set(self.written) - {r.seq for r in self.writer.fetch_after(0, 10**6)}
        assert left <= self.broker.acked
        if left:
            REACHED["deleted after PUBACK"] += 1

    @invariant()
    def order_per_topic_and_duplicates_marked(self) -> None:
        first: dict[int, dict[str, Any]] = {}
        per_topic: dict[str, list[int]] = defaultdict(list)
        for topic, msg in self.broker.received:
            if msg["kind"] not in ("event", "summary"):
                continue
            seq = msg["seq"]
            assert topic == f"cmcan/m1/{self.written[seq]}" and msg["id"] == f"{self.pub.box.stream_id}-{seq}"
            if seq in first:
                REACHED["duplicates"] += 1
                assert {k: v for k, v in msg.items() if k != "late"} == {
                    k: v for k, v in first[seq].items() if k != "late"
                }
            else:
                first[seq] = msg
                per_topic[topic].append(seq)
        for seqs in per_topic.values():
            assert seqs == sorted(seqs)

    def teardown(self) -> None:
        # The broker comes back and acknowledges everything: every entry arrives, the outbox empties.
        try:
            self.broker.up = True
            for _ in range(2000):
                self.clock.t += 0.5
                if self.broker.client is not None:
                    self.broker.client.acks_released += 100
                self.pub.iterate()
                if not self.writer.fetch_after(0, 1) and not self.pub.acked:
                    break
            got = {m["seq"] for _, m in self.broker.received if m["kind"] in ("event", "summary")}
            assert got == set(self.written)
            assert not self.writer.fetch_after(0, 1)
            if any(m.get("late") for _, m in self.broker.received):
                REACHED["late"] += 1
        finally:
            self.pub.box.close()
            self.writer.close()


TMP: Path


def test_publisher_delivery_rules_under_random_interleavings(tmp_path):
    global TMP
    TMP = tmp_path
    REACHED.clear()
    run_state_machine_as_test(
        PublisherModel,
        settings=settings(
            max_examples=120,
            stateful_step_count=40,
            deadline=None,
            derandomize=True,  # the same runs everywhere: the reach check below cannot flake
            suppress_health_check=list(HealthCheck),
        ),
    )
    # The interesting cases were reached, not just the happy path.
    for case in ("drops", "restarts", "duplicates", "deleted after PUBACK", "ack timeouts", "late"):
        assert REACHED[case] > 0, (case, dict(REACHED))


def test_late_is_measured_on_the_outbox_clock_not_the_wall_clock(tmp_path):
    """The wall clock steps 3 years back (a GPS fix after a boot in the future) while an entry waits
    two minutes, then 200 days ahead while the next waits one second: the first is late, the second
    not (on the wall clock it was the other way round)."""
    boot, wall = Clock(), Clock()
    wall.t = 1.7e9
    s = settings_for(tmp_path, late_after_s=60)
    writer = Outbox(s.outbox.path, durable=False, clock=boot)
    broker = ModelBroker()
    pub = Publisher(
        s,
        Outbox(s.outbox.path, durable=False, clock=boot),
        clock=boot,
        wall=wall,
        rng=lambda: 0.5,
        client_factory=lambda: FakeClient(broker),
    )

    def publish_one(n: int) -> dict[str, Any]:
        for _ in range(4):  # connect, CONNACK, publish
            pub.iterate()
        return next(m for _, m in reversed(broker.received) if m.get("n") == n)

    writer.append([("event", 1.7e9, wall(), dumps({"n": 1}))])
    boot.t += 120.0
    wall.t -= 3 * 365 * 86400
    assert publish_one(1)["late"] is True
    writer.append([("event", 1.7e9 + 1, wall(), dumps({"n": 2}))])
    boot.t += 1.0
    wall.t += 200 * 86400
    assert publish_one(2)["late"] is False
    assert pub.stats.late == 1
