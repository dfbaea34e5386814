"""The on-board baseline (issue 29, docs/commissioning.md) on a real SocketCAN bus (vcan0): the daemon
(``cmcan run``) learns from logs canplayer plays, its learning survives a SIGTERM and a ``kill -9``,
it reaches monitoring, and ``cmcan baseline reset`` beside it learns afresh. Collected into ``cases``
(one VM for all).

The learning is counted on frames and in the state file, never on the wall clock: every tick the gate
passes (``cm_gate`` evaluating in CM_RATIO, one frame a tick) inside the configured envelope is a
learned tick, so the learned ticks a daemon saved are those it found at its start plus the evaluating
CM_RATIO frames it sent. ``baseline_learned_h`` in CM_BASELINE has a resolution of 0.1 h (6 minutes):
a test learning for seconds reads 0.0 h there, so on the bus the progress is followed in
``baseline_coverage_pct``, with one operating point per bin of the envelope and one log per point.
"""

from __future__ import annotations

import itertools
import json
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from cmcan import config as cfgmod
from cmcan.assemble import dbc_for
from cmcan.io.candump import write_candump
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run
from cmcan.sim.run import simulate
from tests.vcan import warm
from tests.vcan.cases import Daemon, candump, make_config, play, stop

# cases imports this module at its end: the names above are defined by then

_RATIO_ID, _BASELINE_ID = 0x3A0, 0x3A4
_EVALUATING = 0  # cm_gate
_LEARNING, _MONITORING = 1, 2  # baseline_state
# three operating points (pump speed), each in its own bin of a three-bin envelope; one log for each
_SPEEDS_RPM = (1400.0, 1800.0, 2200.0)
_SECONDS = (10.0, 14.0, 10.0)
_MIN_POINTS = 50  # ticks: 5 s of one point covers its bin
_SAVE_EVERY_S = 1.0
_BASELINE = {
    "enabled": True,
    "edges": {"pump_speed_rpm": [1200, 1600, 2000, 2400], "dp_bar": [250, 350], "temp_c": [40, 60]},
    "min_points": _MIN_POINTS,
    "coverage_pct": 100,  # all three bins
    "min_hours": 0.004,  # 144 ticks: reached by the time the three bins hold 50 each
    "check_every_s": 1,  # the learning's end (and the progress the ticks carry) checked every second
}
_H_PER_TICK = 0.1 / 3600.0


def _point_log(path: Path, rpm: float, seconds: float, seed: int) -> Path:
    s = scn.from_dict(
        {
            "name": "vcan-baseline",
            "seed": seed,
            "duration_h": seconds / 3600,
            "start_epoch_s": 1767225600.0,
            "oil": {"model": "prescribed", "temp_c": 50.0},
            "duty": {"kind": "constant", "pump_speed_rpm": rpm, "pump_disp_pct": 70, "dp_bar": 300},
            "events": [],
        }
    )
    db = dbc_for(cfgmod.load())
    f = frames_from_run(simulate(s, db), db)
    write_candump(path, f.timestamp_s, f.arbitration_id, f.dlc, f.data, channel="can0")
    return path


def _baseline_config(tmp: Path) -> Path:
    p = make_config(tmp)
    raw = yaml.safe_load(p.read_text())
    raw["baseline"] = _BASELINE
    raw["state"]["save_every_s"] = _SAVE_EVERY_S
    p.write_text(yaml.safe_dump(raw))
    return p


def _frames(path: Path) -> list[tuple[float, int, bytes]]:
    """What candump -L has written so far (complete lines only: it may be writing the next one)."""
    text = path.read_text() if path.exists() else ""
    out = []
    for line in text[: text.rfind("\n") + 1].splitlines():
        stamp, _, frame = line.split()
        ident, data = frame.split("#", 1)
        out.append((float(stamp.strip("()")), int(ident, 16), bytes.fromhex(data)))
    return out


class _Bus:
    """A candump recording decoded with the DBC: CM_BASELINE's values, CM_RATIO's gate, in order."""

    def __init__(self, db, path: Path) -> None:
        self.path = path
        self.baseline_msg = db.get_message_by_name("CM_BASELINE")
        self.ratio_msg = db.get_message_by_name("CM_RATIO")
        self.proc = candump(path)
        time.sleep(0.5)

    def rows(self) -> list[tuple[float, int, dict]]:
        out = []
        for t, i, d in _frames(self.path):
            if i == _BASELINE_ID:
                out.append((t, i, self.baseline_msg.decode(d, decode_choices=False)))
            elif i == _RATIO_ID:
                out.append((t, i, self.ratio_msg.decode(d, decode_choices=False)))
        return out

    def baseline(self) -> list[dict]:
        return [v for _, i, v in self.rows() if i == _BASELINE_ID]

    def evaluating(self, rows=None) -> int:
        """The evaluating ticks among the CM_RATIO frames: the ticks the baseline learned from."""
        rows = self.rows() if rows is None else rows
        return sum(1 for _, i, v in rows if i == _RATIO_ID and v["cm_gate"] == _EVALUATING)

    def quiet(self, still_s: float = 3.0, timeout: float = 60.0) -> None:
        """Until no evaluating tick has come for ``still_s``: the daemon has worked through what was
        played (in an emulated guest it may trail the player by seconds after the player ends)."""
        deadline = time.monotonic() + timeout
        last, since = self.evaluating(), time.monotonic()
        while time.monotonic() - since < still_s:
            assert time.monotonic() < deadline, f"{self.path.name}: still evaluating after {timeout:g} s"
            time.sleep(0.2)
            n = self.evaluating()
            if n != last:
                last, since = n, time.monotonic()

    def wait(self, pred, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            got = pred(self.rows())
            if got:
                return got
            time.sleep(0.2)
        raise AssertionError(f"{what}: not seen within {timeout:g} s in {self.path.name}")

    def caught_up(self, timeout: float = 120.0) -> None:
        """Wait until the daemon has gone through the whole log: an evaluating tick and, after it, a
        tick the gate did not pass (the inputs went stale when canplayer stopped)."""

        def done(rows):
            gates = [v["cm_gate"] for _, i, v in rows if i == _RATIO_ID]
            return _EVALUATING in gates and any(g != _EVALUATING for g in gates[gates.index(_EVALUATING) :])

        self.wait(done, timeout, "the end of the played log")

    def stop(self) -> None:
        stop(self.proc)


def _ratio_tally(rows) -> dict:
    """The CM_RATIO frames by gate state and how far apart they came (for a failing count)."""
    t = [ts for ts, i, _ in rows if i == _RATIO_ID]
    gates: dict = {}
    for _, i, v in rows:
        if i == _RATIO_ID:
            gates[v["cm_gate"]] = gates.get(v["cm_gate"], 0) + 1
    gaps = sorted((round(b - a, 3) for a, b in itertools.pairwise(t)), reverse=True)[:5]
    return {"gates": gates, "widest_gaps_s": gaps}


def _saved(tmp: Path) -> dict:
    return json.loads((tmp / "state" / "state.json").read_text())["baseline"]


def _coverage_pct(doc: dict) -> float:
    return 100.0 * sum(1 for v in doc["n"] if v >= _MIN_POINTS) / len(doc["n"])


def _cli(*args: str) -> subprocess.CompletedProcess:
    return warm.run(["baseline", *args], timeout=300)


def _learned_h(doc: dict) -> float:
    """Hours learned as the baseline counts them: the operating clock's, saved with it."""
    return doc["clock"]["operating_s"] / 3600.0


def _starts_from(first: dict, doc: dict) -> None:
    """A daemon's first CM_BASELINE says the saved baseline (learned hours to the signal's 0.1 h)."""
    assert first["baseline_state"] == _LEARNING, first
    assert first["baseline_coverage_pct"] == pytest.approx(_coverage_pct(doc), abs=0.5), (first, doc["n"])
    assert first["baseline_learned_h"] == pytest.approx(_learned_h(doc), abs=0.05), (first, doc["clock"])


@pytest.mark.vcan
def test_baseline_learns_across_sigterm_and_kill_9_reaches_monitoring_and_resets(tmp_path_factory):
    t0 = time.monotonic()
    took: list[tuple[str, float]] = []

    def mark(what: str) -> None:
        took.append((what, time.monotonic() - t0 - sum(s for _, s in took)))

    tmp = tmp_path_factory.mktemp("bl")  # short: the notify socket's path has a length limit
    cfg = _baseline_config(tmp)
    db = dbc_for(cfgmod.load(cfg))
    logs = [
        _point_log(tmp / f"point{k}.log", rpm, s, seed=5 + k)
        for k, (rpm, s) in enumerate(zip(_SPEEDS_RPM, _SECONDS, strict=True))
    ]
    mark("logs")
    running: list = []
    try:
        # 1. a fresh daemon starts learning; it learns the first point; SIGTERM
        bus = _Bus(db, tmp / "bus1.log")
        running.append(bus)
        d = Daemon(tmp, cfg, "bl1")
        running.append(d)
        mark("start 1")
        first = bus.wait(lambda r: [v for _, i, v in r if i == _BASELINE_ID], 60, "CM_BASELINE")[0]
        assert first["baseline_state"] == _LEARNING and first["baseline_learned_h"] == 0.0, first
        assert first["baseline_coverage_pct"] == 0.0, first
        player = play(logs[0])
        assert player.wait(timeout=120) == 0, player.stderr.read()
        bus.caught_up()
        d.stop()
        assert d.proc.returncode == 0, d.stderr()
        bus.stop()
        after_term = _saved(tmp)
        learned_1 = after_term["learned_ticks"]
        assert after_term["state"] == "learning" and after_term["n"][0] >= _MIN_POINTS, after_term["n"]
        # every evaluating tick learned, all of it saved at the stop
        assert learned_1 == bus.evaluating() > 0, (learned_1, bus.evaluating(), _ratio_tally(bus.rows()))
        assert all(v["baseline_state"] == _LEARNING for v in bus.baseline())
        mark("play 1, SIGTERM")

        # 2. restarted: it goes on from the saved baseline; kill -9 mid-learning, after a periodic save
        bus = _Bus(db, tmp / "bus2.log")
        running.append(bus)
        d = Daemon(tmp, cfg, "bl2")
        running.append(d)
        mark("start 2")
        first = bus.wait(lambda r: [v for _, i, v in r if i == _BASELINE_ID], 60, "CM_BASELINE")[0]
        _starts_from(first, after_term)
        assert first["baseline_coverage_pct"] > 0
        player = play(logs[1])
        running.append(player)
        deadline = time.monotonic() + 120
        while not (_saved(tmp)["n"][1] >= _MIN_POINTS and _saved(tmp)["learned_ticks"] > learned_1):
            assert d.proc.poll() is None, d.stderr()
            assert time.monotonic() < deadline, "no periodic save with the second point's bin covered"
            time.sleep(0.2)
        d.proc.kill()
        d.proc.wait(timeout=30)
        d.notify.stop = True
        while_playing = player.poll() is None
        player.kill()
        player.wait()
        bus.stop()
        assert d.proc.returncode == -9
        after_kill = _saved(tmp)  # atomically written: the last periodic save, whole
        rows = bus.rows()
        sent = bus.evaluating(rows)
        # what the daemon had learned when it died: the saved ticks it started from and the evaluating
        # ticks it sent since; the state file lost at most those of the last save interval (counted on
        # the bus stamps of its last frames, with a second's slack for a guest that sends in bursts)
        in_memory = learned_1 + sent
        last = rows[-1][0]
        window = bus.evaluating([r for r in rows if r[0] >= last - 2 * _SAVE_EVERY_S - 1.0])
        lost = in_memory - after_kill["learned_ticks"]
        print(
            f"kill -9 {'while canplayer played' if while_playing else 'after the log'}: learned {in_memory} "
            f"ticks, {after_kill['learned_ticks']} saved ({lost} lost; at most {window} allowed)"
        )
        assert after_kill["state"] == "learning"
        assert -1 <= lost <= window, (in_memory, after_kill["learned_ticks"], window)
        assert after_kill["learned_ticks"] > max(learned_1, sent)  # went on from the first daemon's
        mark("play 2, kill -9")

        # 3. restarted again: it goes on from the last save and reaches monitoring on the third point
        bus = _Bus(db, tmp / "bus3.log")
        running.append(bus)
        d = Daemon(tmp, cfg, "bl3")
        running.append(d)
        mark("start 3")
        first = bus.wait(lambda r: [v for _, i, v in r if i == _BASELINE_ID], 60, "CM_BASELINE")[0]
        _starts_from(first, after_kill)
        assert first["baseline_coverage_pct"] == pytest.approx(200 / 3, abs=0.5)
        player = play(logs[2])
        running.append(player)

        def monitoring_from(rows):
            return next(
                (k for k, (_, i, v) in enumerate(rows) if i == _BASELINE_ID and v["baseline_state"] == _MONITORING),
                None,
            )

        bus.wait(lambda r: monitoring_from(r) is not None, 120, "CM_BASELINE in monitoring")
        assert player.wait(timeout=120) == 0, player.stderr.read()
        rows = bus.rows()
        ended = monitoring_from(rows)
        assert all(v["baseline_state"] == _LEARNING for _, i, v in rows[:ended] if i == _BASELINE_ID)
        assert rows[ended][2]["baseline_coverage_pct"] == 100.0
        deadline = time.monotonic() + 30
        while _saved(tmp)["state"] != "monitoring":
            assert time.monotonic() < deadline, "monitoring not saved"
            time.sleep(0.2)
        done = _saved(tmp)
        # the learning went on from the killed daemon's last save up to the tick that ended it: that
        # tick (its CM_RATIO the last before its CM_BASELINE) is judged in the new state, not learned
        end_tick = max(j for j, (_, i, _) in enumerate(rows[:ended]) if i == _RATIO_ID)
        learned_3 = done["learned_ticks"] - after_kill["learned_ticks"]
        assert learned_3 == bus.evaluating(rows[:end_tick]), (done["learned_ticks"], after_kill["learned_ticks"])
        mark("play 3, monitoring")
        # (cmcan baseline status reads this same file: its own tests are on the host, one start less here)

        # 4. a reset beside the running daemon (through its reload): learning again, the old one kept;
        # once the daemon has judged the whole log (a tick still queued would be learned afresh)
        bus.quiet()
        n_before = len(bus.rows())
        r = _cli("reset", "--config", str(cfg), "--reason", "pump replaced", "--wait", "120")
        assert r.returncode == 0, r.stderr
        assert "running daemon" in r.stdout, r.stdout
        again = bus.wait(
            lambda r: [v for _, i, v in r[n_before:] if i == _BASELINE_ID and v["baseline_state"] == _LEARNING],
            30,
            "CM_BASELINE in learning after the reset",
        )[0]
        assert again["baseline_coverage_pct"] == 0.0 and again["baseline_learned_h"] == 0.0, again
        mark("reset")
        r = _cli("show", "--config", str(cfg))
        assert r.returncode == 0, r.stderr
        shown = json.loads(r.stdout)
        assert shown["state"] == "learning" and shown["learned_ticks"] == 0
        old = shown["history"][-1]
        assert old["state"] == "monitoring" and old["reset_reason"] == "pump replaced", old
        # learned hours are operating hours while learning (the clock), at least the learned ticks' time
        assert (
            old["learned_h"] == pytest.approx(_learned_h(done))
            and old["learned_h"] >= done["learned_ticks"] * _H_PER_TICK - 1e-9
        ), (old, done["clock"], done["learned_ticks"])
        assert old["coverage_pct"] == 100.0
        mark("show")
        d.stop()
        assert d.proc.returncode == 0, d.stderr()
        assert "baseline reset (pump replaced)" in d.stderr()
        bus.stop()
        mark("stop")
    finally:
        print("seconds: " + ", ".join(f"{what} {s:.1f}" for what, s in took))
        for p in running:
            if isinstance(p, Daemon):
                if p.proc.poll() is None:
                    p.proc.kill()
                    p.proc.wait()
            elif isinstance(p, _Bus):
                if p.proc.poll() is None:
                    p.stop()
            elif p.poll() is None:
                p.kill()
                p.wait()
