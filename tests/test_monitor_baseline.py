"""The on-board baseline inside the monitor: both engines alike, learning to monitoring on a unit that
differs from its type, the state across a restart, a reset."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from cmcan import config as cfgmod
from cmcan.assemble import assemble
from cmcan.can.frame import FrameColumns
from cmcan.monitor.baseline import Mode
from cmcan.monitor.warnings import Level
from cmcan.replay import FrameCollector, TimelineCollector, replay, replay_columns
from tests.helpers import as_frames, sim_frames


def _cfg(**over) -> cfgmod.Config:
    cfg = cfgmod.load()
    b = cfgmod.BaselineConfig.on(min_points=40, coverage_pct=20.0, min_hours=0.02, **over)
    return dataclasses.replace(cfg, baseline=b)


@pytest.fixture(scope="module")
def unit():
    """A unit whose motor speed sensor reads 1.5 % high: the type model sees a ratio near 101.5 %."""
    sensors = {"errors": {"motor_speed_rpm": {"gain_pct": 1.5}}}
    _, frames = sim_frames("two_set_validation", duration_h=0.12, sensors=sensors)
    return as_frames(frames)


def _run(cfg, frames, engine: str, chunk: int = 997):
    mon = assemble(cfg).monitor
    tl, fr = TimelineCollector(), FrameCollector()
    if engine == "streaming":
        s = replay(mon, frames, [tl, fr])
    else:
        chunks = [FrameColumns.from_frames(frames[i : i + chunk]) for i in range(0, len(frames), chunk)]
        s = replay_columns(mon, chunks, [tl, fr])
    return tl.timeline, fr.frames_out, s, mon


def test_both_engines_learn_alike_and_the_unit_is_judged_against_its_own_baseline(unit):
    cfg = _cfg()
    a = _run(cfg, unit, "streaming")
    b = _run(cfg, unit, "columnar")
    for name in a[0].__dataclass_fields__:
        assert np.array_equal(getattr(a[0], name), getattr(b[0], name), equal_nan=True), name
    assert a[1] == b[1]
    assert json.dumps(a[3].baseline.to_dict()) == json.dumps(b[3].baseline.to_dict())
    tl, mon = a[0], a[3]
    assert mon.baseline.mode == Mode.MONITORING
    states = tl.baseline_state
    assert states[0] == Mode.LEARNING and states[-1] == Mode.MONITORING
    assert np.all(np.diff(states.astype(int)) >= 0)  # learning, then monitoring, once
    ev = tl.filt_valid
    learning, monitoring = ev & (states == Mode.LEARNING), ev & (states == Mode.MONITORING)
    assert learning.any() and monitoring.any()
    # against the type model the unit reads high; against its own baseline it is healthy
    assert np.median(tl.ratio_filt_pct[learning]) > 101.0
    assert abs(np.median(tl.ratio_filt_pct[monitoring]) - 100.0) < 0.4
    assert not np.any(tl.level[monitoring] != Level.OK)
    assert mon.snapshot()["baseline"]["state"] == "monitoring"


def test_the_baseline_survives_a_restart_and_a_reset_learns_afresh(unit):
    cfg = _cfg()
    *_, mon = _run(cfg, unit[: len(unit) // 2], "columnar")
    saved = json.loads(json.dumps(mon.save_totals().to_dict()))
    assert saved["baseline"]["state"] in ("learning", "monitoring")
    from cmcan.monitor.totals import Totals

    again = assemble(cfg, totals=Totals.from_dict(saved)).monitor
    assert again.baseline.to_dict() == mon.baseline.to_dict()
    assert again.reset_baseline("pump replaced", "2026-11-27T18:00:00Z")
    assert again.baseline.mode == Mode.LEARNING and again.baseline.learned_ticks == 0
    assert again.baseline.history[-1]["reset_reason"] == "pump replaced"
    assert again.machine.th.low_pct == cfg.baseline.settings.learning_low_pct


def test_a_unit_arriving_with_a_leak_is_suspect_and_warns(unit):
    leak = {"type": "leakage", "start_h": 0.0, "extra_lpm": 12.0, "ref_dp_bar": 300}
    _, frames = sim_frames("two_set_validation", duration_h=0.12, events=[leak])
    *_, mon = _run(_cfg(suspect_lpm=3.0), as_frames(frames), "columnar")
    assert mon.baseline.mode == Mode.SUSPECT
    assert mon.baseline.distance_lpm < -3.0
    assert mon.snapshot()["baseline"]["state"] == "baseline_suspect"


def test_a_leak_a_unit_reading_high_hides_in_the_mean_is_suspect_by_its_pressure_part():
    # the motor speed sensor reads 4 % high (the flow part), an orifice leak of 6 l/min at 480 bar: every
    # bin's mean within the allowance, what the baseline learned less its flow part beyond it
    leak = {"type": "leakage", "start_h": 0.0, "extra_lpm": 6.0, "ref_dp_bar": 480}
    sensors = {"errors": {"motor_speed_rpm": {"gain_pct": 4.0}}}
    _, frames = sim_frames("two_set_validation", duration_h=0.12, events=[leak], sensors=sensors)
    cfg = _cfg(suspect_lpm=3.5)
    a, b = (_run(cfg, as_frames(frames), engine)[3].baseline for engine in ("streaming", "columnar"))
    assert json.dumps(a.to_dict()) == json.dumps(b.to_dict())
    assert a.mode == Mode.SUSPECT and a.suspect_by == ("pressure",)
    assert abs(a.distance_lpm) < 3.5 < -a.pressure_part_lpm


def test_cm_baseline_goes_on_the_bus_on_each_change_and_every_second(unit):
    import cantools

    from tests.conftest import ROOT

    db = cantools.database.load_file(str(ROOT / "dbc" / "cmcan.dbc"))
    msg = db.get_message_by_name("CM_BASELINE")
    tl, frames, _, mon = _run(_cfg(), unit, "columnar")
    sent = [f for f in frames if f.arbitration_id == msg.frame_id]
    decoded = [msg.decode(f.data, decode_choices=False) for f in sent]
    states = [d["baseline_state"] for d in decoded]
    assert states[0] == Mode.LEARNING and states[-1] == Mode.MONITORING
    first_monitoring = states.index(Mode.MONITORING)
    # the change goes at once: at the tick the learning ended, not up to a second later
    ended = int(np.flatnonzero(tl.baseline_state == Mode.MONITORING)[0])
    assert sent[first_monitoring].timestamp_s == pytest.approx(tl.t_s[ended])
    gaps = np.diff([f.timestamp_s for f in sent])
    assert gaps.max() <= 1.0 + 1e-6
    learned = [d["baseline_learned_h"] for d in decoded]
    assert learned == sorted(learned) and learned[-1] == pytest.approx(mon.baseline.learned_h, abs=0.05)
    assert decoded[-1]["baseline_coverage_pct"] == pytest.approx(mon.baseline.coverage_pct, abs=0.5)
    assert decoded[-1]["baseline_distance_lpm"] == pytest.approx(mon.baseline.distance_lpm, abs=0.01)
    # without the baseline section nothing of it is sent
    _, plain, _, _ = _run(cfgmod.load(), unit[:20000], "columnar")
    assert not any(f.arbitration_id == msg.frame_id for f in plain)
