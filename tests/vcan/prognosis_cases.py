"""The prognosis (issue 30, docs/prognosis.md) on a real SocketCAN bus (vcan0): the daemon (``cmcan
run``) sends CM_PROGNOSIS, decoded with cantools from the repository's DBC, and its estimate survives a
SIGTERM and a restart. Collected into ``cases`` (one VM for all).

An estimate needs hours of operation with a wear trend, more than a test can play. So the history is
made by the real core before the daemon starts: a short simulated wear run (bursts of a few seconds
every operating hour, the motor wearing) replayed through the monitor assembled from the daemon's own
configuration, its totals saved into the daemon's state directory by the daemon's ``StateStore``.
The run ends at the present: the stage's operating clock adds the time between ticks (up to
``max_gap_h``), and the daemon's ticks are stamped with this machine's clock.

The log canplayer plays is the machine idling (the pump below its minimum speed): ticks, and
CM_PROGNOSIS with them, but none the gate evaluates, so none adds to the history. Then the history
the daemon saves at its stop is the one it started from, and the estimate each daemon sends is the
one the core makes from it, less the hours since its last point, counted on the frames' stamps (the
ticks' own time base), never on the wall clock of the test. Only ``prognosis_state`` and the hours to
end of life (``prognosis_to_eol_p10_h`` / ``_p50_h`` / ``_p90_h``) are read, by name, and the frame's
layout is not asserted.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import pytest
import yaml

from tests.vcan.cases import ROOT, Daemon, candump, make_config, play, stop

# cases imports this module at its end: the names above are defined by then. The core's modules
# are imported in the test, not here: collecting the other cases pays nothing for this one.

_HISTORY_H = 36.0  # the simulated wear run: operating hours, one burst of _BURST_S every hour
_BURST_S = 3.0
_WEAR = {"type": "wear", "component": "motor", "start_h": 4.0, "fail_h": 70.0, "fail_extra_lpm": 40.0}
_PROGNOSIS = {"enabled": True, "end_of_life": {"kind": "leak_lpm", "value": 40.0}}
_HOURS = ("prognosis_to_eol_p10_h", "prognosis_to_eol_p50_h", "prognosis_to_eol_p90_h")
_SPAN_H = 4000.0  # the hours are saturated here (and sent as this where the curve never gets there)
_RESOLUTION_H = 0.5
_EVALUATED = (0, 6)  # cm_gate evaluating, extrapolated
_IDLE_S = 8.0


def _prognosis_config(tmp: Path) -> Path:
    p = make_config(tmp)
    raw = yaml.safe_load(p.read_text())
    raw["prognosis"] = _PROGNOSIS
    p.write_text(yaml.safe_dump(raw))
    return p


def _scenario(name: str, duration_h: float, start_epoch_s: float, rpm: float, dp_bar: float, **over):
    from cmcan.sim import scenario as scn

    return scn.from_dict(
        {
            "name": name,
            "seed": 11,
            "duration_h": duration_h,
            "start_epoch_s": start_epoch_s,
            "oil": {"model": "prescribed", "temp_c": 60.0},
            "duty": {"kind": "constant", "pump_speed_rpm": rpm, "pump_disp_pct": 100, "dp_bar": dp_bar},
            **over,
        }
    )


def _save_worn_history(cfg_path: Path, state_dir: Path) -> dict:
    """The simulated wear run through the monitor the daemon's configuration assembles, its totals
    saved as the daemon saves them; ending now. Returns the saved document."""
    from cmcan import config as cfgmod
    from cmcan.assemble import assemble, dbc_for
    from cmcan.can.frame import FrameColumns
    from cmcan.io.candump import iter_frames, write_candump
    from cmcan.replay import replay_columns
    from cmcan.service.statefile import StateStore
    from cmcan.sim.frames import frames_from_run
    from cmcan.sim.run import simulate

    cfg = cfgmod.load(cfg_path)
    db = dbc_for(cfg)
    s = _scenario(
        "vcan-wear",
        _HISTORY_H,
        # its last burst (one each hour from the start) ends now: the daemon's first tick, a minute
        # on, continues its operating clock (a gap over max_gap_h would be the machine off)
        time.time() - (_HISTORY_H - 1.0) * 3600.0 - _BURST_S,
        3000.0,
        480.0,
        sampling={"mode": "bursts", "burst_s": _BURST_S, "every_min": 60.0},
        events=[_WEAR],
    )
    f = frames_from_run(simulate(s, db), db)
    log = state_dir.parent / "wear.log"
    write_candump(log, f.timestamp_s, f.arbitration_id, f.dlc, f.data, channel="can0")
    frames = list(iter_frames(log))
    mon = assemble(cfg).monitor
    replay_columns(mon, [FrameColumns.from_frames(frames[k : k + 4096]) for k in range(0, len(frames), 4096)])
    store = StateStore(cfg.state.directory)
    store.save(mon.save_totals())
    return json.loads(store.path.read_text())


def _estimate(cfg_path: Path, saved: dict):
    """What the daemon's stage estimates at its start from a saved history."""
    from cmcan import config as cfgmod
    from cmcan.assemble import prognosis_params
    from cmcan.monitor.prognosis import Stage

    return Stage(prognosis_params(cfgmod.load(cfg_path)), saved["prognosis"]).est


def _idle_log(path: Path) -> Path:
    """The machine idling: the pump at 500 rpm, below the gate's minimum (700 rpm)."""
    from cmcan import config as cfgmod
    from cmcan.assemble import dbc_for
    from cmcan.io.candump import write_candump
    from cmcan.sim.frames import frames_from_run
    from cmcan.sim.run import simulate

    s = _scenario("vcan-idle", _IDLE_S / 3600.0, 1767225600.0, 500.0, 40.0, events=[])
    db = dbc_for(cfgmod.load())
    f = frames_from_run(simulate(s, db), db)
    write_candump(path, f.timestamp_s, f.arbitration_id, f.dlc, f.data, channel="can0")
    return path


class _Bus:
    """A candump recording of cmcan's frames, CM_PROGNOSIS and CM_RATIO decoded by name."""

    def __init__(self, db, path: Path) -> None:
        self.path = path
        self.prognosis = db.get_message_by_name("CM_PROGNOSIS")
        self.ratio = db.get_message_by_name("CM_RATIO")
        self.proc = candump(path)
        time.sleep(0.5)

    def rows(self) -> tuple[list[tuple[float, dict]], list[int]]:
        """(bus stamp, CM_PROGNOSIS decoded) in order, and each CM_RATIO's gate."""
        text = self.path.read_text() if self.path.exists() else ""
        progn, gates = [], []
        for line in text[: text.rfind("\n") + 1].splitlines():  # complete lines only
            stamp, _, frame = line.split()
            ident, data = frame.split("#", 1)
            i, d = int(ident, 16), bytes.fromhex(data)
            if i == self.prognosis.frame_id:
                progn.append((float(stamp.strip("()")), self.prognosis.decode(d, decode_choices=False)))
            elif i == self.ratio.frame_id:
                gates.append(int(self.ratio.decode(d, decode_choices=False)["cm_gate"]))
        return progn, gates

    def wait(self, pred, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            got = pred(*self.rows())
            if got:
                return got
            time.sleep(0.2)
        raise AssertionError(f"{what}: not seen within {timeout:g} s in {self.path.name}")

    def stop(self) -> None:
        stop(self.proc)


def _history(state: dict) -> dict:
    """The saved prognosis without its operating clock."""
    return {k: v for k, v in state["prognosis"].items() if k != "clock"}


def _expected(est, clock: dict, stamp_s: float) -> dict[str, float]:
    """The estimate's hours at ``stamp_s`` (a tick's time), as sent: less the operating hours since its
    last history point, the saved operating clock gone on by the time since its last tick (every gap
    here is far under prognosis.max_gap_h)."""
    since = (clock["operating_s"] + stamp_s - clock["last_t_s"]) / 3600.0 - est.at_h
    return {
        name: min(max(v - since, 0.0), _SPAN_H) if math.isfinite(v) else _SPAN_H
        for name, v in zip(_HOURS, est.to_eol_h, strict=True)
    }


def _carries(est, clock: dict, rows: list[tuple[float, dict]], code: int) -> None:
    """Every CM_PROGNOSIS frame says the estimate: its state, and its hours less the hours since its
    last point (to the bus stamp: the ticks' own time base), within the signal's resolution."""
    assert rows
    for t, v in rows:
        assert v["prognosis_state"] == code, (t, v)
        want = _expected(est, clock, t)
        got = [v[name] for name in _HOURS]
        assert got == sorted(got), v
        for name in _HOURS:
            assert v[name] == pytest.approx(want[name], abs=_RESOLUTION_H + 0.01), (name, v, want)


@pytest.mark.vcan
def test_prognosis_frame_decoded_from_the_dbc_survives_a_restart(tmp_path_factory):
    import cantools

    from cmcan.monitor.prognosis import STATE_CODES, TREND

    t0 = time.monotonic()
    took: list[tuple[str, float]] = []

    def mark(what: str) -> None:
        took.append((what, time.monotonic() - t0 - sum(s for _, s in took)))

    tmp = tmp_path_factory.mktemp("pg")  # short: the notify socket's path has a length limit
    cfg = _prognosis_config(tmp)
    (tmp / "state").mkdir()
    saved = _save_worn_history(cfg, tmp / "state")
    est = _estimate(cfg, saved)
    log = _idle_log(tmp / "idle.log")
    db = cantools.database.load_file(str(ROOT / "dbc" / "cmcan.dbc"))
    mark("history, log")
    code = STATE_CODES[est.state]
    p10, p50, p90 = est.to_eol_h
    print(
        f"the core's estimate from {len(saved['prognosis']['points'])} history points: {est.state}, "
        f"{p10:.1f} / {p50:.1f} / {p90:.1f} h to end of life at the last point (rise {est.rise_lpm:.1f} l/min)"
    )
    assert code >= STATE_CODES[TREND], est
    assert all(math.isfinite(x) for x in est.to_eol_h) and 0.0 < p10 <= p50 <= p90 < _SPAN_H, est
    running: list = []
    try:
        # 1. the daemon starts from the saved history; the idle machine's ticks carry its estimate
        bus = _Bus(db, tmp / "bus1.log")
        running.append(bus)
        d = Daemon(tmp, cfg, "pg1")
        running.append(d)
        mark("start 1")
        bus.wait(lambda p, g: p, 60, "CM_PROGNOSIS")
        player = play(log)
        running.append(player)
        assert player.wait(timeout=120) == 0, player.stderr.read()
        # the log's ticks went out (the gate says the pump is too slow), and CM_PROGNOSIS after them
        n_before = len(bus.rows()[0])
        bus.wait(lambda p, g: g.count(4) >= 20 and len(p) >= n_before + 2, 60, "the log's ticks")
        d.stop()
        assert d.proc.returncode == 0, d.stderr()
        bus.stop()
        first, gates = bus.rows()
        assert not any(g in _EVALUATED for g in gates), gates  # nothing for the history from the bus
        clock = saved["prognosis"]["clock"]
        _carries(est, clock, first, code)
        mark("play, SIGTERM")

        # 2. the history the daemon saved at its stop is the one it started from
        after = json.loads((tmp / "state" / "state.json").read_text())
        assert _history(after) == _history(saved)
        # the operating clock went on by the daemon's ticks (the idling machine runs), nothing else
        c0, c1 = clock, after["prognosis"]["clock"]
        assert c1["operating_s"] - c0["operating_s"] == pytest.approx(c1["last_t_s"] - c0["last_t_s"], abs=1e-3)
        assert after["prognosis"]["points"] and after["condition"] == saved["condition"]

        # 3. restarted: its first frames carry the same state and hours, less the hours since
        bus = _Bus(db, tmp / "bus2.log")
        running.append(bus)
        d = Daemon(tmp, cfg, "pg2")
        running.append(d)
        mark("start 2")
        again = bus.wait(lambda p, g: p if len(p) >= 3 else None, 60, "CM_PROGNOSIS after the restart")
        d.stop()
        assert d.proc.returncode == 0, d.stderr()
        bus.stop()
        kept = _estimate(cfg, json.loads((tmp / "state" / "state.json").read_text()))
        assert (kept.state, kept.at_h, kept.to_eol_h) == (est.state, est.at_h, est.to_eol_h)
        _carries(est, clock, again, code)
        (t1, last), (t2, next_) = first[-1], again[0]
        for name in _HOURS:  # the same, less the hours between the two frames
            assert next_[name] == pytest.approx(max(last[name] - (t2 - t1) / 3600.0, 0.0), abs=_RESOLUTION_H + 0.01)
        print(
            f"CM_PROGNOSIS: {len(first)} frames before the stop, {len(again)} after the restart; the last "
            f"before {[last[n] for n in _HOURS]} h, the first after {[next_[n] for n in _HOURS]} h "
            f"({t2 - t1:.1f} s later)"
        )
        mark("restart, SIGTERM")
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
