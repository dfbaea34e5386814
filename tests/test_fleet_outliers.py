"""`cmcan fleet train` against machines that do not fit their type: a machine that arrives leaking (or
with its displacement set high) is named and left out of the type model and its unit-to-unit spread,
judged on the median and MAD of the machines' offsets, which one or two such machines cannot move, and
against the reference (the model the logs were replayed with), which half of a type leaking cannot move.
Machines drawn from the simulator's own steady flow balance (the fit, not the Dask path, is tested here;
tests/test_fleet_train.py runs the command line)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

pytest.importorskip("onnx")

from cmcan.fleet.train import (
    MIN_MACHINES_JUDGED,
    OUTLIER_Z,
    DriveFacts,
    MachinePoints,
    fit_type,
    machine_points,
    off_reference,
    outlying,
    reference_shape,
)
from cmcan.sim.physics import DriveParams, steady_motor_speed_rpm

DRIVE = DriveParams()
MOTOR_CC = DRIVE.motor_disp_cc
FACTS = DriveFacts("motor_speed_rpm", MOTOR_CC, DRIVE.oil.nu40_cst, DRIVE.oil.nu100_cst)
POINTS = 400


def machine(name: str, rng: np.random.Generator, extra_leak_lpm: float, disp_factor: float = 1.0) -> MachinePoints:
    """A machine's healthy points over the envelope: the simulator's steady motor speed with the unit's
    own extra leak (negative: it delivers more), and speed-sensor noise."""
    x = np.column_stack(
        [
            rng.uniform(900.0, 3300.0, POINTS),  # pump speed, rpm
            rng.uniform(10.0, 78.0, POINTS),  # pump displacement, cc
            rng.uniform(40.0, 450.0, POINTS),  # delta p, bar
            rng.uniform(35.0, 85.0, POINTS),  # oil, C
        ]
    )
    n_m = steady_motor_speed_rpm(DRIVE, *x.T, extra_leak_lpm=extra_leak_lpm, motor_disp_factor=disp_factor)
    n_m = n_m + rng.normal(0.0, 3.0, POINTS)
    return MachinePoints(name, x, n_m, np.linspace(0.0, 50.0, POINTS), rows=POINTS, refused={})


def fleet(seed: int, n: int, leaks_lpm: dict[int, float], unit_sd_lpm: float = 0.8) -> list[MachinePoints]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        unit = rng.normal(0.0, unit_sd_lpm)  # the unit-to-unit spread of healthy drives
        out.append(machine(f"m{i:03d}", rng, unit + leaks_lpm.get(i, 0.0)))
    return out


@pytest.fixture(scope="module")
def leaking():
    """Twelve machines, two of which arrive leaking 8 and 9 l/min; and the same ten without those two."""
    ms = fleet(11, 12, {3: 8.0, 8: 9.0})
    with_leaks = fit_type(ms, FACTS, "mid", "test")
    without = fit_type([m for m in ms if m.machine not in ("m003", "m008")], FACTS, "mid", "test")
    return ms, with_leaks, without


def test_both_leaking_machines_are_named_and_left_out(leaking):
    _, res, _ = leaking
    sp = res.training["unit_spread"]
    assert sorted(sp["outliers"]) == ["m003", "m008"]
    assert all("arrives leaking" in v["why"] for v in sp["outliers"].values())
    assert all(v["offset_lpm"] < -6.0 and v["robust_z"] < -OUTLIER_Z for v in sp["outliers"].values())
    assert sp["machines"] == 10 and "m003" not in sp["per_machine"]
    assert res.training["selection"]["outliers"] == ["m003", "m008"]


def test_the_spread_is_the_fleets_without_them(leaking):
    """The kept machines are the ten healthy ones, so the model and the spread are those of the fleet
    without the two (the issue asks for within 20 %)."""
    _, res, without = leaking
    a, b = res.training["unit_spread"]["offset_sd_lpm"], without.training["unit_spread"]["offset_sd_lpm"]
    assert without.training["unit_spread"]["outliers"] == {}
    assert abs(a - b) <= 0.2 * b and 0.3 < b < 2.0
    assert res.training["points_trn"] == without.training["points_trn"]


def test_without_the_rule_the_leaks_would_have_inflated_the_spread(leaking):
    ms, res, _ = leaking
    kept_all = fit_type(ms, FACTS, "mid", "test", keep=[m.machine for m in ms])
    sp = kept_all.training["unit_spread"]
    assert sp["outliers"] == {} and sp["machines"] == 12
    assert sp["offset_sd_lpm"] > 2.5 * res.training["unit_spread"]["offset_sd_lpm"]
    assert kept_all.training["selection"]["kept_by_hand"] == sorted(m.machine for m in ms)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_healthy_fleet_loses_no_machine(seed):
    res = fit_type(fleet(seed, 9, {}), FACTS, "mid", "test")
    assert res.training["unit_spread"]["outliers"] == {}
    assert res.training["unit_spread"]["machines"] == 9


def test_a_displacement_set_high_is_named_as_delivering_more():
    rng = np.random.default_rng(5)
    ms = fleet(5, 7, {})
    ms.append(machine("m099", rng, 0.0, disp_factor=0.88))  # swallows 12 % less per rev: reads fast
    sp = fit_type(ms, FACTS, "mid", "test").training["unit_spread"]
    assert list(sp["outliers"]) == ["m099"] and "delivers more" in sp["outliers"]["m099"]["why"]


def test_three_machines_are_not_judged():
    ms = fleet(7, 3, {1: 12.0})
    assert fit_type(ms, FACTS, "mid", "test").training["unit_spread"]["outliers"] == {}


@settings(max_examples=300, deadline=None)
@given(
    healthy=st.lists(st.floats(-1.0, 1.0), min_size=MIN_MACHINES_JUDGED, max_size=20),
    odd=st.lists(st.floats(-40.0, 40.0).filter(lambda v: abs(v) >= 8.0), max_size=2),
)
def test_one_or_two_odd_machines_cannot_hide_themselves_or_a_healthy_one(healthy, odd):
    """Healthy offsets within +-1 l/min (the floor 1 l/min: 3.5 robust SDs are 3.5 l/min at least),
    at most two far off, and the healthy ones the majority: exactly the odd ones are named."""
    if len(odd) * 2 >= len(healthy):
        odd = odd[: max(0, (len(healthy) - 1) // 2)]
    offsets = {f"h{i:02d}": v for i, v in enumerate(healthy)} | {f"x{i}": v for i, v in enumerate(odd)}
    event(f"{len(odd)} odd")
    assert sorted(outlying(offsets, 1.0)) == [f"x{i}" for i in range(len(odd))]


def test_the_scale_has_a_floor():
    """Identical units (MAD 0) do not make a tenth of a l/min an outlier."""
    offsets = {f"m{i}": 0.0 for i in range(8)} | {"m9": 0.1}
    assert outlying(offsets, 1.0) == {} and outlying(offsets | {"m9": 3.4}, 1.0) == {}
    assert math.isclose(outlying(offsets | {"m9": 4.0}, 1.0)["m9"]["robust_z"], 4.0)


# -- against the reference: the model the machines' logs were replayed with --------------------------------


def with_reference(ms: list[MachinePoints], model: str = "sha-type", level: float = 1.0) -> list[MachinePoints]:
    """The machines as replayed with one model of the nominal drive (``level``: that model's flow over
    the nominal's, 1.0 a model of a healthy nominal unit)."""
    return [
        dataclasses.replace(mp, reference=level * steady_motor_speed_rpm(DRIVE, *mp.x.T), reference_model=model)
        for mp in ms
    ]


@pytest.fixture(scope="module")
def half_leaking():
    """Four machines of a type, two of them arriving with 8 and 9 l/min leaks: the median lies between
    the healthy pair and the leaking pair."""
    return fleet(21, 4, {1: 8.0, 2: 9.0})


def test_the_median_cannot_judge_a_type_half_leaking(half_leaking):
    assert fit_type(half_leaking, FACTS, "mid", "test").training["unit_spread"]["outliers"] == {}


def test_the_reference_names_both_leaks_of_a_type_half_leaking(half_leaking):
    res = fit_type(with_reference(half_leaking), FACTS, "mid", "test")
    sp = res.training["unit_spread"]
    assert sorted(sp["outliers"]) == ["m001", "m002"]
    assert all("arrives leaking" in v["why"] for v in sp["outliers"].values())
    assert all(v["reference_offset_lpm"] < -sp["reference"]["bound_lpm"] for v in sp["outliers"].values())
    assert sp["reference"]["applied"] and sp["reference"]["model"] == "sha-type"
    without = fit_type(with_reference([half_leaking[0], half_leaking[3]]), FACTS, "mid", "test")
    a, b = sp["offset_sd_lpm"], without.training["unit_spread"]["offset_sd_lpm"]
    assert abs(a - b) <= 0.2 * b


def test_a_healthy_fleet_is_not_named_against_its_reference():
    for seed in (1, 2, 3):
        sp = fit_type(with_reference(fleet(seed, 5, {})), FACTS, "mid", "test").training["unit_spread"]
        assert sp["outliers"] == {} and sp["reference"]["applied"]


def test_a_reference_most_machines_lie_off_is_not_used(half_leaking):
    """A model 6 % off the whole type (another unit's rig run, another oil): every machine is beyond the
    bound against it, so it says nothing of which one is odd."""
    healthy = fleet(22, 5, {})
    sp = fit_type(with_reference(healthy, level=1.06), FACTS, "mid", "test").training["unit_spread"]
    assert sp["outliers"] == {} and not sp["reference"]["applied"]


def test_machines_replayed_with_different_models_are_not_judged_on_them(half_leaking):
    ms = with_reference(half_leaking[:2]) + with_reference(half_leaking[2:], model="sha-other")
    sp = fit_type(ms, FACTS, "mid", "test").training["unit_spread"]
    assert sp["outliers"] == {} and sp["reference"] == {
        "applied": False,
        "why": "the machines were not all replayed with one model",
    }


def test_off_reference_bound_and_majority():
    offsets = {"a": 0.5, "b": -0.9, "c": -3.1, "d": 2.9}
    got = off_reference(offsets, 3.0)["outliers"]  # no shapes: the mean alone
    assert list(got) == ["c"] and got["c"]["reference_offset_lpm"] == -3.1 and "arrives leaking" in got["c"]["why"]
    assert off_reference(offsets, 2.8)["applied"]  # two of four: not more than half
    assert not off_reference(offsets | {"e": 4.0}, 2.8)["applied"] and off_reference({}, 1.0)["outliers"] == {}


def test_off_reference_names_only_a_part_beyond_the_bound():
    """Off in the mean, but no part of it beyond the bound (a unit whose tolerances add up): not named;
    a leak's part beyond it: leaking, even where a unit delivering more hides it in the mean; the
    flow's part and the mean beyond it: delivers less, or more."""
    offsets = {"tol": -3.5, "leak": -3.5, "hidden": -2.0, "disp": -3.5, "high": 3.5}
    offsets |= {f"h{i}": 0.1 * i for i in range(6)}
    shapes = {"tol": (-2.0, -2.0), "leak": (1.0, -6.0), "hidden": (2.5, -6.0), "disp": (-3.4, 0.0), "high": (3.4, 0.5)}
    got = off_reference(offsets, 3.0, shapes)["outliers"]
    assert sorted(got) == ["disp", "hidden", "high", "leak"]
    assert all("arrives leaking" in got[m]["why"] and "pressure" in got[m]["why"] for m in ("leak", "hidden"))
    assert got["disp"]["why"].startswith("delivers less") and got["high"]["why"].startswith("delivers more")
    shapes["h0"] = (0.0, -3.1)  # five of eleven would be named: applied; six: the reference does not fit
    assert off_reference(offsets, 3.0, shapes)["applied"]
    shapes["h1"] = (0.0, -3.1)
    assert off_reference(offsets, 3.0, shapes) | {"offset_lpm": {}} == {
        "applied": False, "bound_lpm": 3.0, "offset_lpm": {}, "outliers": {}
    }  # fmt: skip


def test_reference_shape_tells_a_leak_from_a_displacement():
    rng = np.random.default_rng(3)
    ms = [machine("m", rng, 0.0)]
    x = ms[0].x
    q = x[:, 0] * x[:, 1] / 1000.0
    leak = -6.0 * np.sqrt(x[:, 2] / 480.0)  # an orifice, 6 l/min at 480 bar
    disp = -0.04 * q  # 4 % less per revolution
    flow_part, leak_part = reference_shape(x, leak)
    assert leak_part == pytest.approx(-6.0) and abs(flow_part) < 1e-6
    flow_part, leak_part = reference_shape(x, disp)
    assert flow_part == pytest.approx(-0.04 * q.mean()) and abs(leak_part) < 1e-6
    same = x.copy()
    same[:, 2] = 300.0  # one pressure: the shapes cannot be told apart
    assert reference_shape(same, disp[:POINTS]) == (pytest.approx(disp.mean()),) * 2


def test_a_unit_off_by_its_displacement_is_not_named_leaking():
    """Three units (too few for the median) and one whose motor swallows 4.5 % more per revolution: off
    the reference by more than 3.5 % of the flow, in the flow's shape: named as delivering less, not as
    leaking; at 2.5 % it is a unit's tolerance and kept."""
    rng = np.random.default_rng(9)
    ms = fleet(9, 3, {}, unit_sd_lpm=0.3)
    for factor, named in ((1.045, True), (1.025, False)):
        odd = with_reference([*ms, machine("m099", rng, 0.0, disp_factor=factor)])
        sp = fit_type(odd, FACTS, "mid", "test").training["unit_spread"]
        assert (list(sp["outliers"]) == ["m099"]) is named
        if named:
            assert sp["outliers"]["m099"]["why"].startswith("delivers less than the type, in proportion to the flow")
        shape = sp["reference"]["shape_lpm"]["m099"]
        assert abs(shape["leak_at_ref_dp"]) < 0.5 * abs(shape["flow"])


def test_a_machine_replayed_with_two_models_or_its_own_baseline_has_no_reference():
    n = 30
    cols = {
        "time_s": np.arange(n, dtype=float),
        "operating_h": np.linspace(0.0, 1.0, n),
        "ticks": np.full(n, 5),
        "evaluated": np.full(n, 5),
        "gate": np.array(["evaluating"] * n, dtype=object),
        "warning_level": np.array(["ok"] * n, dtype=object),
        "measured": np.full(n, 1000.0),
        "predicted": np.full(n, 990.0),
        "pump_speed_rpm": np.full(n, 2000.0),
        "pump_disp_cc": np.full(n, 40.0),
        "dp_bar": np.full(n, 200.0),
        "temp_c": np.full(n, 50.0),
        "model_hash": np.array(["a"] * n, dtype=object),
    }
    mp = machine_points("m1", cols)
    assert mp.reference_model == "a" and np.all(mp.reference == 990.0)
    cols["baseline_state"] = np.zeros(n, dtype=np.int8)  # no baseline: the model's own prediction
    assert machine_points("m1", cols).reference_model == "a"
    cols["baseline_state"][-1] = 2  # monitoring: the prediction corrected by the machine's own baseline
    assert machine_points("m1", cols).reference is None
    cols["baseline_state"][-1] = 1  # learning judges on the type model
    assert machine_points("m1", cols).reference_model == "a"
    cols["model_hash"] = np.array(["a"] * (n - 1) + ["b"], dtype=object)
    assert machine_points("m1", cols).reference is None
    del cols["predicted"]
    assert machine_points("m1", cols).reference is None
