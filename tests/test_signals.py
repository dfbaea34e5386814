"""Signals (issue 17, item 2): SIGHUP reloads the configuration and model after checking them, keeping
the monitor's state; SIGTERM and SIGINT stop cleanly; every other signal that would end the daemon at
once saves the state first and exits 128 + N."""

from __future__ import annotations

import dataclasses
import json
import logging
import signal

import pytest
import yaml

from cmcan import config as cfgmod
from cmcan.assemble import assemble
from cmcan.cli import signals as sigmod
from cmcan.daemon.loop import Daemon, DaemonOptions, Reloaded
from cmcan.monitor.warnings import Level
from tests.daemon_proc import DaemonProc, virtual_config
from tests.helpers import as_frames, messages, monitor, sim_frames
from tests.test_daemon import ScriptedBus, run_daemon_until


@pytest.fixture(scope="module")
def leak():
    """The excavator-like run with a leak early: a low warning within the first 0.06 h."""
    ev = {"type": "leakage", "start_h": 0.02, "extra_lpm": 8.0, "ref_dp_bar": 300}
    return sim_frames("two_set_validation", duration_h=0.1, events=[ev])[1]


def split(frames, at: float):
    k = int(len(frames.timestamp_s) * at)
    return as_frames(frames)[:k], as_frames(frames)[k:]


# -- the core: what a reload keeps -------------------------------------------------------------------


def test_a_reload_of_the_same_configuration_is_seamless(leak):
    """Reloading an unchanged configuration and model gives, frame for frame, what the daemon would
    have sent without the reload: nothing started afresh."""
    first, second = split(leak, 0.5)
    whole = monitor()
    want = [f for fr in (*first, *second) for f in whole.feed(fr)] + whole.flush()
    old = monitor()
    got = [f for fr in first for f in old.feed(fr)]
    new = monitor()
    assert new.take_over(old) == []
    got += [f for fr in second for f in new.feed(fr)] + new.flush()
    assert got == want
    assert new.counters == whole.counters and new.save_totals().to_dict() == whole.save_totals().to_dict()


def test_a_reload_keeps_the_warning_and_says_what_starts_afresh(leak):
    first, second = split(leak, 0.7)
    old = monitor()
    for fr in first:
        old.feed(fr)
    assert old.machine.level == Level.LOW and old.totals.warning_count == 1
    # a new mapping scale for the motor speed (a sensor swapped): windows and clock start afresh
    base = cfgmod.load()
    sig = dict(base.signals)
    sig["motor_speed_rpm"] = dataclasses.replace(sig["motor_speed_rpm"], scale=1.0001)
    th = dataclasses.replace(base.thresholds, debounce_s=30.0)
    new = assemble(dataclasses.replace(base, signals=sig, thresholds=th)).monitor
    afresh = new.take_over(old)
    assert any("input windows" in a for a in afresh) and any("tick clock" in a for a in afresh)
    assert new.machine.level == Level.LOW and new.machine.th.debounce_s == 30.0
    assert new.totals is old.totals and new.counters["frames_total"] == old.counters["frames_total"]
    n_before = old.counters["frames_total"]
    for fr in second:
        new.feed(fr)
    assert new.counters["frames_total"] == n_before + len(second)
    assert new.totals.warning_count == 1 and new.machine.level == Level.LOW


# -- the daemon: reload between two frames ------------------------------------------------------------


def test_the_daemon_reloads_between_frames_and_keeps_running_on_a_bad_reload(leak, caplog):
    cfg = cfgmod.load()
    msgs = messages(leak)
    bus = ScriptedBus(list(msgs))
    d = Daemon(cfg, monitor(), None, lambda: bus, options=DaemonOptions(idle_after_s=3600))
    calls = []

    def reloader():
        calls.append(d.monitor.counters["frames_total"])
        if len(calls) == 2:
            raise cfgmod.SchemaError("machine.yaml", "thresholds.low_pct", "expected a number in [50, 100] %")
        new_cfg = dataclasses.replace(cfg, thresholds=dataclasses.replace(cfg.thresholds, low_pct=97.5))
        return Reloaded(new_cfg, assemble(new_cfg).monitor, lambda: bus)

    d.reloader = reloader
    caplog.set_level(logging.INFO, logger="cmcan.daemon")

    def progress():
        n = d.monitor.counters["frames_total"]
        if (n > len(msgs) // 3 and not calls) or (n > 2 * len(msgs) // 3 and len(calls) == 1):
            d.request_reload()
        return n == len(msgs) and len(calls) == 2 and not d.reload_pending  # (a reload is built in a thread)

    run_daemon_until(d, progress)
    assert len(calls) == 2
    assert d.monitor.params.thresholds.low_pct == 97.5  # the first reload took, the second did not undo it
    assert d.monitor.counters["frames_total"] == len(msgs) and d.stats["bus_opens"] == 1
    assert "reloaded" in caplog.text and "started afresh: nothing" in caplog.text
    assert "reload failed, running on with the previous configuration: machine.yaml: thresholds.low_pct" in (
        caplog.text
    )


# -- the real process ---------------------------------------------------------------------------------


def test_kill_hup_reloads_a_checked_configuration_and_keeps_the_running_one_on_error(tmp_path):
    cfg = virtual_config(tmp_path)
    d = DaemonProc(tmp_path, cfg)
    try:
        raw = yaml.safe_load(cfg.read_text())
        raw["thresholds"]["low_pct"] = 97.0
        cfg.write_text(yaml.safe_dump(raw))
        d.signal(signal.SIGHUP)
        assert d.wait_for(lambda: "reloaded" in d.stderr() and d.count("READY=1") >= 2)
        assert d.count("RELOADING=1") == 1 and any("MONOTONIC_USEC=" in n for n in d.notes)
        raw["thresholds"]["low_pct"] = 120.0  # out of range: the running configuration stays
        cfg.write_text(yaml.safe_dump(raw))
        d.signal(signal.SIGHUP)
        assert d.wait_for(lambda: "reload failed" in d.stderr())
        assert "thresholds.low_pct: expected a number in [50, 100] %, got 120" in d.stderr()
        assert d.proc.poll() is None and d.count("READY=1") >= 3
        (tmp_path / "cmcan.yaml").unlink()  # even without its file
        d.signal(signal.SIGHUP)
        assert d.wait_for(lambda: "configuration file not found" in d.stderr()) and d.proc.poll() is None
    finally:
        d.signal(signal.SIGTERM)
        code = d.wait()
    assert code == 0 and "Traceback" not in d.stderr()
    assert json.loads((tmp_path / "state" / "state.json").read_text())["format"] == "cmcan-state/1"


@pytest.mark.parametrize("sig", [signal.SIGUSR1, signal.SIGQUIT, signal.SIGUSR2, signal.SIGRTMIN + 3])
def test_other_fatal_signals_save_the_state_and_exit_128_plus_n(tmp_path, sig):
    cfg = virtual_config(tmp_path)
    d = DaemonProc(tmp_path, cfg)
    d.signal(sig)
    assert d.wait() == 128 + sig, d.stderr()
    err = d.stderr()
    assert "saving state" in err and "stopped:" in err and "Traceback" not in err
    assert json.loads((tmp_path / "state" / "state.json").read_text())["format"] == "cmcan-state/1"
    assert d.count("STOPPING=1") == 1


def test_the_fatal_set_leaves_out_faults_and_the_uncatchable():
    handled = {sigmod.RELOAD, *sigmod.STOP, *sigmod.FATAL}
    for s in ("SIGKILL", "SIGSTOP", "SIGSEGV", "SIGBUS", "SIGFPE", "SIGILL", "SIGABRT", "SIGSYS", "SIGCHLD"):
        assert getattr(signal, s) not in handled
    for s in ("SIGHUP", "SIGTERM", "SIGINT", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM", "SIGPWR"):
        assert getattr(signal, s) in handled


def test_the_unit_restarts_on_failure_but_not_on_a_configuration_error():
    """Every exit code of a problem a restart cannot cure (usage, data, no input, unavailable, cannot
    create, configuration) is in RestartPreventExitStatus; a temporary failure (75: another daemon
    holds the state directory) and a crash are restarted; SIGHUP reloads."""
    from cmcan.cli.errors import EXIT_CODES
    from cmcan.errors import Kind
    from tests.conftest import ROOT

    unit = (ROOT / "systemd" / "cmcan.service").read_text().splitlines()
    keys = {}
    for line in unit:
        if "=" in line and not line.startswith("#"):
            k, v = line.split("=", 1)
            keys.setdefault(k, []).append(v)
    prevent = {int(x) for v in keys["RestartPreventExitStatus"] for x in v.split()}
    for kind, code in EXIT_CODES.items():
        if kind in (Kind.TEMPFAIL, Kind.SOFTWARE, Kind.IO_ERROR):  # what a restart may cure
            assert code not in prevent, kind
        else:
            assert code in prevent, kind
    assert keys["Restart"] == ["on-failure"] and keys["ExecReload"] == ["/bin/kill -HUP $MAINPID"]


# -- a J1939 machine: input health, DM1 and BAM sessions carry over; a reload that moves an input -------


def test_a_reload_of_a_j1939_machine_is_seamless_through_a_fault_and_a_bam():
    """Input health (the frozen counter's run), DM1 occurrence counts and a BAM session under way
    carry over: the reloaded monitor sends, frame for frame, what the running one would have."""
    from tests.test_monitor_j1939 import freeze_counter, j1939_cfg, machine_frames

    cfg = j1939_cfg()
    frames, plan = machine_frames(cfg, 40.0)
    t0 = float(frames.timestamp_s[0])
    frames = freeze_counter(frames, cfg, plan, "HST_MOTOR", t0 + 25.0).to_frames()
    whole = assemble(cfg).monitor
    want = [f for fr in frames for f in whole.feed(fr)] + whole.flush()
    assert whole.totals.history[-1]["to"] == "fault"
    assert any(len(f.data) == 8 and f.arbitration_id >> 8 & 0xFFFF == 0xECFF for f in want)  # a BAM went out
    for at_s in (27.0, 31.05):  # during the erratic run; after the fault, a BAM session under way
        k = next(i for i, f in enumerate(frames) if f.timestamp_s >= t0 + at_s)
        old = assemble(cfg).monitor
        got = [f for fr in frames[:k] for f in old.feed(fr)]
        new = assemble(cfg).monitor
        assert new.take_over(old) == []
        got += [f for fr in frames[k:] for f in new.feed(fr)] + new.flush()
        assert got == want, at_s
        assert new.snapshot()["inputs"] == whole.snapshot()["inputs"]
        assert new.save_totals().to_dict() == whole.save_totals().to_dict()


def test_a_reload_that_moves_an_input_to_another_channel_reopens_every_bus(leak):
    """The new configuration adds a channel: the daemon closes its bus and opens one per configured
    channel with the new openers; monitoring goes on."""
    from tests.test_monitor_j1939 import j1939_cfg, two_channel_cfg

    cfg = j1939_cfg()
    two = two_channel_cfg(cfg)
    opened: list[str] = []

    def opener(name):
        def open_bus():
            opened.append(name)
            return ScriptedBus([])

        return open_bus

    d = Daemon(cfg, assemble(cfg).monitor, None, {"can0": opener("can0")}, options=DaemonOptions(idle_after_s=3600))
    d.reloader = lambda: Reloaded(two, assemble(two).monitor, {"can0": opener("can0"), "can1": opener("can1")})

    def progress():
        if opened == ["can0"]:
            d.request_reload()
        return len(opened) >= 3

    run_daemon_until(d, progress)
    assert opened == ["can0", "can0", "can1"]
    assert [x.name for x in d.links] == ["can0", "can1"] and d.monitor.channels.names == ("can0", "can1")


# -- requests while every link is down ------------------------------------------------------------------


def test_a_reload_during_the_back_off_is_applied_at_once_and_retries_the_bus():
    """Every link down and 30 s to the next retry: a reload request wakes the wait, the new
    configuration takes over and the bus is retried there and then (the operator has just plugged the
    adapter in), long before the back-off would have."""
    import errno
    import threading

    import can

    cfg = cfgmod.load()
    plugged = threading.Event()
    events: list[str] = []

    def open_bus():
        if not plugged.is_set():
            events.append("open failed")
            raise can.CanOperationError("Failed to open: No such device", errno.ENODEV)
        events.append("open")
        return ScriptedBus([])

    opt = DaemonOptions(backoff_min_s=30.0, backoff_max_s=30.0, status_every_s=3600.0)
    d = Daemon(cfg, monitor(), None, open_bus, options=opt)

    def reloader():
        events.append("reload")
        new_cfg = dataclasses.replace(cfg, thresholds=dataclasses.replace(cfg.thresholds, low_pct=97.5))
        return Reloaded(new_cfg, assemble(new_cfg).monitor, open_bus)

    d.reloader = reloader
    th = threading.Thread(target=d.run, daemon=True)
    th.start()
    try:
        assert _wait_until(lambda: events == ["open failed"], 10)  # in its 30 s back-off now
        plugged.set()
        d.request_reload()
        assert _wait_until(lambda: "open" in events, 10), events
        assert events == ["open failed", "reload", "open"]
        assert d.monitor.params.thresholds.low_pct == 97.5 and d.links_down == []
    finally:
        d.stop()
        th.join(10)
    assert not th.is_alive()


def test_a_stop_during_the_back_off_ends_the_wait():
    import threading

    def open_bus():
        raise OSError(19, "No such device")

    opt = DaemonOptions(backoff_min_s=30.0, backoff_max_s=30.0, status_every_s=3600.0)
    d = Daemon(cfgmod.load(), monitor(), None, open_bus, options=opt)
    th = threading.Thread(target=d.run, daemon=True)
    th.start()
    assert _wait_until(lambda: d.stats["bus_errors"] == 1, 10)
    d.stop(signal.SIGTERM)
    th.join(10)  # the back-off had 30 s to go
    assert not th.is_alive() and d.stats["bus_errors"] == 1


def _wait_until(pred, timeout_s: float) -> bool:
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return bool(pred())


def test_a_process_whose_bus_cannot_open_keeps_its_watchdog_and_reloads_on_sighup(tmp_path, monkeypatch):
    """The review's reproducer: an interface that cannot be opened on this machine (python-can's
    vector, Windows only), a watchdog of 0.4 s (a ping every 0.2 s). The pings go on at their interval
    through the back-off, SIGHUP reloads in the middle of it, SIGTERM stops it."""
    monkeypatch.setenv("WATCHDOG_USEC", "400000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    cfg = virtual_config(tmp_path, bus={"interface": "vector", "channel": "0"})
    d = DaemonProc(tmp_path, cfg)
    try:
        assert d.wait_for(lambda: "cannot open the bus 0" in d.stderr(), 30), d.stderr()
        start = d.count("WATCHDOG=1")
        # 10 more pings take 2 s; with a back-off of 0.5, 1, 2, 4 s between pings it took over 7 s
        assert d.wait_for(lambda: d.count("WATCHDOG=1") >= start + 10, 6.0), d.notes
        assert d.count("WATCHDOG=1") >= start + 10
        d.signal(signal.SIGHUP)
        assert d.wait_for(lambda: "reloaded" in d.stderr(), 6.0), d.stderr()
        assert d.proc.poll() is None
    finally:
        d.signal(signal.SIGTERM)
        code = d.wait()
    assert code == 0, d.stderr()
    assert "Traceback" not in d.stderr() and "bus down (cannot open: " in "\n".join(d.notes)


def test_the_unit_comes_back_with_its_can_device():
    """BindsTo= stops the service when can0 goes away; WantedBy= on the same device starts it again
    when the device comes back (Restart= does not restart a stop by a dependency)."""
    from tests.conftest import ROOT

    keys: dict[str, list[str]] = {}
    for line in (ROOT / "systemd" / "cmcan.service").read_text().splitlines():
        if "=" in line and not line.startswith("#"):
            k, v = line.split("=", 1)
            keys.setdefault(k, []).extend(v.split())
    bound = keys["BindsTo"]
    assert bound == ["sys-subsystem-net-devices-can0.device"]
    assert set(bound) <= set(keys["After"])
    assert set(keys["WantedBy"]) == {"multi-user.target", *bound}


class _Pings:
    """A notifier that counts watchdog pings (every 20 ms of the daemon's monotonic clock)."""

    watchdog_interval_s = 0.02
    enabled = True

    def __init__(self) -> None:
        self.pings = 0
        self.sent: list[str] = []

    def watchdog(self) -> None:
        self.pings += 1

    def __getattr__(self, name):  # ready, status, reloading, stopping: noted
        return lambda *a: self.sent.append(name)


def test_a_reload_that_hangs_keeps_the_loop_answering_frames_the_watchdog_and_sigterm():
    """A reload builds its configuration and model off the loop: one that never finishes (a model that
    hangs on load, a configuration on a stalled mount) leaves the daemon handling frames, pinging its
    watchdog and stopping at once when told to, on the configuration it runs."""
    import threading

    release = threading.Event()
    cfg = cfgmod.load()
    msgs = messages(sim_frames("two_set_validation", duration_h=0.01)[1])
    bus = ScriptedBus(list(msgs))
    notifier = _Pings()
    d = Daemon(cfg, monitor(), None, lambda: bus, notifier=notifier, options=DaemonOptions(idle_after_s=3600))
    started = threading.Event()

    def reloader():
        started.set()
        release.wait(60)
        raise RuntimeError("never here in time")

    d.reloader = reloader
    th = threading.Thread(target=d.run, daemon=True)
    th.start()
    try:
        d.request_reload()
        assert started.wait(10)
        pings = notifier.pings
        assert _wait_until(lambda: d.monitor.counters["frames_total"] == len(msgs), 30)
        assert _wait_until(lambda: notifier.pings >= pings + 5, 10)
        assert d.reload_pending and "reloading" in notifier.sent
        d.stop(signal.SIGTERM)
        th.join(5)
        assert not th.is_alive()  # stopped while the reload still hangs
    finally:
        release.set()
        d.stop()
