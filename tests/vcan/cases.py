"""Integration tests on a real SocketCAN bus (vcan0) with can-utils as the peers.

They run where vcan0 exists (natively, or inside the throwaway VM of ``tests/vcan/vm.py``); on a
host without CAN, ``test_vcan.py`` stands in for them and reports what the VM ran. One daemon
(``cmcan run`` as a real process) serves the module; the tests run in file order.
"""

from __future__ import annotations

import itertools
import os
import re
import signal
import socket
import subprocess
import sys
import threading
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

ROOT = Path(__file__).resolve().parents[2]
IFACE = "vcan0"
RATIO_ID, SPEED_ID, WARN_ID = 0x3A0, 0x3A1, 0x3A2
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


def make_config(tmp: Path) -> Path:
    """The shipped configuration on vcan0, with windows short enough for a 30 s test."""
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    raw["bus"].update(interface="socketcan", channel=IFACE)
    raw["filter"].update(samples=20, min_samples=10)
    raw["thresholds"].update(debounce_s=2.0)
    raw["state"]["directory"] = str(tmp / "state")
    p = tmp / "vcan.yaml"
    p.write_text(yaml.safe_dump(raw))
    return p


class Notifications:
    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.path = path
        self.got: list[tuple[float, str]] = []
        self.stop = False
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while not self.stop:
            try:
                self.got.append((time.monotonic(), self.sock.recv(4096).decode()))
            except (TimeoutError, OSError):
                continue

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
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "cmcan", "run", "--config", str(cfg)],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=self._err,
        )
        ok = self.notify.wait_for(
            lambda: any("READY=1" in m for _, m in self.notify.got) or self.proc.poll() is not None, 180
        )
        assert ok and self.proc.poll() is None, self.stderr()

    def stderr(self) -> str:
        return self.log.read_text() if self.log.exists() else ""

    def fresh_status(self, timeout: float = 10.0) -> dict[str, int]:
        """Counters from a STATUS sent after now (the daemon reports every 2 s)."""
        n = len(self.notify.got)
        assert self.notify.wait_for(lambda: any("STATUS=" in m for _, m in self.notify.got[n:]), timeout)
        return self.notify.counters()

    def stop(self) -> float:
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(timeout=10)
        self.notify.stop = True
        return time.monotonic() - t0


def candump(out: Path) -> subprocess.Popen:
    """Record cmcan's output frames (0x3A0-0x3AF) in candump -L format."""
    return subprocess.Popen(["candump", "-L", f"{IFACE},3A0:7F0"], stdout=open(out, "w"), stderr=subprocess.DEVNULL)


def stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()


def play(log: Path) -> subprocess.Popen:
    return subprocess.Popen(["canplayer", "-I", str(log), f"{IFACE}=can0"], stderr=subprocess.PIPE, text=True)


def recorded(path: Path) -> list[tuple[float, int, bytes]]:
    return [(t, i, d) for t, i, d, *_ in iter_frames(path)]


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
    # the same warning transitions at the same time after the first CM frame, within frame periods
    t_live0 = next(t for t, i, _ in live if i == RATIO_ID)
    t_off0 = next(t for t, i, _ in offline if i == RATIO_ID)
    tr_live = [(t - t_live0, lvl) for t, lvl in transitions(db, live)]
    tr_off = [(t - t_off0, lvl) for t, lvl in transitions(db, offline)]
    assert [lvl for _, lvl in tr_live] == [lvl for _, lvl in tr_off] == [0, 1]
    assert abs(tr_live[1][0] - tr_off[1][0]) <= 0.5
    # the same ratios: healthy and leaking medians, and the filtered value at the end
    r_live, r_off = decode_ratio(db, live), decode_ratio(db, offline)
    for lo, hi in ((3.0, LEAK_AT_S - 1.0), (LEAK_AT_S + 5.0, 29.0)):
        a = [r for t, r, _, _, ok in r_live if ok and lo <= t - t_live0 <= hi]
        b = [r for t, r, _, _, ok in r_off if ok and lo <= t - t_off0 <= hi]
        assert len(a) > 0.7 * len(b) > 10
        assert np.median(a) == pytest.approx(np.median(b), abs=0.05)
    # CM frames at their 100 ms period on the real bus
    stamps = np.array([t for t, *_ in r_live])
    assert np.median(np.diff(stamps)) == pytest.approx(0.1, abs=0.01)


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
        runs[flood] = (
            cpu,
            after["accepted"] - before["accepted"],
            after["frames_total"] - before["frames_total"],
            stamps,
            on_bus,
        )
    cpu_quiet, got_quiet, _, _, bus_quiet = runs[False]
    cpu_flood, got_flood, total_flood, stamps, bus_flood = runs[True]
    print(
        f"frames on the bus {bus_quiet} quiet, {bus_flood} flooded; daemon CPU {cpu_quiet:.2f} s quiet, "
        f"{cpu_flood:.2f} s flooded"
    )
    assert bus_flood > 3 * bus_quiet  # the flood really was there
    assert got_quiet == got_flood == n_inputs  # no input frame lost
    assert total_flood == n_inputs  # not one flood frame reached the daemon
    assert cpu_flood < 1.5 * cpu_quiet + 0.3
    gaps = np.diff(stamps)
    assert np.median(gaps) == pytest.approx(0.1, abs=0.01) and gaps.max() < 0.35


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
    assert daemon.stop() < 2.0
    assert daemon.proc.returncode == 0, daemon.stderr()
    assert "stopped:" in daemon.stderr()
    import json

    state = json.loads((work["tmp"] / "state" / "state.json").read_text())
    assert state["warning_count"] == warnings_before and state["history"]
    again = Daemon(work["tmp"], work["cfg"], "second")
    try:
        assert again.notify.wait_for(lambda: f"{warnings_before} warnings" in again.notify.status(), 10)
    finally:
        assert again.stop() < 2.0


# -- wall-clock steps (issue 17): the daemon keeps sending through each ------------------------------
#
# SocketCAN stamps frames with the wall clock; NTP or a GPS fix steps it. The inputs come from cangen
# (one process per input message, a fixed payload of a steady operating point, paced by nanosleep:
# unmoved by the steps; canplayer paces by the wall clock and would stall or burst at each one) while
# the guest's clock is stepped back by 1, 30 and 59 s, forward by one hour, and back to about where
# it was; candump records the daemon's CM frames.

STEPS_S = (-1.0, -30.0, -59.0, 3600.0, -3510.0)


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
    cfg = make_config(tmp_path)
    (tmp_path / "state").mkdir()
    payloads = _steady_payloads(tmp_path)
    assert sorted(payloads) == [0x100, 0x101, 0x102, 0x103]
    err = open(tmp_path / "steps.stderr", "w")  # noqa: SIM115 - the daemon writes it until it stops
    daemon = subprocess.Popen(
        [sys.executable, "-m", "cmcan", "run", "--config", str(cfg)],
        stdout=subprocess.DEVNULL,
        stderr=err,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
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
            time.sleep(5.0)
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
    assert len(ratio) > 10 * (8 + 5 * len(STEPS_S)) * 0.8, (len(ratio), head, log[-2000:])
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
