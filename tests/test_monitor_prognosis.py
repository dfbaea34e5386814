"""The prognosis stage inside the monitor: both engines alike, no trend on the healthy stretch, the
hours to end of life before the paper's motor wear failure, restarted after the replacement."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from cmcan import config as cfgmod
from cmcan.assemble import assemble
from cmcan.can.frame import FrameColumns
from cmcan.demo import scale_windows
from cmcan.monitor.totals import Totals
from cmcan.replay import FrameCollector, TimelineCollector, replay, replay_columns
from tests.helpers import as_frames, sim_frames


def _cfg() -> cfgmod.Config:
    cfg = scale_windows(cfgmod.load(), 2.0, 60.0)  # the filter and debounce for the time-lapse, as the demo
    # the rig loses function at 40 l/min of wear leakage at 480 bar and 60 C: its known end of life
    p = cfgmod.PrognosisConfig.on(eol_kind="leak_lpm", eol_value=40.0)
    return dataclasses.replace(cfg, prognosis=p)


@pytest.fixture(scope="module")
def rig():
    """The paper's run to failure up to after the motor's replacement (290.5 h), 2 s every hour."""
    run, frames = sim_frames(
        "run_to_failure", duration_h=300.0, sampling={"mode": "bursts", "burst_s": 2.0, "every_min": 60.0}
    )
    return run, as_frames(frames)


def _run(cfg, frames, engine: str, chunk: int = 4099):
    mon = assemble(cfg).monitor
    tl, fr = TimelineCollector(), FrameCollector()
    if engine == "streaming":
        replay(mon, frames, [tl, fr])
    else:
        chunks = [FrameColumns.from_frames(frames[i : i + chunk]) for i in range(0, len(frames), chunk)]
        replay_columns(mon, chunks, [tl, fr])
    return tl.timeline, fr.frames_out, mon


@pytest.fixture(scope="module")
def rig_replays(rig):
    """Both engines over the whole ``rig``, once for the tests that read them (and change nothing)."""
    _, frames = rig
    cfg = _cfg()
    return _run(cfg, frames, "streaming"), _run(cfg, frames, "columnar")


def test_both_engines_alike_and_the_estimate_before_the_motor_wear_failure(rig, rig_replays):
    run, _frames = rig
    a, b = rig_replays
    for name in a[0].__dataclass_fields__:
        assert np.array_equal(getattr(a[0], name), getattr(b[0], name), equal_nan=True), name
    assert a[1] == b[1]
    assert json.dumps(a[2].save_totals().to_dict()) == json.dumps(b[2].save_totals().to_dict())
    tl = a[0]
    hours = (tl.t_s - run.start_epoch_s) / 3600.0
    healthy = hours < 200.0
    assert np.all(tl.prognosis_state[healthy] == 1)  # none: no trend invented on the healthy drive
    fail_h = 290.0
    near = (hours > fail_h - 11.0) & (hours < fail_h - 9.0)
    assert near.any() and np.all(tl.prognosis_state[near] >= 2)
    p50 = float(np.median(tl.prognosis_to_eol_p50_h[near]))
    assert abs(p50 - 10.0) <= 0.2 * 10.0 + 1.0, p50
    # the motor replaced at 290.5 h: once its low warning clears, a new history without a trend
    cleared = np.flatnonzero((hours > fail_h) & (tl.level == 0))
    assert len(cleared)
    after = np.arange(len(hours)) >= cleared[0]
    assert np.all(tl.prognosis_state[after] == 1)
    assert np.all(np.isnan(tl.prognosis_to_eol_p50_h[after]))


def test_the_hours_are_operating_hours_a_night_parked_counts_nothing(rig):
    """The machine parked for 12 h at 260 h, in the middle of the motor's wear (no frames): the
    operating clock skips the night, and the estimate 10 h before the failure (at 290 operating hours)
    is the truth's, not 12 h longer; both engines alike."""
    run, frames = rig
    park_s, at_s = 12 * 3600.0, run.start_epoch_s + 260.5 * 3600.0
    parked = [f._replace(timestamp_s=f.timestamp_s + park_s) if f.timestamp_s > at_s else f for f in frames]
    cfg = _cfg()
    a = _run(cfg, parked, "streaming")
    b = _run(cfg, parked, "columnar")
    for name in a[0].__dataclass_fields__:
        assert np.array_equal(getattr(a[0], name), getattr(b[0], name), equal_nan=True), name
    tl, mon = a[0], a[2]
    op_h = (tl.t_s - run.start_epoch_s - np.where(tl.t_s > at_s, park_s, 0.0)) / 3600.0
    # the clock: the hours since the first tick less the night and the one sampled hour it swallowed
    clock_h = mon.prognosis.clock.operating_s / 3600.0
    assert clock_h == pytest.approx(op_h[-1] - op_h[0] - 1.0, abs=0.01), (clock_h, op_h[-1])
    near = (op_h > 279.0) & (op_h < 281.0)
    assert near.any() and np.all(tl.prognosis_state[near] >= 2)
    p50 = float(np.median(tl.prognosis_to_eol_p50_h[near]))
    assert abs(p50 - 10.0) <= 0.2 * 10.0 + 1.0, p50  # 22 h were it calendar hours


def test_a_silent_bus_adds_no_operating_hours():
    """The daemon's ticks on a silent bus (Monitor.advance: no input) move no clock: a replay of its
    log, which has no ticks there, counts the same."""
    mon = assemble(_cfg()).monitor
    t0 = 1.7e9
    for k in range(1, 1201):  # 20 minutes, 12,000 ticks
        mon.advance(t0 + k)
    assert mon.prognosis.clock.operating_s == 0.0 and mon.last_tick.gate == 1  # no input


@pytest.mark.parametrize(
    ("before", "ratio", "restart"),
    [
        (1, 98.4, False),
        (1, 99.2, True),
        (2, 101.6, False),
        (2, 100.4, True),
        (1, float("nan"), False),
        (0, 100.0, False),
    ],
)
def test_a_warning_clearing_restarts_the_history_only_with_the_ratio_back_near_100(before, ratio, restart):
    """Replaced (the ratio near 100 % again) or a flicker at the band's edge (the history goes on)."""
    from cmcan.monitor.core import _replaced
    from cmcan.monitor.warnings import Thresholds

    th = Thresholds()
    assert bool(_replaced(before, 0, ratio, th)) is restart
    assert _replaced(np.array([before]), np.array([0]), np.array([ratio]), th).tolist() == [restart]


def test_a_misposition_is_a_high_trend_in_both_engines_and_ends_with_the_replacement():
    """The motor's displacement control drifts 10 % short from 40 h until it fails at 60 h (the paper's
    misposition, earlier): the trend is on the high side, the hours to its end of life (the ratio at
    which it fails, 111 %) 10 h before within 20 %; the replacement at 61 h clears it."""
    from cmcan.demo import misposition_eol_pct

    events = [
        {"type": "misposition", "mode": "drift", "start_h": 40, "end_h": 60, "pct": -10, "fail_h": 60},
        {"type": "replace", "component": "motor", "at_h": 61},
    ]
    sampling = {"mode": "bursts", "burst_s": 2.0, "every_min": 20.0}
    run, frames = sim_frames("run_to_failure", duration_h=70.0, events=events, sampling=sampling)
    frames = as_frames(frames)
    cfg = scale_windows(cfgmod.load(), 2.0, 20.0)
    p = cfgmod.PrognosisConfig.on(eol_high_pct=misposition_eol_pct(events))
    cfg = dataclasses.replace(cfg, prognosis=p)
    a = _run(cfg, frames, "streaming")
    b = _run(cfg, frames, "columnar")
    for name in a[0].__dataclass_fields__:
        assert np.array_equal(getattr(a[0], name), getattr(b[0], name), equal_nan=True), name
    assert a[1] == b[1]
    tl = a[0]
    hours = (tl.t_s - run.start_epoch_s) / 3600.0
    assert np.all(tl.prognosis_state[hours < 40.0] == 1)
    near = (hours > 49.0) & (hours < 51.0)
    assert near.any() and np.all(tl.prognosis_state[near] >= 2) and np.all(tl.prognosis_direction[near] == 2)
    p50 = float(np.median(tl.prognosis_to_eol_p50_h[near]))
    assert abs(p50 - 10.0) <= 0.2 * 10.0, p50
    cleared = np.flatnonzero((hours > 60.0) & (tl.level == 0))
    assert len(cleared)
    after = np.arange(len(hours)) >= cleared[0]
    assert np.all(tl.prognosis_state[after] == 1) and np.all(tl.prognosis_direction[after] == 0)


def test_the_history_survives_a_restart(rig):
    _, frames = rig
    cfg = _cfg()
    *_, mon = _run(cfg, frames[: len(frames) * 9 // 10], "columnar")
    saved = json.loads(json.dumps(mon.save_totals().to_dict()))
    assert saved["prognosis"]["points"]
    again = assemble(cfg, totals=Totals.from_dict(saved)).monitor
    assert again.prognosis.history.points == mon.prognosis.history.points
    snap = again.snapshot()["prognosis"]
    assert snap["state"] in ("trend", "imminent") and snap["history_points"] == len(mon.prognosis.history.points)
    assert all(v is None or v == "never" or (isinstance(v, float) and math.isfinite(v)) for v in snap["to_eol_h"])


def test_cm_prognosis_carries_the_estimate_decoded_from_the_dbc(rig_replays):
    import cantools

    from tests.conftest import ROOT

    db = cantools.database.load_file(str(ROOT / "dbc" / "cmcan.dbc"))
    msg = db.get_message_by_name("CM_PROGNOSIS")
    tl, out, _ = rig_replays[1]  # the columnar engine's
    sent = [f for f in out if f.arbitration_id == msg.frame_id]
    assert sent
    by_t = {round(t, 3): i for i, t in enumerate(tl.t_s)}
    for f in sent:
        d = msg.decode(f.data, decode_choices=False)
        i = by_t[round(f.timestamp_s, 3)]
        assert d["prognosis_state"] == tl.prognosis_state[i]
        assert d["prognosis_direction"] == tl.prognosis_direction[i]
        p50 = tl.prognosis_to_eol_p50_h[i]
        assert d["prognosis_to_eol_p50_h"] == pytest.approx(0.0 if np.isnan(p50) else min(p50, 4000.0), abs=0.25)
    states = [msg.decode(f.data)["prognosis_state"] for f in sent]
    assert {str(s) for s in states} >= {"none", "trend", "imminent"}


def test_the_uplink_summaries_carry_the_prognosis():
    from cmcan.monitor.gating import Gate
    from cmcan.monitor.tick import Tick
    from cmcan.monitor.warnings import Level, Reason
    from cmcan.uplink.feed import _sample
    from cmcan.uplink.records import Cumulative, SummaryBuilder

    def tick(t: float, state: int, p50: float) -> Tick:
        return Tick(
            t_s=t, gate=Gate.EVALUATING, measured=1.0, predicted=1.0, whitebox=1.0, ratio_raw_pct=100.0,
            ratio_filt_pct=100.0, extra_leak_lpm=0.0, filt_valid=True, level=Level.OK, reason=Reason.NONE,
            time_below_s=0.0, prognosis_state=state, prognosis_direction=1 if state > 1 else 0,
            prognosis_to_warning_h=math.nan,
            prognosis_to_eol_p10_h=p50 - 2, prognosis_to_eol_p50_h=p50, prognosis_to_eol_p90_h=math.inf,
        )  # fmt: skip

    cum = Cumulative({}, 0.0, 0, 0, {})
    sb = SummaryBuilder(60.0, cum)
    sb.add(_sample(tick(10.0, 2, 30.0)), cum)
    (entry,) = sb.add(_sample(tick(70.0, 3, 20.0)), cum)
    body = entry.body
    want = {"state": "trend", "direction": "low", "to_warning_h": None, "to_eol_h": [28.0, 30.0, "never"]}
    assert body["prognosis"] == want
    assert _sample(tick(80.0, 0, math.nan)).prognosis is None  # not configured: no key


def test_the_high_end_of_life_is_configured_and_checked():
    from cmcan.assemble import prognosis_params
    from cmcan.schema import SchemaError, load_yaml

    path = cfgmod.default_config_path()

    def config(prognosis):
        return cfgmod.from_dict({**load_yaml(path), "prognosis": prognosis}, str(path), path.parent)

    cfg = config({"enabled": True, "end_of_life": {"high_pct": 112.5}})
    params = prognosis_params(cfg)
    assert params is not None and params.eol_high_pct == 112.5 and params.high_pct == cfg.thresholds.high_pct
    assert prognosis_params(config({"enabled": True})).eol_high_pct == 110.0  # the documented default
    with pytest.raises(SchemaError, match=r"prognosis\.end_of_life\.high_pct.*thresholds\.high_pct"):
        config({"enabled": True, "end_of_life": {"high_pct": 101.5}})
    raw = {**load_yaml(path), "prognosis": {"enabled": True}}
    raw["thresholds"] = {**raw.get("thresholds", {}), "low_pct": 99.0, "high_pct": 100.0, "hysteresis_pct": 0.2}
    with pytest.raises(SchemaError, match=r"thresholds\.high_pct.*band around 100"):
        cfgmod.from_dict(raw, str(path), path.parent)
