"""The daemon around the core: virtual bus, recovery from bus errors, systemd notify, signals, state."""

import contextlib
import errno
import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import can
import numpy as np
import pytest

from cmcan import config as cfgmod
from cmcan.daemon.loop import Daemon, DaemonOptions
from cmcan.demo import stream
from cmcan.monitor.totals import Totals
from cmcan.replay import FrameCollector, replay
from cmcan.service.sdnotify import Notifier
from cmcan.service.statefile import StateStore
from tests.conftest import ROOT
from tests.helpers import as_frames, feed_all, messages, monitor, sim_frames


@pytest.fixture(scope="module")
def frames():
    return sim_frames("two_set_validation", duration_h=0.15)[1]


def test_daemon_on_a_virtual_bus_emits_exactly_what_replay_emits(frames, tmp_path):
    sink = FrameCollector()
    replay(monitor(), as_frames(frames), [sink])
    expected = [(f.arbitration_id, f.data) for f in sink.frames_out]
    received, sent, processed, _ = stream(frames, cfgmod.load(), tmp_path, f"eq-{os.getpid()}")
    got = [(m.arbitration_id, m.data) for m in received]
    assert processed == sent == len(frames)
    assert len(expected) > 10_000
    # After the log ends the daemon goes on broadcasting on its idle timer: those frames come after.
    assert got[: len(expected)] == expected
    assert all(m.timestamp_s >= received[len(expected) - 1].timestamp_s for m in received[len(expected) :])


class ScriptedBus(can.BusABC):
    """A bus that serves frames from a shared list and fails on cue, like a link going down."""

    def __init__(self, source, fail_after=None, fail_send=None, **kw):
        super().__init__(channel="scripted", **kw)
        self.source = source
        self.fail_after = fail_after
        self.fail_send = fail_send
        self.sent = []
        self.served = 0

    def _recv_internal(self, timeout):
        if self.fail_after is not None and self.served >= self.fail_after:
            raise can.CanOperationError("Failed to receive: Network is down", errno.ENETDOWN)
        if not self.source:
            time.sleep(min(timeout or 0, 0.01))
            return None, False
        self.served += 1
        return self.source.pop(0), False

    def send(self, msg, timeout=None):
        if self.fail_send is not None:
            raise can.CanOperationError("Failed to transmit: No buffer space available", self.fail_send)
        self.sent.append(msg)


def run_daemon_until(daemon, done, timeout=60.0):
    """Run the daemon in a thread until ``done()`` holds (which must come within ``timeout``: a
    condition that is never met is the test's fault or the daemon's, not a way to stop it)."""
    th = threading.Thread(target=daemon.run, daemon=True)
    th.start()
    deadline = time.monotonic() + timeout
    while not (reached := done()) and time.monotonic() < deadline:
        time.sleep(0.02)
    daemon.stop()
    th.join(5)
    assert not th.is_alive()
    assert reached, f"not done within {timeout} s"


def test_network_down_is_recovered_by_reopening_the_bus(frames, tmp_path):
    source = messages(frames)[:20000]
    buses = []

    def open_bus():
        if len(buses) == 1:  # the link is still down on the first retry
            buses.append(None)
            raise can.CanOperationError("Failed to open: Network is down", errno.ENETDOWN)
        bus = ScriptedBus(source, fail_after=5000 if not buses else None)
        buses.append(bus)
        return bus

    mon = monitor()
    d = Daemon(
        cfgmod.load(),
        mon,
        StateStore(tmp_path),
        open_bus,
        options=DaemonOptions(backoff_min_s=0.01, backoff_max_s=0.05),
    )
    run_daemon_until(d, lambda: mon.counters["frames_total"] == 20000)
    assert mon.counters["frames_total"] == 20000
    assert d.stats["bus_opens"] == 2 and d.stats["bus_errors"] == 2
    assert buses[-1].sent and (tmp_path / "state.json").exists()


def test_a_full_transmit_queue_drops_frames_but_not_the_daemon(frames, tmp_path):
    source = messages(frames)[:5000]
    mon = monitor()
    d = Daemon(cfgmod.load(), mon, None, lambda: ScriptedBus(source, fail_send=errno.ENOBUFS))
    run_daemon_until(d, lambda: mon.counters["frames_total"] == 5000)
    assert mon.counters["frames_total"] == 5000
    assert d.stats["tx_dropped"] > 0 and d.stats["tx_frames"] == 0 and d.stats["bus_opens"] == 1


def test_a_failing_core_never_stops_the_loop(frames):
    source = messages(frames)[:3000]
    mon = monitor()
    calls = {"n": 0}
    real_feed = mon.feed

    def flaky_feed(*a, **k):
        calls["n"] += 1
        if calls["n"] % 100 == 0:
            raise ZeroDivisionError("a bug")
        return real_feed(*a, **k)

    mon.feed = flaky_feed
    d = Daemon(cfgmod.load(), mon, None, lambda: ScriptedBus(source))
    run_daemon_until(d, lambda: calls["n"] == 3000)
    assert d.stats["internal_errors"] == 30 and calls["n"] == 3000


# the unit's TimeoutStopSec: past it systemd kills the daemon
TIMEOUT_STOP_S = int(re.search(r"^TimeoutStopSec=(\d+)s$", (ROOT / "systemd" / "cmcan.service").read_text(), re.M)[1])


def notify_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(0.2)
    return sock, path


def start_run(tmp_path, env_extra, state_dir):
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **env_extra}
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cmcan",
            "run",
            "--interface",
            "virtual",
            "--channel",
            f"t{os.getpid()}",
            "--state-dir",
            str(state_dir),
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def read_notifications(sock, until, seconds):
    got = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not until(got):
        with contextlib.suppress(TimeoutError):
            got.append(sock.recv(4096).decode())
    return got


def test_run_reports_ready_watchdog_status_and_stops_on_sigterm(tmp_path):
    state = tmp_path / "state"
    state.mkdir()
    StateStore(state).save(Totals(warning_count=7, condition="low"))
    sock, path = notify_socket(tmp_path)
    proc = start_run(tmp_path, {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "400000"}, state)
    try:
        got = read_notifications(sock, lambda g: sum("WATCHDOG=1" in x for x in g) >= 3, 30)
        assert any("READY=1" in g for g in got), got
        assert sum("WATCHDOG=1" in g for g in got) >= 3
        assert any("STATUS=low (ratio_low)" in g and "7 warnings" in g for g in got), got
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        # acted on within 2 s: STOPPING=1 as it leaves its loop to save the state; and the process gone
        # before systemd would kill it (the unit's TimeoutStopSec; the interpreter's own teardown of
        # the test extras' modules takes its time on a loaded machine)
        stopping = read_notifications(sock, lambda g: any("STOPPING=1" in x for x in g), 2.0)
        assert any("STOPPING=1" in g for g in stopping) and time.monotonic() - t0 < 2.0, stopping
        proc.wait(timeout=TIMEOUT_STOP_S)
        assert proc.returncode == 0, proc.stderr.read()
        assert "received SIGTERM, stopping" in proc.stderr.read()
    finally:
        proc.kill()
        sock.close()
    back = StateStore(state).load()
    assert back.warning_count == 7 and back.condition == "low"


def test_sigint_stops_cleanly_and_state_survives_restart(tmp_path):
    state = tmp_path / "state"
    state.mkdir()
    for i in range(2):
        (tmp_path / str(i)).mkdir()
        sock, path = notify_socket(tmp_path / str(i))
        proc = start_run(tmp_path, {"NOTIFY_SOCKET": path}, state)
        try:  # SIGINT once the daemon is up (READY), not after a guess of its start-up time
            assert any("READY=1" in g for g in read_notifications(sock, lambda g: any("READY=1" in x for x in g), 60))
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=5) == 0
        finally:
            proc.kill()
            sock.close()
    doc = json.loads((state / "state.json").read_text())
    assert doc["format"] == "cmcan-state/1" and doc["warning_count"] == 0


def test_corrupt_state_is_kept_aside_not_lost(tmp_path):
    (tmp_path / "state.json").write_text("{ half a docu")
    totals = StateStore(tmp_path).load()
    assert totals == Totals()
    assert (tmp_path / "state.json.corrupt-1").read_text() == "{ half a docu"


@pytest.mark.parametrize("step_s", [3600.0, -30.0])
def test_a_wall_clock_step_does_not_pause_the_daemon(frames, step_s):
    """Frames go on arriving while the wall clock steps: the daemon moves onto the new time base
    (forward: seen against the boot clock; back: seen by the core) and evaluates on without a pause."""
    msgs = messages(frames)
    half = len(msgs) // 2
    for m in msgs[half:]:
        m.timestamp += step_s
    first = msgs[0].timestamp
    after_step = {id(m) for m in msgs[half:]}

    def boot_clock():  # the frames' own pace: the bus played in real time, the boot clock never steps
        m = served[0]
        return m.timestamp - first - (step_s if id(m) in after_step else 0.0)

    plain = monitor()
    feed_all(plain, frames)
    mon = monitor()
    bus = ScriptedBus(list(msgs))
    served = [msgs[0]]
    orig = bus._recv_internal

    def recv(timeout):
        m, f = orig(timeout)
        if m is not None:
            served[0] = m
        return m, f

    bus._recv_internal = recv
    d = Daemon(cfgmod.load(), mon, None, lambda: bus, options=DaemonOptions(idle_after_s=3600), boot_clock=boot_clock)
    run_daemon_until(d, lambda: mon.counters["frames_total"] == len(msgs))
    mon.flush()
    assert mon.counters["clock_steps"] == 1 and mon.counters["late"] == 0
    assert abs(mon.counters["ticks"] - plain.counters["ticks"]) <= 1
    assert abs(mon.counters["evaluated"] - plain.counters["evaluated"]) <= 20


def replayed(mon, frames):
    """The frames a replay emits."""
    sink = FrameCollector()
    replay(mon, frames, [sink])
    return sink.frames_out


def test_two_channels_daemon_emits_what_replay_emits(tmp_path):
    """Inputs split over two buses: the daemon merges them in time order, as the log has them."""
    from dataclasses import replace

    from cmcan.assemble import bus_plan, dbc_for
    from cmcan.sim import scenario as scn
    from cmcan.sim.frames import frames_from_run
    from cmcan.sim.run import simulate

    base = cfgmod.load()
    cfg = replace(
        base,
        channels=replace(base.channels, extra=(cfgmod.ChannelConfig("can1"),)),
        messages={n: cfgmod.MessageConfig(channel="can1") for n in ("MOTOR_STATUS", "OIL_STATUS")},
    )
    db = dbc_for(cfg)
    plan = bus_plan(cfg, db)
    s = scn.load(scn.shipped("two_set_validation")).with_overrides(duration_h=0.03)
    frames = frames_from_run(simulate(s, db, plan.mapping), db, plan=plan)
    assert set(frames.channels("can0")) == {"can0", "can1"}
    expected = replayed(monitor(cfg=cfg), frames.to_frames())
    received, sent, processed, _ = stream(frames, cfg, tmp_path, f"two-{os.getpid()}")
    assert processed == sent == len(frames)
    got = [(m.arbitration_id, m.data) for m in received]
    assert len(expected) > 1000
    assert got[: len(expected)] == [(f.arbitration_id, f.data) for f in expected]


def test_transport_packets_keep_their_spacing_on_the_wire_when_frames_come_fast():
    """A J1939 BAM from a log played much faster than real time: the daemon sends every frame replay
    emits, and its transport packets at least the configured gap apart in wall time."""
    from collections import Counter

    from cmcan.can.j1939 import ids
    from tests.test_monitor_j1939 import freeze_counter, j1939_cfg, machine_frames

    cfg = j1939_cfg()
    frames, plan = machine_frames(cfg, 40.0)
    frames = freeze_counter(frames, cfg, plan, "HST_MOTOR", float(frames.timestamp_s[0]) + 25.0)
    expected = replayed(monitor(cfg=cfg), frames.to_frames())
    n_tp = sum(ids.pdu_format(f.arbitration_id) in (0xEC, 0xEB) for f in expected)
    assert n_tp >= 9
    source = [
        can.Message(timestamp=f.timestamp_s, arbitration_id=f.arbitration_id, is_extended_id=True, data=f.data)
        for f in frames.to_frames()
    ]
    sent_at = []

    class Recording(ScriptedBus):
        def send(self, msg, timeout=None):
            sent_at.append((time.monotonic(), msg))

    mon = monitor(cfg=cfg)
    d = Daemon(cfg, mon, None, lambda: Recording(list(source)), options=DaemonOptions(idle_after_s=3600))
    run_daemon_until(d, lambda: len(sent_at) >= len(expected), timeout=60)
    got = Counter((m.arbitration_id, bytes(m.data)) for _, m in sent_at)
    assert got == Counter((f.arbitration_id, f.data) for f in expected)
    tp = [t for t, m in sent_at if ids.pdu_format(m.arbitration_id) in (0xEC, 0xEB)]
    assert len(tp) == n_tp and min(np.diff(tp)) >= cfg.j1939.bam_packet_gap_ms / 1000 - 1e-3


def test_can_fd_frames_count_the_same_in_the_daemon_and_the_replay():
    """On a classic channel CAN FD frames are counted bad_fd and unused, on an FD channel they are
    inputs; the daemon asks python-can for an FD bus exactly when the configuration says FD."""
    from dataclasses import replace

    from cmcan.daemon.loop import bus_kwargs

    frames = sim_frames("two_set_validation", duration_h=0.01)[1]
    fd_msgs = [
        can.Message(
            timestamp=m.timestamp, arbitration_id=m.arbitration_id, data=m.data, is_extended_id=False, is_fd=True
        )
        for m in messages(frames)
    ]
    for fd in (False, True):
        base = cfgmod.load()
        cfg = replace(base, frames=replace(base.frames, fd=fd))
        assert bus_kwargs(cfg, cfg.channel_list[0], monitor(cfg=cfg).inputs).get("fd", False) == fd
        offline = monitor(cfg=cfg)
        replay(offline, [f._replace(fd=True) for f in as_frames(frames)])
        mon = monitor(cfg=cfg)
        d = Daemon(cfg, mon, None, lambda: ScriptedBus(list(fd_msgs)))
        run_daemon_until(d, lambda m=mon: m.counters["frames_total"] == len(fd_msgs))
        for key in ("accepted", "bad_fd"):
            assert mon.counters[key] == offline.counters[key]
        assert mon.counters["accepted" if fd else "bad_fd"] == len(fd_msgs)


# -- links that are down: the watchdog keeps its interval, a channel that comes late ---------------------


class FakeTime:
    """The loop's clock and sleep: a sleep moves the clock on by what the loop asked for."""

    def __init__(self) -> None:
        self.t = 1000.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.t += seconds


class RecordingNotifier(Notifier):
    """What the daemon tells systemd, with the time of its clock."""

    def __init__(self, clock, watchdog_interval_s: float | None = None) -> None:
        super().__init__(env={})
        self.watchdog_interval_s = watchdog_interval_s
        self.clock = clock
        self.sent: list[tuple[float, tuple[str, ...]]] = []

    def send(self, *fields: str) -> bool:
        self.sent.append((self.clock(), fields))
        return True

    def times(self, field: str) -> list[float]:
        return [t for t, fields in self.sent if field in fields]

    def statuses(self) -> list[str]:
        return [f[len("STATUS=") :] for _, fields in self.sent for f in fields if f.startswith("STATUS=")]


def test_the_watchdog_keeps_its_interval_while_every_link_is_down():
    """The unit's WatchdogSec=10s (a ping every 5 s) and the default back-off growing to 10 s: with the
    adapter gone for a minute the pings keep their interval, and the bus is retried on its back-off,
    not at every ping."""
    ft = FakeTime()
    tries: list[float] = []

    def open_bus():
        tries.append(ft.t)
        raise can.CanOperationError("Failed to open: No such device", errno.ENODEV)

    notifier = RecordingNotifier(ft.clock, watchdog_interval_s=5.0)
    holder: list[Daemon] = []

    def sleep(seconds):
        ft.sleep(seconds)
        if ft.t - 1000.0 >= 60.0:
            holder[0].stop()

    opt = DaemonOptions(status_every_s=3600.0)  # the watchdog alone bounds the waits here
    d = Daemon(cfgmod.load(), monitor(), None, open_bus, notifier, opt, clock=ft.clock, sleep=sleep)
    holder.append(d)
    d.run()
    pings = notifier.times("WATCHDOG=1")
    assert len(pings) >= 12 and pings[0] == 1000.0
    assert max(np.diff([*pings, ft.t])) <= 5.0 + 1e-6, np.diff(pings)
    assert max(ft.sleeps) <= 5.0 + 1e-6
    gaps = np.diff(tries)
    want = [0.5, 1.0, 2.0, 4.0, 8.0] + [10.0] * (len(gaps) - 5)
    assert np.allclose(gaps, want), gaps
    assert "bus down (cannot open: " in notifier.statuses()[-1]
    assert d.links_down == ["can0"] and d.stats["bus_errors"] == len(tries) and d.stats["bus_opens"] == 0


def test_an_overdue_watchdog_ping_is_no_negative_receive_timeout():
    """A guest that falls behind (an emulated one under load) reaches the receive step after its ping
    was due: the wait is zero, not negative. Before, the bus refused the negative timeout, the daemon
    took that for a failed link and reopened it (losing what it held, and a J1939 node claimed again)."""
    ft = FakeTime()
    bus = can.Bus(interface="virtual", channel="overdue-ping", receive_own_messages=False)
    notifier = RecordingNotifier(ft.clock, watchdog_interval_s=1.0)
    d = Daemon(cfgmod.load(), monitor(), None, lambda: bus, notifier, DaemonOptions(), clock=ft.clock, sleep=ft.sleep)
    try:
        live = d.links_up(ft.clock())
        d.loop.next_wd = ft.clock() - 0.3  # the ping is 0.3 s overdue when the loop comes to receive
        got = d.receive(live)
        assert got is not None and len(got) == 0 and d.stats["bus_errors"] == 0 and d.links_down == []
    finally:
        bus.shutdown()


def test_one_bus_hands_its_backlog_over_in_batches_and_keeps_what_it_read_before_a_failure():
    """What has arrived behind the first frame is read in one go (the loop's other steps then run once
    per batch, not per frame), at most DRAIN frames; a bus failing in the middle of a batch loses none
    of the frames read before it."""
    from cmcan.daemon.loop import DRAIN

    ft = FakeTime()
    bus = can.Bus(interface="virtual", channel="backlog", receive_own_messages=False)
    peer = can.Bus(interface="virtual", channel="backlog")
    d = Daemon(
        cfgmod.load(), monitor(), None, lambda: bus, RecordingNotifier(ft.clock), DaemonOptions(), clock=ft.clock
    )
    try:
        live = d.links_up(ft.clock())
        for i in range(DRAIN + 5):
            peer.send(can.Message(arbitration_id=0x100, data=bytes([i % 256]), is_extended_id=False))
        first, rest = d.receive(live), d.receive(live)
        assert len(first) == DRAIN and len(rest) == 5
        assert [m.data[0] for _, m in first + rest] == [i % 256 for i in range(DRAIN + 5)]
        for i in range(3):
            peer.send(can.Message(arbitration_id=0x100, data=bytes([i]), is_extended_id=False))
        real_recv, calls = bus.recv, []

        def failing_recv(timeout=None):
            calls.append(timeout)
            if len(calls) == 3:
                raise can.CanOperationError("the adapter went away")
            return real_recv(timeout)

        bus.recv = failing_recv
        got = d.receive(live)
        assert [m.data[0] for _, m in got] == [0, 1] and d.stats["bus_errors"] == 1
    finally:
        peer.shutdown()
        bus.shutdown()


def test_the_sleep_is_injectable_and_ends_by_the_next_ping_with_a_fast_watchdog():
    """A watchdog faster than the first back-off step (WatchdogSec=0.4s): no wait of the loop outlasts
    its interval, whatever the back-off says."""
    ft = FakeTime()

    def open_bus():
        raise OSError(errno.ENETDOWN, "Network is down")

    notifier = RecordingNotifier(ft.clock, watchdog_interval_s=0.2)
    holder: list[Daemon] = []

    def sleep(seconds):
        ft.sleep(seconds)
        if ft.t - 1000.0 >= 30.0:
            holder[0].stop()

    opt = DaemonOptions(backoff_min_s=5.0, backoff_max_s=20.0)
    d = Daemon(cfgmod.load(), monitor(), None, open_bus, notifier, opt, clock=ft.clock, sleep=sleep)
    holder.append(d)
    d.run()
    pings = notifier.times("WATCHDOG=1")
    assert max(np.diff(pings)) <= 0.2 + 1e-6 and len(pings) >= 140
    assert max(ft.sleeps) <= 0.2 + 1e-6
    assert d.stats["bus_errors"] <= 4  # 0, 5, 15, 35: retried on its back-off only


def test_an_extra_channel_absent_at_the_start_is_a_link_down_until_it_appears(frames, caplog):
    """can1 (a second USB adapter) does not exist when the daemon starts: a warning naming it, can0
    monitored meanwhile, the status says can1 is down and why, and can1 is opened once it appears."""
    from dataclasses import replace

    base = cfgmod.load()
    cfg = replace(base, channels=replace(base.channels, extra=(cfgmod.ChannelConfig("can1"),)))
    source = messages(frames)[:6000]  # served (and used up) by can0's bus
    n_frames = len(source)
    present = threading.Event()
    can1_buses: list[ScriptedBus] = []

    def open_can1():
        if not present.is_set():
            raise OSError(errno.ENODEV, "No such device")
        can1_buses.append(ScriptedBus([]))
        return can1_buses[-1]

    mon = monitor(cfg=cfg)
    notifier = RecordingNotifier(time.monotonic)
    opens = {"can0": lambda: ScriptedBus(source), "can1": open_can1}
    d = Daemon(cfg, mon, None, opens, notifier, DaemonOptions(backoff_min_s=0.01, backoff_max_s=0.05))
    caplog.set_level(logging.INFO, logger="cmcan.daemon")
    seen_down: list[list[str]] = []

    def progress():
        n = mon.counters["frames_total"]
        if n >= n_frames // 2 and not present.is_set():
            seen_down.append(d.links_down)
            present.set()  # the adapter enumerates
        done = n == n_frames and not d.links_down
        finished.append(done)
        return done

    finished: list[bool] = []
    run_daemon_until(d, progress, timeout=30)
    assert seen_down == [["can1"]] and finished[-1]  # both up, before the stop closed them
    assert mon.counters["frames_total"] == n_frames and len(can1_buses) == 1
    warned = [r for r in caplog.records if r.levelno == logging.WARNING and "cannot open the bus can1" in r.message]
    assert warned and "No such device" in warned[0].message and "retrying" in warned[0].message
    statuses = notifier.statuses()
    down = [s for s in statuses if "can0 up, can1 down (cannot open: [Errno 19] No such device)" in s]
    assert down and any("can0 up, can1 up" in s for s in statuses[statuses.index(down[-1]) :])
    assert d.stats["bus_opens"] == 2 and d.stats["bus_errors"] >= 1


class LateBus(ScriptedBus):
    """A kernel-like bus: silent for ``silent_s`` after it opens, then serves its frames stamped with
    the wall clock as they are received."""

    def __init__(self, source, silent_s: float):
        super().__init__(source)
        self.opened = time.monotonic()
        self.silent_s = silent_s
        self.first_served_t: float | None = None  # the first input's time

    def _recv_internal(self, timeout):
        if time.monotonic() - self.opened < self.silent_s:
            time.sleep(min(timeout or 0, 0.01))
            return None, False
        msg, filtered = super()._recv_internal(timeout)
        if msg is not None:
            msg.timestamp = time.time()
            if self.first_served_t is None:
                self.first_served_t = msg.timestamp
        return msg, filtered


def test_a_silent_bus_gets_the_warning_frame_every_second_from_the_start(frames, db):
    """Before any input frame the daemon still says what it knows on the bus: its CM frames with the
    gate no_input and the warning frame every second (nothing to warn about); the first inputs,
    stamped by the bus's wall clock, are then used as usual, not taken for late."""
    source = messages(frames)[:3000]
    bus = LateBus(list(source), silent_s=2.6)
    mon = monitor()
    d = Daemon(cfgmod.load(), mon, None, lambda: bus, options=DaemonOptions(idle_after_s=0.2))
    run_daemon_until(d, lambda: mon.counters["accepted"] >= 2000, timeout=60)
    warn = db.get_message_by_name("CM_WARNING")
    ratio = db.get_message_by_name("CM_RATIO")
    sent = [(m.timestamp, m.arbitration_id, m.data) for m in bus.sent]
    inputs_from = bus.first_served_t
    silent = [(t, i, d) for t, i, d in sent if t < inputs_from]
    warnings = [(t, warn.decode(d, decode_choices=False)) for t, i, d in silent if i == warn.frame_id]
    assert len(warnings) >= 2 and all(w["warning_level"] == 0 for _, w in warnings)
    # the first at the first tick, then one at every whole second of ticks
    assert np.allclose(np.diff([t for t, _ in warnings[1:]]), 1.0, atol=1e-6)
    gates = {ratio.decode(d, decode_choices=False)["cm_gate"] for _, i, d in silent if i == ratio.frame_id}
    assert gates == {1}  # no_input while the bus is silent
    assert mon.counters["late"] == 0 and mon.counters["accepted"] >= 2000


# -- the state directory's files on the daemon's loop (issue 38) ------------------------------------------


def _baseline_daemon(tmp_path, totals=None):
    """A daemon whose configuration learns a baseline, on a bus that is never opened (the steps a test
    drives read the state directory only)."""
    from tests import statefile_support as sf

    path = sf.config_file(tmp_path)
    mon = sf.build(path, totals or Totals())
    store = StateStore(tmp_path / "state")
    return Daemon(cfgmod.load(path), mon, store, lambda: ScriptedBus([])), store


def test_a_fifo_as_the_request_file_does_not_hang_the_start(tmp_path, caplog):
    d, store = _baseline_daemon(tmp_path)
    os.mkfifo(store.dir / "baseline-reset.json")
    th = threading.Thread(target=d._start, daemon=True)
    th.start()
    th.join(5)
    assert not th.is_alive()
    assert "(not a regular file (a FIFO))" in caplog.text and not (store.dir / "baseline-reset.json").exists()


def test_a_failed_reload_still_carries_out_the_reset_it_was_asked_for(tmp_path, caplog):
    """``cmcan baseline reset`` asks for a reload; a configuration that no longer loads keeps the running
    one, and the reset (which needs no new configuration) is carried out all the same."""
    from cmcan.errors import CmcanError, Kind
    from cmcan.service.statefile import write_baseline_request

    d, store = _baseline_daemon(tmp_path)

    def broken():
        raise CmcanError("cmcan.yaml: thresholds.low_pct: expected a number", Kind.CONFIG)

    d.reloader = broken
    caplog.set_level(logging.INFO, "cmcan.daemon")
    d._start()
    write_baseline_request(store.dir, "pump replaced", "2026-01-01T00:00:00Z")
    d.request_reload()
    deadline = time.monotonic() + 10  # built in a thread, swapped in (here: refused) by a later step
    while "reload failed" not in caplog.text and time.monotonic() < deadline:
        d.handle_requests()
        time.sleep(0.01)
    assert "reload failed" in caplog.text and "baseline reset (pump replaced)" in caplog.text
    assert not (store.dir / "baseline-reset.json").exists()
    assert store.read().baseline["history"][-1]["reset_reason"] == "pump replaced"


def test_the_daemon_says_what_of_a_sound_state_it_does_not_go_on_with(tmp_path, caplog):
    """A baseline learned over another envelope (the configuration changed) learns afresh: said at the
    start, naming the state file (a damaged file is said as it is read: tests/test_statefile.py)."""
    from tests import statefile_support as sf

    doc = sf.good_doc()
    doc["baseline"]["envelope"]["edges"][2] = [0.0, 50.0, 100.0]
    d, store = _baseline_daemon(tmp_path, Totals.from_dict(doc))
    d._start()
    (line,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert line == f"{store.path}: baseline: the configured envelope changed: learning afresh"
