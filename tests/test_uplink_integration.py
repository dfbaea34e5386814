"""The uplink end to end against a real mosquitto: the daemon fed a simulated run on python-can's
virtual bus writes the outbox, ``cmcan uplink`` runs as a real process; the broker is killed (SIGKILL)
mid-stream and restarted, the uplink is killed (SIGKILL) and restarted, and the subscriber must end
with every entry, duplicates only with the same id, order kept per topic."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import can
import pytest

from cmcan import config as cfgmod
from cmcan.assemble import dbc_for
from cmcan.daemon.loop import Daemon, DaemonOptions, bus_kwargs
from cmcan.daemon.preflight import prepare
from cmcan.demo import demo_scenario, scale_windows
from cmcan.sim.frames import frames_from_run
from cmcan.sim.run import simulate
from cmcan.uplink.feed import UplinkFeed
from tests.uplink_support import Broker, Received, Subscriber, needs_mosquitto, uplink_config

pytestmark = needs_mosquitto

LATE_AFTER_S = 1.0


def start_uplink(config: Path, log: Path) -> subprocess.Popen[bytes]:
    with open(log, "ab") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "cmcan", "-v", "uplink", "--config", str(config)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )


def outbox_entries(path: Path) -> int:
    con = sqlite3.connect(path, timeout=5)
    try:
        return con.execute("SELECT entries FROM usage").fetchone()[0]
    finally:
        con.close()


class Player:
    """Plays frames onto the virtual bus in phases the test controls; the daemon monitors them."""

    def __init__(self, frames, channel: str, monitor) -> None:
        self.ts = frames.timestamp_s.tolist()
        self.ids = frames.arbitration_id.tolist()
        self.data = [bytes(r) for r in frames.data]
        self.bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.monitor = monitor
        self.pos = 0

    def play_to(self, end: int) -> None:
        for i in range(self.pos, end):
            self.bus.send(
                can.Message(timestamp=self.ts[i], arbitration_id=self.ids[i], data=self.data[i], is_extended_id=False),
                timeout=30.0,
            )
            if i % 4096 == 0:
                while self.bus.recv(timeout=0) is not None:  # the daemon's own frames: not needed here
                    pass
        self.pos = end
        deadline = time.monotonic() + 60
        while self.monitor.counters["frames_total"] < end and time.monotonic() < deadline:
            time.sleep(0.01)
        assert self.monitor.counters["frames_total"] == end


@pytest.mark.slow
def test_nothing_lost_when_broker_and_uplink_are_killed(tmp_path):
    state = tmp_path / "state"
    state.mkdir()
    broker = Broker(
        tmp_path,
        conf=["allow_anonymous true", "persistence true", f"persistence_location {tmp_path}/", "max_queued_messages 0"],
    ).start()
    config = uplink_config(
        tmp_path / "cmcan.yaml",
        state,
        broker.port,
        summary_every_s=600,
        mqtt={"late_after_s": LATE_AFTER_S, "max_inflight": 10, "health_every_s": 1.0},
    )
    sub = Subscriber(broker.port, "cmcan/wl-0042/#").start()
    # Keep the subscriber's session (its subscription) in the broker's persistence file, so the
    # restarted broker queues for it even before it is back.
    broker.signal(signal.SIGUSR1)
    deadline = time.monotonic() + 10
    while not (tmp_path / "mosquitto.db").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (tmp_path / "mosquitto.db").exists(), broker.log_text()

    # The run-to-failure time-lapse (2 s every hour of operation): three warnings and their clearing.
    cfg = scale_windows(cfgmod.load(config), 2.0, 60.0)
    db = dbc_for(cfg)
    frames = frames_from_run(simulate(demo_scenario(2.0, 60.0), db), db)
    channel = f"uplink-it-{os.getpid()}"
    cfg = cfgmod.with_overrides(cfg, interface="virtual", channel=channel)
    prep = prepare(cfg)
    mon = prep.parts.monitor
    kw = {**bus_kwargs(cfg, cfg.channel_list[0], list(mon.inputs)), "rx_queue_size": 20000, "preserve_timestamps": True}
    settings = cfg.uplink
    feed = UplinkFeed.open(settings, mon)
    daemon = Daemon(cfg, mon, prep.store, lambda: can.Bus(**kw), options=DaemonOptions(), uplink=feed)
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    while daemon.bus is None:
        time.sleep(0.01)
    player = Player(frames, channel, mon)
    uplink_log = tmp_path / "uplink.log"
    uplink = start_uplink(config, uplink_log)
    n = len(frames)
    try:
        # 1: everything flows live.
        player.play_to(n // 3)
        sub.wait_for(lambda m: sum(x.payload.get("kind") == "summary" for x in m) >= 20, 30, "live summaries")
        # 2: the broker dies (SIGKILL) mid-stream; the daemon goes on and the outbox fills.
        broker.kill(signal.SIGKILL)
        player.play_to(2 * n // 3)
        backlog = outbox_entries(settings.outbox.path)
        assert backlog > 50
        time.sleep(LATE_AFTER_S + 0.5)
        broker.start()
        # 3: the uplink catches up, and is killed (SIGKILL) while the daemon streams on.
        player.play_to(5 * n // 6)
        uplink.send_signal(signal.SIGKILL)
        uplink.wait(10)
        player.play_to(n)
        uplink = start_uplink(config, uplink_log)
        daemon.stop()
        thread.join(20)
        assert not thread.is_alive()
        deadline = time.monotonic() + 60
        while outbox_entries(settings.outbox.path) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert outbox_entries(settings.outbox.path) == 0, uplink_log.read_text()
        w = feed.writer.stats
        total = w.written
        sub.wait_for(lambda m: {x.payload.get("seq") for x in m if "seq" in x.payload} >= set(range(1, total + 1)),
                     30, "every entry")  # fmt: skip
    finally:
        uplink.send_signal(signal.SIGTERM)
        try:
            uplink.wait(10)
        except subprocess.TimeoutExpired:
            uplink.kill()
        player.bus.shutdown()
        sub.stop()
        broker.kill()

    # Nothing dropped on the daemon's side, so the outbox holds exactly what the daemon wrote.
    assert (w.queue_full, w.write_failures, w.pruned, w.lost) == (0, 0, 0, 0)
    data = sub.data()
    by_id: dict[str, list[Received]] = defaultdict(list)
    for m in data:
        by_id[m.payload["id"]].append(m)
    stream = {m.payload["id"].rsplit("-", 1)[0] for m in data}
    assert len(stream) == 1
    # Every entry arrived; duplicates (QoS 1 after a lost PUBACK) carry the same id and body.
    assert sorted(m[0].payload["seq"] for m in by_id.values()) == list(range(1, total + 1))
    for copies in by_id.values():
        first = {k: v for k, v in copies[0].payload.items() if k != "late"}
        assert all({k: v for k, v in c.payload.items() if k != "late"} == first for c in copies[1:])
        assert len({c.topic for c in copies}) == 1
    # Order kept per topic: first copies arrive in sequence order.
    per_topic: dict[str, list[int]] = defaultdict(list)
    seen: set[str] = set()
    for m in data:
        if m.payload["id"] not in seen:
            seen.add(m.payload["id"])
            per_topic[m.topic].append(m.payload["seq"])
    assert set(per_topic) == {"cmcan/wl-0042/event", "cmcan/wl-0042/summary"}
    for seqs in per_topic.values():
        assert seqs == sorted(seqs)
    # Entries written during the outage were published late, with their frame times.
    firsts = [by_id[i][0].payload for i in sorted(by_id, key=lambda i: by_id[i][0].payload["seq"])]
    assert any(p["late"] for p in firsts) and any(not p["late"] for p in firsts)
    events = [p for p in firsts if p["kind"] == "event"]
    history = mon.totals.history
    assert [(e["t_s"], e["from"], e["to"], e["reason"]) for e in events] == [
        (h["t_s"], h["from"], h["to"], h["reason"]) for h in history
    ]
    assert [e["to"] for e in events].count("low") == 2 and "high" in [e["to"] for e in events]
    summaries = [p for p in firsts if p["kind"] == "summary"]
    times = [s["t_s"] for s in summaries]
    assert times == sorted(times) and summaries[-1]["window"]["closed_by"] == "shutdown"
    # No summary missing: their per-period parts add up to the monitor's totals.
    assert sum(s["counters"]["ticks"] for s in summaries) == mon.counters["ticks"]
    for lv, total_s in mon.totals.time_in_level_s.items():
        assert sum(s["time_in_level_s"][lv] for s in summaries) == pytest.approx(total_s, abs=1e-2 * len(summaries))
    # Birth on every connection, the last will when the uplink vanished, health while connected.
    status = [m.payload for m in sub.snapshot() if m.topic.endswith("/status")]
    assert sum(s["state"] == "online" for s in status) >= 2
    assert any(s["state"] == "offline" and s["reason"] == "connection lost" for s in status)
    assert any(m.topic.endswith("/health") for m in sub.snapshot())
