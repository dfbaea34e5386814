"""Reverse travel on a machine whose bus sends signed values is normal operation, never a fault.

The drive is judged in its forward direction (the one its model is trained in). A machine that sends
a signed motor speed and a signed pump displacement (swash plate over centre) reverses: those ticks
are ``REVERSE``, with no ratio and no fault however long the machine reverses, in both replay
engines alike; the ratio is evaluated before and after.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cmcan import config as cfgmod
from cmcan.assemble import assemble, dbc_for
from cmcan.can.frame import FrameColumns
from cmcan.io.candump import write_candump
from cmcan.monitor.gating import EVALUATED, Gate
from cmcan.monitor.warnings import Level
from cmcan.replay import FrameCollector, TimelineCollector, replay, replay_columns
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run
from cmcan.sim.run import simulate
from tests.conftest import ROOT, run_cli
from tests.test_columnar import assert_same

DURATION_H = 0.1  # 360 s: steady points before, during and after the reverse stretch
REVERSE_S = (100.0, 260.0)  # operating seconds of reverse travel: far longer than fault_after_s


@pytest.fixture(scope="module")
def signed_config(tmp_path_factory) -> Path:
    """The shipped configuration on a copy of the shipped DBC whose motor speed is signed (the pump
    displacement already is): a machine that sends its direction in the signs."""
    d = tmp_path_factory.mktemp("signed")
    text = (ROOT / "dbc" / "cmcan.dbc").read_text()
    old = ' SG_ motor_speed_rpm : 0|16@1+ (0.25,0) [0|10000] "rpm"'
    assert old in text
    (d / "signed.dbc").write_text(text.replace(old, ' SG_ motor_speed_rpm : 0|16@1- (0.25,0) [-8000|8000] "rpm"'))
    cfg = (ROOT / "config" / "cmcan.yaml").read_text()
    assert "dbc: ../dbc/cmcan.dbc" in cfg and "directory: /var/lib/cmcan" in cfg
    cfg = cfg.replace("dbc: ../dbc/cmcan.dbc", "dbc: signed.dbc").replace(
        "directory: /var/lib/cmcan", "directory: state"
    )
    (d / "cmcan.yaml").write_text(cfg)
    return d / "cmcan.yaml"


@pytest.fixture(scope="module")
def healthy_run(signed_config):
    cfg = cfgmod.load(signed_config)
    s = scn.load(scn.shipped("two_set_validation")).with_overrides(duration_h=DURATION_H)
    return cfg, simulate(s, dbc_for(cfg))


def reversed_frames(cfg, run, roles: tuple[str, ...]):
    """The run's frames through the signed DBC, ``roles`` negated over the reverse stretch."""
    t = run["time_s"]
    back = (t >= REVERSE_S[0]) & (t < REVERSE_S[1])
    cols = dict(run.columns)
    for r in roles:
        cols[r] = np.where(back, -cols[r], cols[r])
    return frames_from_run(replace(run, columns=cols), dbc_for(cfg))


def both_engines(cfg, frames):
    frames_in = frames.to_frames()
    out = {}
    for engine in ("streaming", "columnar"):
        mon = assemble(cfg).monitor
        tl, fr = TimelineCollector(), FrameCollector()
        if engine == "streaming":
            s = replay(mon, frames_in, [tl, fr])
        else:
            chunk = 5000
            chunks = [FrameColumns.from_frames(frames_in[i : i + chunk]) for i in range(0, len(frames_in), chunk)]
            s = replay_columns(mon, chunks, [tl, fr])
        out[engine] = (tl.timeline, fr.frames_out, s, mon)
    return out["streaming"], out["columnar"]


@pytest.mark.parametrize(
    "roles",
    [("motor_speed_rpm", "pump_disp_cc"), ("motor_speed_rpm",), ("pump_disp_cc",)],
    ids=["both_signed", "signed_motor_speed", "signed_displacement"],
)
def test_reversing_is_gated_reverse_never_a_fault_in_both_engines(healthy_run, roles):
    cfg, run = healthy_run
    fwd, _ = both_engines(cfg, reversed_frames(cfg, run, ()))
    a, b = both_engines(cfg, reversed_frames(cfg, run, roles))
    assert_same(a, b)  # timeline, emitted frames, summary and the monitor's state

    tl, tl_fwd = a[0], fwd[0]
    t_op = tl.t_s - run.start_epoch_s
    assert np.array_equal(tl.t_s, tl_fwd.t_s)
    window_s = cfg.gate_limits.window_s
    inside = (t_op >= REVERSE_S[0] + window_s + 0.05) & (t_op < REVERSE_S[1] - 0.05)
    untouched = (t_op < REVERSE_S[0] - 0.05) | (t_op >= REVERSE_S[1] + window_s + 0.05)
    gates, gates_fwd = tl.gate.astype(int), tl_fwd.gate.astype(int)
    ev_fwd = np.isin(gates_fwd, [int(g) for g in EVALUATED])

    # Every point the forward run evaluated inside the stretch is REVERSE; none there is evaluated.
    assert ev_fwd[inside].sum() > 300
    assert np.all(gates[inside & ev_fwd] == Gate.REVERSE)
    assert not np.isin(gates[inside], [int(g) for g in EVALUATED]).any()
    # No fault, no warning: not implausible, not a model error, anywhere (straddling windows included).
    bad = [int(Gate.IMPLAUSIBLE_INPUT), int(Gate.MODEL_ERROR), int(Gate.STALE_INPUT)]
    assert not np.isin(gates, bad).any()
    assert np.all(tl.level == int(Level.OK)) and not a[2].warnings
    assert a[3].counters["model_errors"] == 0
    # Outside the stretch nothing changed, and the ratio is evaluated before and after it.
    assert np.array_equal(gates[untouched], gates_fwd[untouched])
    assert np.array_equal(tl.ratio_raw_pct[untouched], tl_fwd.ratio_raw_pct[untouched])
    ev = np.isin(gates, [int(g) for g in EVALUATED])
    assert ev[t_op < REVERSE_S[0]].sum() > 100 and ev[t_op >= REVERSE_S[1]].sum() > 100
    # The CM frames say so: cm_gate reverse, no valid raw ratio during the stretch.
    db = dbc_for(cfg)
    msg = db.get_message_by_name("CM_RATIO")
    sent = [
        (f.timestamp_s - run.start_epoch_s, db.decode_message(msg.frame_id, f.data, decode_choices=False))
        for f in a[1]
        if f.arbitration_id == msg.frame_id
    ]
    during = [v for ts, v in sent if REVERSE_S[0] + window_s + 0.05 <= ts < REVERSE_S[1] - 0.05]
    assert during and all(v["cm_raw_valid"] == 0 for v in during)
    assert sum(v["cm_gate"] == Gate.REVERSE for v in during) > 300


def test_the_cli_engines_write_identical_files_for_a_reversing_machine(tmp_path, healthy_run, signed_config):
    cfg, run = healthy_run
    frames = reversed_frames(cfg, run, ("motor_speed_rpm", "pump_disp_cc"))
    log = tmp_path / "reverse.log"
    write_candump(log, frames.timestamp_s, frames.arbitration_id, frames.dlc, frames.data)
    outs = {}
    for engine in ("streaming", "columnar"):
        tl, em = tmp_path / f"{engine}.csv", tmp_path / f"{engine}.emit.log"
        args = ("--config", str(signed_config), "--engine", engine, "--out", str(tl), "--emit", str(em), "--json")
        r = run_cli("replay", str(log), *args)
        assert r.returncode == 0, r.stderr
        outs[engine] = (tl.read_bytes(), em.read_bytes(), json.loads(r.stdout))
    assert outs["streaming"] == outs["columnar"]
    summary = outs["columnar"][2]
    assert summary["warnings"] == [] and summary["final"]["level"] == "ok"
    assert b",reverse," in outs["columnar"][0]
