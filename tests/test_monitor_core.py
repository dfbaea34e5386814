"""The monitor core: ticks on frame time, frames out, counters, the same gate as training."""

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from cmcan import config as cfgmod
from cmcan.assemble import dbc_for
from cmcan.model.features import operating_points, series_from_log
from cmcan.monitor.gating import EVALUATED, Gate
from cmcan.monitor.totals import Totals
from cmcan.monitor.warnings import Level
from cmcan.replay import replay_columns
from tests.helpers import as_frames, feed_all, frame, monitor, sim_frames, timeline, write_log

PUMP, PRESS, MOTOR, OIL = 0x100, 0x101, 0x102, 0x103


@pytest.fixture(scope="module")
def short():
    return sim_frames("two_set_validation", duration_h=0.05)


def test_ticks_at_the_evaluation_rate_and_frames_at_their_periods(short):
    _run, frames = short
    mon = monitor()
    out = feed_all(mon, frames)
    n_ticks = mon.counters["ticks"]
    span = frames.timestamp_s[-1] - frames.timestamp_s[0]
    assert abs(n_ticks - span * 10) <= 2
    ids = [f.arbitration_id for f in out]
    assert ids.count(0x3A0) == n_ticks and ids.count(0x3A1) == n_ticks
    assert n_ticks / 10 - 2 <= ids.count(0x3A2) <= n_ticks / 10 + 20  # 1 s period plus changes
    stamps = [f.timestamp_s for f in out]
    assert stamps == sorted(stamps)
    assert mon.counters["frames_total"] == mon.counters["accepted"] == len(frames)


def test_same_input_same_output(short):
    _, frames = short
    assert feed_all(monitor(), frames) == feed_all(monitor(), frames)


def test_core_gates_equal_the_training_features(short, tmp_path):
    """Training and the monitor share the gate: the same windows get the same verdicts and the same
    operating points."""
    _, frames = short
    cfg = cfgmod.load()
    mon = monitor()
    feed_all(mon, frames)
    log = write_log(tmp_path / "r.log", frames)
    mdl = mon.model
    op = operating_points(series_from_log(log, dbc_for(cfg), cfg.signals), cfg.gate_limits, 10.0)
    from cmcan.monitor.gating import gate

    codes = gate(op.stats, cfg.gate_limits, envelope=mon.params.envelope)
    by_t = {round(k.t_s, 3): k for k in timeline(mon)}
    matched = [
        (by_t[round(t, 3)], int(c), op.x[i], op.measured[i])
        for i, (t, c) in enumerate(zip(op.t_s, codes, strict=True))
        if round(t, 3) in by_t
    ]
    assert len(matched) >= len(op.t_s) - 2
    agree = sum(tk.gate == c for tk, c, _, _ in matched)
    assert agree / len(matched) > 0.999
    for tk, c, x, meas in matched:
        if tk.gate in EVALUATED and c == tk.gate:
            assert tk.measured == pytest.approx(meas, rel=1e-9)
            # the tick's operating point is the training's: what a fleet's type model trains on
            assert [tk.pump_speed_rpm, tk.pump_disp_cc, tk.dp_bar, tk.temp_c] == pytest.approx(x, rel=1e-9)
            assert tk.predicted == pytest.approx(mdl.predict(x[None, :])[0][0], rel=1e-6)


def test_bad_frames_are_counted_and_ignored(short):
    _, frames = short
    mon = monitor()
    t0 = float(frames.timestamp_s[0])
    good = bytes(frames.data[0])
    mon.feed(frame(t0, PUMP, good))
    mon.feed(frame(t0 + 0.001, 0x555, good))  # unknown identifier
    mon.feed(frame(t0 + 0.002, PUMP, good[:3]))  # too short
    mon.feed(frame(t0 + 0.003, PUMP, good, extended=True))  # extended id with the same number
    mon.feed(frame(t0 + 0.004, PUMP, good, remote=True))
    mon.feed(frame(t0 + 0.005, 0x20000080, b"", error=True))
    # 16383.75 rpm: beyond the DBC's 8000 rpm (the alive counter in byte 8 moves on, or it would be frozen)
    mon.feed(frame(t0 + 0.006, PUMP, b"\xff\xff" + good[2:7] + bytes([good[7] + 1 & 0x0F | good[7] & 0xF0])))
    mon.feed(frame(t0 + 0.5, PUMP, good))
    mon.feed(frame(t0 + 0.2, PUMP, good))  # older than a tick already evaluated
    c = mon.counters
    assert c == {
        **c,
        "frames_total": 9,
        "accepted": 2,
        "unknown_id": 2,
        "bad_length": 1,
        "remote_frame": 1,
        "error_frame": 1,
        "out_of_range": 1,
        "late": 1,
    }
    assert (
        sum(
            c[k]
            for k in ("accepted", "unknown_id", "bad_length", "out_of_range", "error_frame", "remote_frame", "late")
        )
        == c["frames_total"]
    )


def test_a_gap_skips_ticks_and_keeps_the_time_base(short):
    _, frames = short
    mon = monitor()
    n = len(frames) // 2
    t, ids, data = frames.timestamp_s, frames.arbitration_id, frames.data
    for k in range(n):
        mon.feed(frame(float(t[k]), int(ids[k]), bytes(data[k])))
    ticks_before = mon.counters["ticks"]
    for k in range(n, len(frames)):  # the rest one hour later: the machine was off in between
        mon.feed(frame(float(t[k]) + 3600.0, int(ids[k]), bytes(data[k])))
    mon.flush()
    assert mon.counters["ticks"] - ticks_before < (t[-1] - t[n]) * 10 + 15
    assert mon.counters["clock_steps"] == 0


def test_stale_input_raises_a_fault_and_idle_does_not(short):
    _, frames = short
    cfg = cfgmod.load()
    mon = monitor(cfg=cfg)
    t, ids, data = frames.timestamp_s, frames.arbitration_id, frames.data
    for k in range(len(frames)):
        if ids[k] != OIL:  # the oil temperature sensor is silent
            mon.feed(frame(float(t[k]), int(ids[k]), bytes(data[k])))
    assert mon.machine.level == Level.FAULT
    assert mon.totals.fault_count == 1 and mon.totals.warning_count == 0
    idle = monitor(cfg=cfg)
    for k in range(2000):
        idle.feed(frame(t[k], ids[k], data[k]))
    idle.advance(float(t[2000]) + 600.0)  # bus silent for ten minutes
    assert idle.machine.level == Level.OK and idle.last_tick.gate == Gate.NO_INPUT


def test_totals_round_trip_and_restore_the_condition():
    t = Totals(warning_count=3, condition="low", filter_ratios=[97.0] * 60, filter_leaks=[4.0] * 60)
    back = Totals.from_dict(t.to_dict())
    assert back == t
    mon = monitor(totals=back)
    assert mon.machine.level == Level.LOW and len(mon.filter) == 60


def test_the_core_never_reads_the_clock():
    """Time is data: no module of the core imports time, datetime or calls a clock."""
    core_dir = Path(__file__).resolve().parents[1] / "cmcan" / "monitor"
    for path in core_dir.glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import | ast.ImportFrom):
                names = [a.name for a in node.names] + [getattr(node, "module", "") or ""]
                assert not any(n.split(".")[0] in ("time", "datetime") for n in names), path.name


def test_model_failure_does_not_stop_the_core(short):
    _, frames = short

    class Broken:
        def predict_one(self, *a):
            raise RuntimeError("onnxruntime failed")

    mon = monitor()
    mon.model = Broken()
    feed_all(mon, frames)
    assert mon.counters["model_errors"] > 0 and mon.counters["evaluated"] == 0
    assert math.isfinite(mon.last_tick.ratio_filt_pct)


@pytest.mark.parametrize("nonsense", [math.nan, -5.0, 0.0, math.inf, 1e30])
def test_a_model_returning_nonsense_is_a_model_error_on_the_bus(short, nonsense):
    """Not implausible sensor input (the inputs are fine), not a wear warning (a huge prediction
    would read as a ratio near 0): the tick is MODEL_ERROR and, after fault_after_s, the warning
    frame says fault with reason model_error."""
    from cmcan.monitor.warnings import Reason

    _, frames = short

    class Nonsense:
        def predict_one(self, *a):
            return nonsense, nonsense

    mon = monitor()
    mon.model = Nonsense()
    out = feed_all(mon, frames)
    gates = {k.gate for k in timeline(mon)}
    assert Gate.MODEL_ERROR in gates and Gate.IMPLAUSIBLE_INPUT not in gates
    assert mon.counters["model_errors"] == sum(k.gate == Gate.MODEL_ERROR for k in timeline(mon)) > 0
    assert mon.counters["evaluated"] == 0 and mon.totals.warning_count == 0
    faults = [h for h in mon.totals.history if h["to"] == "fault"]
    assert faults and {h["reason"] for h in faults} == {Reason.MODEL_ERROR.name.lower()}
    assert mon.totals.fault_count == len(faults)
    db = dbc_for(cfgmod.load())
    warning = [db.decode_message(f.arbitration_id, f.data) for f in out if f.arbitration_id == 0x3A2]
    ratio = [db.decode_message(f.arbitration_id, f.data) for f in out if f.arbitration_id == 0x3A0]
    assert ("fault", "model_error") in {(str(w["warning_level"]), str(w["warning_reason"])) for w in warning}
    assert "input_implausible" not in {str(w["warning_reason"]) for w in warning}
    assert "model_error" in {str(r["cm_gate"]) for r in ratio}


def test_leakage_raises_the_low_warning_and_estimates_the_flow():
    # 1.5 h (1.7 M frames) through the replay's columnar engine, which the streaming core's tests hold
    # equal to it frame for frame (test_columnar): a fifth of the time
    run, frames = sim_frames("two_set_validation", duration_h=1.5)
    mon = monitor()
    replay_columns(mon, frames.to_columns(cfgmod.load().bus.channel))
    warns = [(h["t_s"] - run.start_epoch_s) / 3600.0 for h in mon.totals.history if h["to"] == "low"]
    assert len(warns) == 1 and 1.0 < warns[0] < 1.2
    # the per-point estimate (predicted - measured) * V_M against the simulator's truth at the same instants
    late = [k for k in timeline(mon) if k.gate in EVALUATED and (k.t_s - run.start_epoch_s) / 3600 > 1.05]
    est = np.array([(k.predicted - k.measured) * 44.0 / 1000 for k in late])
    idx = np.searchsorted(run["time_s"], [k.t_s - run.start_epoch_s for k in late])
    truth = run["true_extra_leak_lpm"][np.minimum(idx, len(run) - 1)]
    assert np.mean(est) == pytest.approx(np.mean(truth), rel=0.1)
    assert 3.0 < np.mean(truth) < 7.0


def test_a_silent_start_ticks_on_the_idle_clock_and_a_clock_step_before_the_first_frame_is_one():
    """Advanced before any frame (the daemon's idle timer on a silent bus), the monitor ticks with no
    input and sends its frames; frames that then come 5 s earlier than that time (the wall clock set
    back by NTP before the first frame) are a step of the clock, not late frames."""
    _, frames = sim_frames("two_set_validation", duration_h=0.01)
    fs = as_frames(frames)
    t0 = fs[0].timestamp_s
    mon = monitor()
    out = mon.advance(t0 + 5.0)
    for k in range(1, 31):
        out += mon.advance(t0 + 5.0 + 0.1 * k)
    ticks = timeline(mon)
    n_silent = len(ticks)
    assert n_silent in (29, 30) and {tk.gate for tk in ticks} == {Gate.NO_INPUT}  # 3 s at 10 Hz
    assert any(f.arbitration_id == 0x3A2 for f in out)  # the warning frame goes out on a silent bus
    for f in fs:
        mon.feed(f)
    c = mon.counters
    assert c["late"] == 0 and c["clock_steps"] == 1 and c["accepted"] == c["frames_total"]
    assert any(tk.gate in EVALUATED for tk in ticks[n_silent:])
