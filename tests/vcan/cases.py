"""Integration tests on a real SocketCAN bus (vcan0) with can-utils as the peers.

They run where vcan0 exists (natively, or inside the throwaway VM of ``tests/vcan/vm.py``); on a
host without CAN, ``test_vcan.py`` stands in for them and reports what the VM ran. One daemon
(``cmcan run`` as a real process) serves the module; the tests run in file order.
"""

from __future__ import annotations

import itertools
import math
import os
import re
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from cmcan import config as cfgmod
from cmcan.assemble import assemble, dbc_for
from cmcan.io.candump import iter_frames, write_candump
from cmcan.replay import FrameCollector, replay
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run
from cmcan.sim.run import simulate
from tests.vcan import warm
from tests.vcan.support import SocketListener, in_vm

ROOT = Path(__file__).resolve().parents[2]
IFACE = "vcan0"
RATIO_ID, SPEED_ID, WARN_ID = 0x3A0, 0x3A1, 0x3A2
INPUT_MESSAGES = ("PUMP_STATUS", "LOOP_PRESSURE", "MOTOR_STATUS", "OIL_STATUS")
# Past the unit's TimeoutStopSec systemd kills the daemon: its process must be gone by then.
STOP_TIMEOUT_S = float(
    re.search(r"^TimeoutStopSec=(\d+)s$", (ROOT / "systemd" / "cmcan.service").read_text(), re.M).group(1)
)
LEAK_AT_S = 12.0


def make_log(path: Path, seconds: float, leak_lpm: float) -> Path:
    """A steady rig point; a bypass leakage opens at LEAK_AT_S and raises the low warning."""
    events = (
        [{"type": "leakage", "start_h": LEAK_AT_S / 3600, "extra_lpm": leak_lpm, "ref_dp_bar": 300}] if leak_lpm else []
    )
    s = scn.from_dict(
        {
            "name": "vcan",
            "seed": 5,
            "duration_h": seconds / 3600,
            "start_epoch_s": 1767225600.0,
            "oil": {"model": "prescribed", "temp_c": 50.0},
            "duty": {"kind": "constant", "pump_speed_rpm": 2000, "pump_disp_pct": 70, "dp_bar": 300},
            "events": events,
        }
    )
    db = dbc_for(cfgmod.load())
    f = frames_from_run(simulate(s, db), db)
    write_candump(path, f.timestamp_s, f.arbitration_id, f.dlc, f.data, channel="can0")
    return path


def make_config(tmp: Path, counters: bool = True) -> Path:
    """The shipped configuration on vcan0, with windows short enough for a 30 s test; without
    ``counters`` the inputs' alive counters are not checked (a peer that repeats one payload)."""
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    if not counters:
        for name in INPUT_MESSAGES:
            raw.setdefault("messages", {}).setdefault(name, {})["counter"] = "none"
    raw["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    raw["bus"].update(interface="socketcan", channel=IFACE)
    raw["filter"].update(samples=20, min_samples=10)
    raw["thresholds"].update(debounce_s=2.0)
    raw["state"]["directory"] = str(tmp / "state")
    p = tmp / "vcan.yaml"
    p.write_text(yaml.safe_dump(raw))
    return p


class Notifications(SocketListener):
    """What the daemon says over its sd_notify socket: (time, text)."""

    def __init__(self, path: Path) -> None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(str(path))
        self.path = path
        super().__init__(sock)

    def read(self) -> tuple[str]:
        return (self.sock.recv(4096).decode(),)

    def status(self) -> str:
        texts = [m for _, m in self.got if "STATUS=" in m]
        return texts[-1].split("STATUS=", 1)[1] if texts else ""

    def counters(self) -> dict[str, int]:
        s = self.status()
        m = re.search(
            r"frames (\d+) \(inputs (\d+), bad length (\d+), out of range (\d+), unknown (\d+), late (\d+)\)", s
        )
        assert m, s
        keys = ("frames_total", "accepted", "bad_length", "out_of_range", "unknown_id", "late")
        return dict(zip(keys, map(int, m.groups()), strict=True))

    def wait_for(self, pred, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred():
                return True
            time.sleep(0.05)
        return False


class Daemon:
    def __init__(self, tmp: Path, cfg: Path, name: str) -> None:
        (tmp / "state").mkdir(exist_ok=True)
        self.notify = Notifications(tmp / f"{name}.sock")
        self.log = tmp / f"{name}.stderr"
        self._err = open(self.log, "w")  # noqa: SIM115 - the daemon process writes it until it stops
        env = {
            **os.environ,
            "NOTIFY_SOCKET": str(self.notify.path),
            "WATCHDOG_USEC": "1000000",
            "PYTHONUNBUFFERED": "1",
        }
        self.proc = warm.WarmProcess(["run", "--config", str(cfg)], env=env, stderr=self.log)
        ok = self.notify.wait_for(
            lambda: any("READY=1" in m for _, m in self.notify.got) or self.proc.poll() is not None, 180
        )
        assert ok and self.proc.poll() is None, self.stderr()

    def stderr(self) -> str:
        return self.log.read_text() if self.log.exists() else ""

    def fresh_status(self, timeout: float = 10.0) -> dict[str, int]:
        """Counters from a STATUS sent after now (the daemon reports every 2 s)."""
        n = len(self.notify.got)
        got = self.notify.wait_for(lambda: any("STATUS=" in m for _, m in self.notify.got[n:]), timeout)
        assert got, f"no STATUS within {timeout} s; the daemon said: {self.stderr()[-3000:]}"
        return self.notify.counters()

    def stop(self) -> tuple[float, float]:
        """SIGTERM; the seconds until the daemon said STOPPING=1 (it has left its loop and saves the
        state) and until its process was gone (after the interpreter's teardown, which in the
        emulated guest takes seconds of its own when the test extras' heavy modules are loaded)."""
        n = len(self.notify.got)
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(timeout=30)
        gone = time.monotonic() - t0
        self.notify.wait_for(lambda: any("STOPPING=1" in m for _, m in self.notify.got[n:]), 1.0)
        self.notify.stop = True
        said = next((t for t, m in self.notify.got[n:] if "STOPPING=1" in m), math.inf)
        return said - t0, gone


def candump(out: Path) -> subprocess.Popen:
    """Record cmcan's output frames (0x3A0-0x3AF) in candump -L format."""
    filters = "3A0:7F0"
    return subprocess.Popen(["candump", "-L", f"{IFACE},{filters}"], stdout=open(out, "w"), stderr=subprocess.DEVNULL)


def stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()


def play(log: Path) -> subprocess.Popen:
    return subprocess.Popen(["canplayer", "-I", str(log), f"{IFACE}=can0"], stderr=subprocess.PIPE, text=True)


def recorded(path: Path) -> list[tuple[float, int, bytes]]:
    return [(f.timestamp_s, f.arbitration_id, f.data) for f in iter_frames(path)]


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("vcan")
    return {
        "tmp": tmp,
        "cfg": make_config(tmp),
        "leak_log": make_log(tmp / "leak.log", 30.0, 15.0),
        "steady_log": make_log(tmp / "steady.log", 14.0, 0.0),
    }


@pytest.fixture(scope="module")
def daemon(work):
    d = Daemon(work["tmp"], work["cfg"], "first")
    yield d
    if d.proc.poll() is None:
        d.proc.kill()


def decode_ratio(db, frames):
    msg = db.get_message_by_name("CM_RATIO")
    out = []
    for t, i, d in frames:
        if i == RATIO_ID:
            v = msg.decode(d, decode_choices=False)
            out.append((t, v["cm_ratio_raw_pct"], v["cm_ratio_filt_pct"], v["cm_filt_valid"], v["cm_raw_valid"]))
    return out


def transitions(db, frames):
    msg = db.get_message_by_name("CM_WARNING")
    levels, last = [], None
    for t, i, d in frames:
        if i == WARN_ID:
            lvl = int(msg.decode(d, decode_choices=False)["warning_level"])
            if lvl != last:
                levels.append((t, lvl))
                last = lvl
    return levels


@pytest.mark.vcan
def test_ready_and_watchdog_over_the_notify_socket(daemon):
    assert daemon.notify.wait_for(lambda: sum("WATCHDOG=1" in m for _, m in daemon.notify.got) >= 3, 10)
    ready = [t for t, m in daemon.notify.got if "READY=1" in m]
    dogs = [t for t, m in daemon.notify.got if "WATCHDOG=1" in m]
    assert len(ready) == 1 and dogs[-1] > ready[0]
    assert np.median(np.diff(dogs)) == pytest.approx(0.5, abs=0.2)  # half of WATCHDOG_USEC


@pytest.mark.vcan
def test_canplayer_log_gives_the_frames_replay_computes(daemon, work):
    tmp = work["tmp"]
    rec = candump(tmp / "out.log")
    time.sleep(0.5)
    player = play(work["leak_log"])
    assert player.wait(timeout=120) == 0, player.stderr.read()
    time.sleep(1.5)
    stop(rec)
    live = recorded(tmp / "out.log")
    parts = assemble(cfgmod.load(work["cfg"]))
    db, mon = parts.db, parts.monitor
    sink = FrameCollector()
    replay(mon, iter_frames(work["leak_log"]), [sink])
    offline = [(f.timestamp_s, f.arbitration_id, f.data) for f in sink.frames_out]
    # every live frame decodes with the DBC
    for _, i, d in live:
        db.decode_message(i, d)
    # Compared on the daemon's clock, which is the frames' time: each CM frame is one 100 ms tick, so a
    # frame's time is the number of CM frames since the first evaluated tick before it. On the wall
    # clock the comparison would measure how far an emulated guest's daemon runs behind the bus (in CI
    # by over 0.5 s), not what it computed. The idle daemon's frames before it are left out.
    live_t, off_t = on_ticks(live, first_evaluated(db, live)), on_ticks(offline, first_evaluated(db, offline))
    tr_live, tr_off = transitions(db, live_t), transitions(db, off_t)
    assert [lvl for _, lvl in tr_live] == [lvl for _, lvl in tr_off] == [0, 1]
    assert abs(tr_live[1][0] - tr_off[1][0]) <= 0.5, (tr_live, tr_off)
    # the same ratios: healthy and leaking medians, and the filtered value at the end
    r_live, r_off = decode_ratio(db, live_t), decode_ratio(db, off_t)
    for lo, hi in ((3.0, LEAK_AT_S - 1.0), (LEAK_AT_S + 5.0, 29.0)):
        a = [r for t, r, _, _, ok in r_live if ok and lo <= t <= hi]
        b = [r for t, r, _, _, ok in r_off if ok and lo <= t <= hi]
        assert len(a) > 0.7 * len(b) > 10
        assert np.median(a) == pytest.approx(np.median(b), abs=0.05)
    # CM frames at their 100 ms period on the real bus, on average over the log (a guest that falls
    # behind sends some in bursts)
    stamps = np.array([t for t, *_ in decode_ratio(db, live)])
    assert (stamps[-1] - stamps[0]) / (len(stamps) - 1) == pytest.approx(0.1, rel=0.2)


def on_ticks(frames, since: float, period_s: float = 0.1, ratio_id: int = RATIO_ID):
    """The frames from ``since`` on, each one's time replaced by its tick: the CM frames from ``since``
    up to it, times the period."""
    out, n = [], -1
    for t, i, d in frames:
        if t >= since:
            n += i == ratio_id
            out.append((max(n, 0) * period_s, i, d))
    return out


def first_evaluated(db, frames, ratio_id: int = RATIO_ID) -> float:
    """When the first evaluated tick's CM_RATIO (a valid raw ratio) went out: where a daemon's frames
    and a replay's line up, whatever each sent before (an idle daemon's ticks, which an emulated
    guest running behind the bus may still send after the log began; a J1939 claim)."""
    msg = db.get_message_by_name("CM_RATIO")
    return next(t for t, i, d in frames if i == ratio_id and msg.decode(d, decode_choices=False)["cm_raw_valid"])


@pytest.mark.vcan
def test_malformed_frames_are_counted_and_ignored(daemon):
    before = daemon.fresh_status()
    for frame in (
        "100#0011",
        "103#FF",
        "100#FFFFFFFFFFFFFFFF",
        "7FF#0011223344556677",
        "00000100#0011223344556677",
        "101#R",
    ):
        subprocess.run(["cansend", IFACE, frame], check=True)
    time.sleep(0.3)
    after = daemon.fresh_status()
    d = {k: after[k] - before[k] for k in after}
    # unknown and extended identifiers never pass the kernel filter; the rest are counted and dropped
    assert d["bad_length"] == 2 and d["out_of_range"] == 1 and d["accepted"] == 0
    assert d["frames_total"] == 4  # the remote frame for 0x101 passes the filter and is counted as such
    assert daemon.proc.poll() is None


def bus_frames() -> int:
    """Frames vcan0 has carried (every frame sent on a vcan is also received on it)."""
    return int(Path(f"/sys/class/net/{IFACE}/statistics/rx_packets").read_text())


def proc_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.vcan
def test_kernel_filters_keep_the_load_flat_under_a_flood(daemon, work):
    tmp = work["tmp"]
    n_inputs = sum(1 for _ in iter_frames(work["steady_log"]))
    runs = {}
    for flood in (False, True):
        before = daemon.fresh_status()
        rec = candump(tmp / f"flood{flood}.log")
        gen = (
            subprocess.Popen(
                ["cangen", IFACE, "-g", "0.2", "-I", "555", "-L", "8", "-D", "r"], stderr=subprocess.DEVNULL
            )
            if flood
            else None
        )
        cpu0 = proc_cpu_s(daemon.proc.pid)
        rx0 = bus_frames()
        player = play(work["steady_log"])
        assert player.wait(timeout=120) == 0
        cpu = proc_cpu_s(daemon.proc.pid) - cpu0
        on_bus = bus_frames() - rx0
        if gen is not None:
            gen.terminate()
            gen.wait(5)
        time.sleep(0.5)
        stop(rec)
        after = daemon.fresh_status()
        stamps = np.array([t for t, i, _ in recorded(tmp / f"flood{flood}.log") if i == RATIO_ID])
        runs[flood] = (cpu, {k: after[k] - before[k] for k in after}, stamps, on_bus)
    cpu_quiet, quiet, _, bus_quiet = runs[False]
    cpu_flood, flooded, stamps, bus_flood = runs[True]
    # The CPU is printed, not asserted: in an emulated guest sharing a busy host it says more about the
    # host than about the filter. What the kernel filter guarantees is asserted instead.
    print(
        f"frames on the bus {bus_quiet} quiet, {bus_flood} flooded; daemon counters quiet {quiet}, "
        f"flooded {flooded}; daemon CPU {cpu_quiet:.2f} s quiet, {cpu_flood:.2f} s flooded"
    )
    assert bus_flood > 3 * bus_quiet  # the flood really was there
    assert quiet["accepted"] == flooded["accepted"] == n_inputs  # no input frame lost
    # Not one flood frame reached the daemon: it counted the inputs and nothing else (the flood's
    # identifier, 0x555, would count as an unknown identifier or a frame beyond the inputs).
    assert flooded["frames_total"] == n_inputs and flooded["unknown_id"] == 0
    assert flooded["bad_length"] == flooded["out_of_range"] == 0
    gaps = np.diff(stamps)
    seen = f"CM_RATIO gaps: median {np.median(gaps):.3f} s, p95 {np.quantile(gaps, 0.95):.3f} s, max {gaps.max():.3f} s"
    assert np.median(gaps) == pytest.approx(0.1, abs=0.01), seen
    # On hardware no period stretches past 350 ms under the flood. In the emulated guest the flood's
    # generator (5000 frames/s, in the same two emulated CPUs) starves every process now and then: there
    # the periods hold (95 % within 250 ms) and nothing stalls like the 1 s idle step of old.
    if in_vm():
        assert np.quantile(gaps, 0.95) < 0.25 and gaps.max() < 0.9, seen
    else:
        assert gaps.max() < 0.35, seen


@pytest.mark.vcan
def test_link_down_and_up_the_daemon_recovers(daemon, work):
    tmp = work["tmp"]
    player = play(work["leak_log"])
    time.sleep(3.0)
    subprocess.run(["ip", "link", "set", IFACE, "down"], check=True)
    time.sleep(2.0)
    subprocess.run(["ip", "link", "set", IFACE, "up"], check=True)
    t_up = time.monotonic()
    rec = candump(tmp / "after_up.log")
    time.sleep(6.0)
    stop(rec)
    player.kill()
    player.wait()
    assert daemon.proc.poll() is None, daemon.stderr()
    frames = recorded(tmp / "after_up.log")
    assert any(i == RATIO_ID for _, i, _ in frames), "no CM frame within 6 s of the link coming back"
    first = min(t for t, i, _ in frames if i == RATIO_ID)
    assert first - (time.time() - (time.monotonic() - t_up)) < 5.0
    assert "network down" in daemon.stderr().lower() or "failed" in daemon.stderr().lower()


@pytest.mark.vcan
def test_sigterm_stops_within_2_s_and_state_survives_restart(daemon, work):
    warnings_before = int(re.search(r"(\d+) warnings", daemon.notify.status()).group(1))
    assert warnings_before >= 1  # the leak of the canplayer test raised one
    reacted, gone = daemon.stop()
    assert reacted < 2.0 and gone < STOP_TIMEOUT_S, (reacted, gone)
    assert daemon.proc.returncode == 0, daemon.stderr()
    assert "stopped:" in daemon.stderr()
    import json

    state = json.loads((work["tmp"] / "state" / "state.json").read_text())
    assert state["warning_count"] == warnings_before and state["history"]
    again = Daemon(work["tmp"], work["cfg"], "second")
    try:
        assert again.notify.wait_for(lambda: f"{warnings_before} warnings" in again.notify.status(), 10)
    finally:
        reacted, gone = again.stop()
        assert reacted < 2.0 and gone < STOP_TIMEOUT_S, (reacted, gone)


# -- the J1939 machine on two channels: a sender that changes its address, DM1 to the kernel's J1939
#    stack (single frame and BAM), inputs split over vcan0 and vcan1 ----------------------------------------

IFACE1 = "vcan1"
J1939_SA = 0x8C
J_SECONDS = 30.0
J_MOVE_AT_S = 8.0  # the drive controller claims address 0x04 instead of 0x03
J_FREEZE_AT_S = 20.0  # its motor message's counter freezes: erratic input, a fault 5 s later
ON_VCAN1 = ("HST_MOTOR", "VF")


def make_j1939_config(tmp: Path) -> Path:
    """The example J1939 machine on vcan0 and vcan1 (motor speed and oil temperature on vcan1)."""
    raw = yaml.safe_load((ROOT / "config" / "j1939-example.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "j1939-example.dbc")
    raw["bus"].update(interface="socketcan", channel=IFACE)
    raw["channels"] = {"extra": [{"channel": IFACE1}], "from_log": {"can0": IFACE, "can1": IFACE1}}
    for name in ON_VCAN1:
        raw["messages"].setdefault(name, {})["channel"] = IFACE1
    raw.setdefault("filter", {}).update(samples=20, min_samples=10)
    raw.setdefault("thresholds", {}).update(debounce_s=2.0)
    raw["state"]["directory"] = str(tmp / "jstate")
    (tmp / "jstate").mkdir(exist_ok=True)
    p = tmp / "j1939-vcan.yaml"
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    return p


def make_j1939_log(path: Path, cfg_path: Path) -> Path:
    """A steady point with a leak from LEAK_AT_S; the sender moves to 0x04 at J_MOVE_AT_S and its
    motor message's counter freezes at J_FREEZE_AT_S. Frames on can0 and can1 as the machine has them."""
    from cmcan.assemble import bus_plan
    from cmcan.sim.frames import with_source_address
    from tests.test_monitor_j1939 import freeze_counter, leak_scenario

    cfg = cfgmod.rename_channels(cfgmod.load(cfg_path), {IFACE: "can0", IFACE1: "can1"})
    db = dbc_for(cfg)
    plan = bus_plan(cfg, db)
    f = frames_from_run(simulate(leak_scenario(J_SECONDS), db, plan.mapping), db, plan=plan)
    t0 = float(f.timestamp_s[0])
    for name in ("HST_PUMP", "HST_MOTOR", "HST_LOOP_PRESSURE", "VF"):
        f = with_source_address(f, db, plan, name, 0x04, t0 + J_MOVE_AT_S)
    f = freeze_counter(f, cfg, plan, "HST_MOTOR", t0 + J_FREEZE_AT_S)
    write_candump(path, f.timestamp_s, f.arbitration_id, f.dlc, f.data, f.channels("can0"), f.is_extended())
    return path


class J1939Listener(SocketListener):
    """A J1939 peer through the kernel's stack (module can-j1939): every broadcast parameter group
    it receives on the interface, transport protocol reassembled by the kernel: (time, PGN, source
    address, data)."""

    def __init__(self, iface: str) -> None:
        sock = socket.socket(socket.PF_CAN, socket.SOCK_DGRAM, socket.CAN_J1939)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        sock.bind((iface, socket.J1939_NO_NAME, socket.J1939_NO_PGN, socket.J1939_NO_ADDR))
        super().__init__(sock)

    def read(self) -> tuple[int, int, bytes]:
        data, addr = self.sock.recvfrom(2048)
        return addr[2], addr[3], data


@pytest.fixture(scope="module")
def j1939_run(work):
    """The J1939 daemon on vcan0 + vcan1 while canplayer plays the log; what the bus and the kernel's
    J1939 stack saw."""
    try:
        socket.socket(socket.PF_CAN, socket.SOCK_DGRAM, socket.CAN_J1939).close()
    except OSError as exc:
        pytest.skip(f"this kernel has no J1939 stack (module can-j1939): {exc}")
    if not Path(f"/sys/class/net/{IFACE1}").exists():
        pytest.skip(f"no {IFACE1}")
    tmp = work["tmp"]
    cfg_path = make_j1939_config(tmp)
    log = make_j1939_log(tmp / "j1939.log", cfg_path)
    d = Daemon(tmp, cfg_path, "j1939")
    listener = J1939Listener(IFACE)
    bus_log = open(tmp / "j1939-bus.log", "w")  # noqa: SIM115 - candump writes it until stopped
    rec = subprocess.Popen(["candump", "-L", IFACE, IFACE1], stdout=bus_log, stderr=subprocess.DEVNULL)
    try:
        before = d.fresh_status()
        time.sleep(0.5)
        player = subprocess.Popen(
            ["canplayer", "-I", str(log), f"{IFACE}=can0", f"{IFACE1}=can1"], stderr=subprocess.PIPE, text=True
        )
        assert player.wait(timeout=180) == 0, player.stderr.read()
        time.sleep(2.0)
        after = d.fresh_status()
        status = d.notify.status()
    finally:
        stop(rec)
        bus_log.close()
        listener.close()
        d.stop()
    return {
        "cfg": cfg_path,
        "log": log,
        "bus": list(iter_frames(tmp / "j1939-bus.log")),
        "dm1": [(t, data) for t, pgn, sa, data in listener.got if pgn == 65226 and sa == J1939_SA],
        "delta": {k: after[k] - before[k] for k in after},
        "status": status,
        "stderr": d.stderr(),
    }


def _outputs(frames):
    from cmcan.can.j1939 import ids

    return [f for f in frames if f.extended and ids.source_address(f.arbitration_id) == J1939_SA]


@pytest.mark.vcan
def test_j1939_machine_decodes_a_sender_that_changes_its_address(j1939_run):
    from cmcan.can.j1939 import ids

    run = j1939_run
    log = list(iter_frames(run["log"]))
    assert sum(ids.source_address(f.arbitration_id) == 0x04 for f in log) > len(log) / 2
    d = run["delta"]
    # every input frame reached the daemon and was used, whichever address it came from; the frozen
    # counter's frames were refused, exactly as the replay of the same log refuses them
    cfg = cfgmod.load(run["cfg"])
    parts = assemble(cfg)
    collected = FrameCollector()
    replay(parts.monitor, iter_frames(run["log"]), [collected])
    offline = collected.frames_out
    c = parts.monitor.counters
    assert c["counter_frozen"] > 900 and c["unknown_id"] == 0
    assert d["frames_total"] == len(log), run["status"]
    assert d["accepted"] == c["accepted"], run["status"]
    assert f"counter frozen {c['counter_frozen']}" in run["status"]
    assert d["unknown_id"] == 0 and d["bad_length"] == 0
    # the live warnings are the ones replay computes for the same log
    db = parts.db
    warn = parts.monitor.outputs.warning.frame_id
    msg = db.get_message_by_name("CM_WARNING")

    live = _outputs(run["bus"])
    # Both timed from the first evaluated tick (the first CM_RATIO with a valid raw ratio), live on the
    # daemon's clock (CM frames since then: on the wall clock an emulated guest's daemon runs behind
    # the bus, and CM frames of idle ticks from before the log may still come out after it began),
    # replay on the log's time. The first warning frame of each (level ok) is where each one's
    # frames begin, not a transition: the daemon was sending before the log played.
    ratio = ids.with_source(parts.monitor.outputs.ratio.frame_id, J1939_SA)

    def from_first_evaluated(frames, count_ticks):
        rows = [(f.timestamp_s, f.arbitration_id, f.data) for f in frames]
        t0 = first_evaluated(db, rows, ratio)
        if count_ticks:
            return on_ticks(rows, t0, ratio_id=ratio)
        return [(t - t0, i, d) for t, i, d in rows if t >= t0]

    def levels(frames):
        out, last = [], None
        for t, i, d in frames:
            if i == warn:
                lvl = int(msg.decode(d, decode_choices=False)["warning_level"])
                if lvl != last:
                    out.append((t, lvl))
                    last = lvl
        return out

    a, b = levels(from_first_evaluated(live, True)), levels(from_first_evaluated(offline, False))
    assert [lvl for _, lvl in a] == [lvl for _, lvl in b] == [0, 1, 3], (a, b)  # ok, low, fault
    assert all(abs(x[0] - y[0]) <= 0.5 for x, y in zip(a[1:], b[1:], strict=True)), (a, b)
    # outputs only on the output channel, from cmcan's own address
    assert live and {f.channel for f in live} == {IFACE}


@pytest.mark.vcan
def test_dm1_reaches_the_kernel_j1939_stack_single_frame_and_bam(j1939_run):
    from cmcan.can.j1939 import dm1, ids

    run = j1939_run
    got = [(t, *dm1.decode(data), len(data)) for t, data in run["dm1"]]
    assert got, "the kernel's J1939 stack received no DM1 from 0x8C"
    kinds = [(lamps.amber_warning, [(x.spn, x.fmi) for x in dtcs], n) for _, lamps, dtcs, n in got]
    # no fault: a single frame with the all-zero DTC and the lamp off
    assert (dm1.Lamp.OFF, [], 8) in kinds
    # the low warning: one DTC, amber lamp, still a single frame
    low = [k for k in kinds if k[0] == dm1.Lamp.ON and len(k[1]) == 1]
    assert low and low[0][1][0][0] == 520192 and low[0][1][0][1] in (17, 18) and low[0][2] == 8
    # low and the erratic input together: two DTCs, which only BAM carries; the kernel reassembled it
    bam = [(lamps, dtcs, n) for _, lamps, dtcs, n in got if len(dtcs) == 2]
    assert bam, kinds
    lamps, dtcs, n = bam[0]
    assert n == 10 and lamps.amber_warning == dm1.Lamp.ON
    assert (dtcs[1].spn, dtcs[1].fmi, dtcs[1].occurrence) == (520193, 2, 1) and dtcs[0].occurrence == 1
    # on the wire: TP.CM, then TP.DT 50..200 ms apart (J1939-21)
    tp = [f for f in _outputs(run["bus"]) if ids.pgn(f.arbitration_id) in (0xEC00, 0xEB00)]
    cm = [i for i, f in enumerate(tp) if ids.pgn(f.arbitration_id) == 0xEC00]
    assert cm
    paced: list[float] = []
    for i in cm:
        session = tp[i : i + 3]
        if len(session) < 3 and i == cm[-1]:
            continue  # the recording stopped during the last session

        assert [ids.pgn(f.arbitration_id) for f in session] == [0xEC00, 0xEB00, 0xEB00]
        gaps = np.diff([f.timestamp_s for f in session])
        # never faster than 50 ms (what the daemon paces); later than J1939-21's 200 ms only by a
        # guest's scheduling (in the emulated guest, 0.23 s once), within a receiver's T1 of 750 ms
        assert np.all((gaps >= 0.05) & (gaps <= 0.75)), gaps
        paced.extend(gaps)
    assert 0.05 <= np.median(paced) <= 0.2, paced


@pytest.mark.vcan
def test_two_vcan_channels_with_inputs_split(j1939_run):
    from cmcan.can.j1939 import ids

    run = j1939_run
    inputs = [f for f in run["bus"] if ids.source_address(f.arbitration_id) != J1939_SA]
    by_channel = {c: sum(f.channel == c for f in inputs) for c in (IFACE, IFACE1)}
    assert by_channel[IFACE] > 1000 and by_channel[IFACE1] > 1000, by_channel
    # every frame of both channels reached the daemon and was used as the replay uses it (the motor
    # speed on vcan1 and the pump on vcan0 make the ratio); only the frozen counter's frames were not
    parts = assemble(cfgmod.load(run["cfg"]))
    replay(parts.monitor, iter_frames(run["log"]))
    assert run["delta"]["frames_total"] == len(inputs)
    assert run["delta"]["accepted"] == parts.monitor.counters["accepted"]
    assert parts.monitor.channels_seen() == {"can0": IFACE, "can1": IFACE1}
    assert "unknown channel" not in run["status"] and "bad fd" not in run["status"]
    assert "Traceback" not in run["stderr"] and "failed" not in run["stderr"], run["stderr"]


# -- wall-clock steps (issue 17): the daemon keeps sending through each ------------------------------
#
# SocketCAN stamps frames with the wall clock; NTP or a GPS fix steps it. The inputs come from cangen
# (one process per input message, a fixed payload of a steady operating point, paced by nanosleep:
# unmoved by the steps; canplayer paces by the wall clock and would stall or burst at each one) while
# the guest's clock is stepped back by 1, 30 and 59 s, forward by one hour, and back to about where
# it was; candump records the daemon's CM frames.

STEPS_S = (-1.0, -30.0, -59.0, 3600.0, -3510.0)
STEP_HOLD_S = 3.0  # after each step: some 30 cycles, the 30 frames judged on each side of a step


def _steady_payloads(tmp: Path) -> dict[int, str]:
    """One frame of each input message from the middle of a steady simulated rig point."""
    frames = list(iter_frames(make_log(tmp / "steady_point.log", 4.0, 0.0)))
    mid = frames[len(frames) // 2].timestamp_s
    out: dict[int, str] = {}
    for f in frames:
        if f.timestamp_s >= mid and f.arbitration_id not in out:
            out[f.arbitration_id] = f.data.hex().upper()
    return out


def _decoded_ratio_frames(db, path: Path):
    msg = db.get_message_by_name("CM_RATIO")
    return [
        (f.timestamp_s, msg.decode(f.data, decode_choices=False))
        for f in iter_frames(path)
        if f.arbitration_id == RATIO_ID
    ]


@pytest.mark.vcan
def test_the_daemon_keeps_sending_through_wall_clock_steps(tmp_path):
    # cangen repeats one payload per message: its alive counter stands still, so it is not checked here
    cfg = make_config(tmp_path, counters=False)
    (tmp_path / "state").mkdir()
    payloads = _steady_payloads(tmp_path)
    assert sorted(payloads) == [0x100, 0x101, 0x102, 0x103]
    err = open(tmp_path / "steps.stderr", "w")  # noqa: SIM115 - the daemon writes it until it stops
    daemon = warm.WarmProcess(
        ["run", "--config", str(cfg)], env={**os.environ, "PYTHONUNBUFFERED": "1"}, stderr=tmp_path / "steps.stderr"
    )
    gens: list[subprocess.Popen] = []
    rec = None
    stepped = 0.0
    try:
        deadline = time.monotonic() + 180
        while "cmcan running on" not in (tmp_path / "steps.stderr").read_text() and time.monotonic() < deadline:
            assert daemon.poll() is None, (tmp_path / "steps.stderr").read_text()
            time.sleep(0.2)
        rec = candump(tmp_path / "steps.log")
        for fid, data in payloads.items():
            gap_ms = "100" if fid == 0x103 else "10"
            gens.append(
                subprocess.Popen(
                    ["cangen", IFACE, "-I", f"{fid:03X}", "-L", "8", "-D", data, "-g", gap_ms],
                    stderr=subprocess.DEVNULL,
                )
            )
        time.sleep(8.0)  # windows filled, filter valid
        for step in STEPS_S:
            time.clock_settime(time.CLOCK_REALTIME, time.time() + step)
            stepped += step
            time.sleep(STEP_HOLD_S)
    finally:
        if stepped:  # the guest's clock back where it was, give or take the time the step took
            time.clock_settime(time.CLOCK_REALTIME, time.time() - stepped)
        for g in gens:
            g.terminate()
            g.wait(5)
        time.sleep(0.5)
        if rec is not None:
            stop(rec)
        daemon.send_signal(signal.SIGTERM)
        code = daemon.wait(20)
        err.close()
    log = (tmp_path / "steps.stderr").read_text()
    assert code == 0, log
    db = dbc_for(cfgmod.load(cfg))
    ratio = _decoded_ratio_frames(db, tmp_path / "steps.log")
    head = (tmp_path / "steps.log").read_text()[:300]
    assert len(ratio) > 10 * (8 + STEP_HOLD_S * len(STEPS_S)) * 0.8, (len(ratio), head, log[-2000:])
    # between two CM frames either a cycle (0.1 s; 0.5 s at most in this slow guest) or a step of the
    # clock plus a cycle: never a silence
    gaps = np.diff([t for t, _ in ratio])
    odd = [g for g in gaps if not 0.0 < g <= 0.5]
    assert len(odd) == len(STEPS_S), (odd, STEPS_S)
    for g, step in zip(odd, STEPS_S, strict=True):
        assert step < g <= step + 0.5, (g, step)
    # not a frame lost or sent twice (the alive counter goes up by one each cycle), and the ratio is
    # evaluated on both sides of each step
    alive = [int(v["cm_alive_counter"]) for _, v in ratio]
    assert all((b - a) % 16 == 1 for a, b in itertools.pairwise(alive))
    cut = [0, *(int(np.flatnonzero(gaps == g)[0]) + 1 for g in odd), len(ratio)]
    for a, b in itertools.pairwise(cut[1:]):
        after = [v["cm_raw_valid"] for _, v in ratio[a : min(b, a + 30)]]
        assert sum(after) >= 0.9 * len(after), after
    print(
        f"{len(ratio)} CM_RATIO frames; the gaps between two frames at the steps {STEPS_S}: "
        f"{[round(float(g), 3) for g in odd]} s; every other gap <= {max(g for g in gaps if 0 < g <= 0.5):.3f} s"
    )
    # and the daemon says so: each step in the journal, with its size
    said = [(w, float(x)) for w, x in re.findall(r"the wall clock stepped (forward|back) by ([0-9.]+) s", log)]
    want = [("back" if s < 0 else "forward", abs(s)) for s in STEPS_S]
    assert len(said) == len(want) and all(
        w == v and abs(x - y) < 0.5 for (w, x), (v, y) in zip(said, want, strict=True)
    ), log


# -- cmcan as a J1939 node and two drives on one bus (tests/vcan/node_cases.py); the on-board baseline:
#    learning, SIGTERM and kill -9, monitoring, reset (tests/vcan/baseline_cases.py); the prognosis's
#    frame and its estimate across a restart (tests/vcan/prognosis_cases.py) ------------------------------
from tests.vcan.baseline_cases import *  # noqa: E402, F403 - collected with these cases, in the same VM
from tests.vcan.connection_cases import *  # noqa: E402, F403
from tests.vcan.node_cases import *  # noqa: E402, F403
from tests.vcan.prognosis_cases import *  # noqa: E402, F403
from tests.vcan.schedule_cases import *  # noqa: E402, F403
