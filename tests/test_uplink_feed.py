"""The daemon's side of the uplink: what the feed queues, and that the outbox never stops the daemon."""

from __future__ import annotations

import json
import logging
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from dataclasses import replace

import pytest

from cmcan import config as cfgmod
from cmcan.daemon.loop import Daemon
from cmcan.uplink import feed as feed_mod
from cmcan.uplink.feed import UplinkFeed
from cmcan.uplink.outbox import Outbox
from cmcan.uplink.writer import OutboxWriter
from tests.conftest import run_cli
from tests.helpers import messages, monitor, sim_frames
from tests.test_daemon import ScriptedBus, run_daemon_until
from tests.uplink_support import uplink_config


@pytest.fixture(scope="module")
def frames():
    return sim_frames("two_set_validation", duration_h=0.06)[1]


def quick_warning_config() -> cfgmod.Config:
    """The shipped configuration with a low threshold above a healthy drive's ratio: a warning soon."""
    cfg = cfgmod.load()
    th = replace(cfg.thresholds, low_pct=100.6, high_pct=103.0, debounce_s=20.0)
    return replace(cfg, thresholds=th, filter=replace(cfg.filter, samples=50, min_samples=20))


def test_the_daemon_queues_every_transition_and_a_summary_per_period(frames, tmp_path):
    cfg = quick_warning_config()
    mon = monitor(cfg=cfg)
    writer = OutboxWriter(str(tmp_path / "outbox.sqlite"), 10**9, 1e9).start()
    feed = UplinkFeed(mon, writer, summary_every_s=30.0)
    source = messages(frames)
    n = len(source)
    d = Daemon(cfg, mon, None, lambda: ScriptedBus(source), uplink=feed)
    run_daemon_until(d, lambda: mon.counters["frames_total"] == n)
    got = [(r.kind, r.t_s, json.loads(r.body)) for r in Outbox(tmp_path / "outbox.sqlite").fetch_after(0, 10**6)]
    events = [b for k, _, b in got if k == "event"]
    assert mon.totals.history and [(e["from"], e["to"], e["reason"]) for e in events] == [
        (h["from"], h["to"], h["reason"]) for h in mon.totals.history
    ]
    assert [t for k, t, _ in got if k == "event"] == [h["t_s"] for h in mon.totals.history]
    summaries = [b for k, _, b in got if k == "summary"]
    assert len(summaries) >= 8  # 216 s of data in 30 s periods, the last one closed at shutdown
    assert summaries[-1]["window"]["closed_by"] == "shutdown"
    assert sum(s["counters"]["ticks"] for s in summaries) == mon.counters["ticks"]
    assert sum(s["counters"]["frames_total"] for s in summaries) == mon.counters["frames_total"] == n
    assert summaries[-1]["counters_total"]["outbox_write_failures"] == 0
    low = [s for s in summaries if s["level"] == "low"]
    assert low and all(s["ratio_filt_pct"] < 100.6 for s in low)
    assert any(s["gate_ticks"].get("evaluating", 0) for s in summaries)
    assert feed.errors == 0 and writer.stats.queue_full == 0


def test_a_failing_outbox_never_stops_the_daemon(frames, tmp_path, monkeypatch, caplog):
    def broken(self, rows):
        raise sqlite3.OperationalError("disk I/O error")

    monkeypatch.setattr(Outbox, "append", broken)
    mon = monitor()
    writer = OutboxWriter(str(tmp_path / "outbox.sqlite"), 10**9, 1e9, queue_size=16, backoff_min_s=0.01).start()
    feed = UplinkFeed(mon, writer, summary_every_s=10.0)
    source = messages(frames)
    n = len(source)
    d = Daemon(cfgmod.load(), mon, None, lambda: ScriptedBus(source), uplink=feed)
    run_daemon_until(d, lambda: mon.counters["frames_total"] == n)
    assert mon.counters["frames_total"] == n and d.stats["internal_errors"] == 0
    # Retried with back-off while the daemon ran, given up (counted) at shutdown.
    assert writer.stats.write_failures >= 2 and writer.stats.written == 0
    assert writer.stats.lost + writer.stats.queue_full == writer.stats.submitted + writer.stats.queue_full > 0
    assert not writer.alive
    assert sum("cannot write the outbox" in r.getMessage() for r in caplog.records) <= 2  # rate-limited


def test_a_stuck_outbox_never_blocks_the_receive_loop(frames, tmp_path, monkeypatch):
    gate = threading.Event()
    real = Outbox.append

    def stuck(self, rows):
        gate.wait(20)
        return real(self, rows)

    monkeypatch.setattr(Outbox, "append", stuck)
    mon = monitor()
    writer = OutboxWriter(str(tmp_path / "outbox.sqlite"), 10**9, 1e9, queue_size=16).start()
    feed = UplinkFeed(mon, writer, summary_every_s=10.0)
    source = messages(frames)
    n = len(source)
    d = Daemon(cfgmod.load(), mon, None, lambda: ScriptedBus(source), uplink=feed)
    th = threading.Thread(target=d.run, daemon=True)
    th.start()
    deadline = time.monotonic() + 60
    while mon.counters["frames_total"] < n and time.monotonic() < deadline:
        time.sleep(0.02)
    # Every frame was processed while the writer was stuck: the queue filled and dropped instead.
    assert mon.counters["frames_total"] == n and writer.stats.queue_full > 0
    gate.set()
    d.stop()
    th.join(10)
    assert not th.is_alive()
    notes = [
        json.loads(r.body) for r in Outbox(tmp_path / "outbox.sqlite").fetch_after(0, 10**6) if r.kind == "dropped"
    ]
    assert sum(x["entries"] for x in notes if x["reason"] == "queue_full") == writer.stats.queue_full


def test_a_bug_in_the_feed_is_counted_not_fatal(frames, tmp_path, monkeypatch):
    def bad_sample(tick):
        raise AttributeError("a renamed field")

    monkeypatch.setattr(feed_mod, "_sample", bad_sample)
    mon = monitor()
    writer = OutboxWriter(str(tmp_path / "outbox.sqlite"), 10**9, 1e9).start()
    feed = UplinkFeed(mon, writer, summary_every_s=10.0)
    source = messages(frames)[:20000]
    d = Daemon(cfgmod.load(), mon, None, lambda: ScriptedBus(source), uplink=feed)
    run_daemon_until(d, lambda: mon.counters["frames_total"] == 20000)
    assert mon.counters["frames_total"] == 20000 and feed.errors == mon.counters["ticks"] > 0


def test_cmcan_run_with_the_uplink_enabled_creates_the_outbox(tmp_path):
    state = tmp_path / "state"
    state.mkdir()
    config = uplink_config(tmp_path / "cmcan.yaml", state, 1883)
    p = subprocess.Popen(
        [sys.executable, "-m", "cmcan", "run", "--config", str(config), "--interface", "virtual", "--channel", "ut"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 30
        while not (state / "outbox.sqlite").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert (state / "outbox.sqlite").exists()
        p.send_signal(signal.SIGTERM)
        assert p.wait(10) == 0, p.stderr.read()
    finally:
        p.kill()
    r = run_cli("uplink", "--config", str(config), "--status")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["entries"] == 0


def test_the_baseline_goes_into_the_summaries_and_its_changes_are_events(frames, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="cmcan.daemon")
    cfg = cfgmod.load()
    cfg = replace(cfg, baseline=cfgmod.BaselineConfig.on(min_points=40, coverage_pct=15.0, min_hours=0.01))
    mon = monitor(cfg=cfg)
    writer = OutboxWriter(str(tmp_path / "outbox.sqlite"), 10**9, 1e9).start()
    feed = UplinkFeed(mon, writer, summary_every_s=30.0)
    source = messages(frames)
    n = len(source)  # the bus takes them from the list
    d = Daemon(cfg, mon, None, lambda: ScriptedBus(source), uplink=feed)
    run_daemon_until(d, lambda: mon.counters["frames_total"] == n)
    got = [(r.kind, json.loads(r.body)) for r in Outbox(tmp_path / "outbox.sqlite").fetch_after(0, 10**6)]
    changes = [b for k, b in got if k == "event" and b["type"] == "baseline_change"]
    assert [(c["from"], c["state"]) for c in changes] == [("learning", "monitoring")]
    assert changes[0]["learned_h"] >= 0.01 and changes[0]["coverage_pct"] >= 15.0
    states = [b["baseline"]["state"] for k, b in got if k == "summary"]
    assert states[0] == "learning" and states[-1] == "monitoring"
    assert feed.errors == 0
    said = [r.getMessage() for r in caplog.records if r.name == "cmcan.daemon" and "baseline" in r.getMessage()]
    assert said[0].startswith("baseline learning") and said[-1].startswith("baseline learned")
