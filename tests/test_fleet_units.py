"""`cmcan fleet train` fits each machine's own unit terms beside the type model: units that differ
(a leakier pump, a displacement at its tolerance) and work at distinct duty must not teach the type
model their differences as a dependence on the operating point. Judged as the gateway uses the model:
on a unit of the type it has not seen, after that unit's own three terms (what its on-board baseline
learns), what is left is the speed sensor's noise, not a swing with the operating point. Machines
drawn from the simulator's own steady flow balance (the fit, not the Dask path)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("onnx")
pytest.importorskip("scipy")

from cmcan.fleet.train import UNIT_TOL_LPM, DriveFacts, MachinePoints, _unit_theta, fit_type, fit_with_units
from cmcan.model.train import fit
from cmcan.monitor.baseline import unit_features
from cmcan.oil import Oil
from cmcan.sim.physics import DriveParams, steady_motor_speed_rpm

DRIVE = DriveParams()
FACTS = DriveFacts("motor_speed_rpm", DRIVE.motor_disp_cc, DRIVE.oil.nu40_cst, DRIVE.oil.nu100_cst)
OIL = Oil(FACTS.oil_nu40_cst, FACTS.oil_nu100_cst)
NOISE_RPM = 2.0
NOISE_LPM = NOISE_RPM * FACTS.lpm_per_unit
POINTS = 400
# Each machine's duty (pump speed rpm, displacement cc, dp bar, oil C): one at high pressure and warm
# oil, one at high speed and low pressure, one between; the unseen unit works over all of it.
DUTIES = (
    ((900, 2000), (10, 50), (250, 450), (60, 85)),
    ((2000, 3300), (40, 78), (40, 200), (35, 60)),
    ((1500, 3000), (20, 70), (100, 400), (45, 75)),
)
WHOLE = ((900, 3300), (10, 78), (40, 450), (35, 85))


def unit(name: str, rng: np.random.Generator, duty, leak_factor: float, disp_factor: float) -> MachinePoints:
    """A healthy unit: the pump's laminar leak coefficient times ``leak_factor``, the motor's
    displacement times ``disp_factor``, speed-sensor noise."""
    x = np.column_stack([rng.uniform(lo, hi, POINTS) for lo, hi in duty])
    pump = dataclasses.replace(DRIVE.pump, laminar_cs=DRIVE.pump.laminar_cs * leak_factor)
    drive = dataclasses.replace(DRIVE, pump=pump)
    y = steady_motor_speed_rpm(drive, *x.T, motor_disp_factor=disp_factor) + rng.normal(0.0, NOISE_RPM, POINTS)
    return MachinePoints(name, x, y, np.linspace(0.0, 50.0, POINTS), rows=POINTS, refused={})


def left_after_own_terms(model, mp: MachinePoints) -> float:
    """The RMS residual (l/min) of a unit against the model once its own three terms are fitted."""
    r = (mp.measured - model.predict(mp.x)) * FACTS.lpm_per_unit
    f = unit_features(mp.x, OIL)
    return float(np.sqrt(np.mean((r - f @ _unit_theta(f, r)) ** 2)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_unseen_unit_is_left_with_its_noise_not_its_types_duty(seed):
    rng = np.random.default_rng(seed)

    def draw(name, duty):
        return unit(name, rng, duty, float(np.exp(rng.normal(0.0, 0.3))), float(1.0 + rng.normal(0.0, 0.01)))

    machines = [draw(f"m{i}", DUTIES[i % 3]) for i in range(4)]
    unseen = draw("new", WHOLE)
    x = np.concatenate([m.x for m in machines])
    y = np.concatenate([m.measured for m in machines])
    pooled = fit(x, y, FACTS.motor_disp_cc, FACTS.quantity, OIL)
    model, terms = fit_with_units(machines, FACTS, OIL)
    assert terms.moved_lpm < UNIT_TOL_LPM and terms.rounds > 1
    # the terms are centred: the model is the machines' average unit
    np.testing.assert_allclose(np.mean(list(terms.theta.values()), axis=0), 0.0, atol=1e-12)
    with_units = left_after_own_terms(model, unseen)
    assert with_units < 1.25 * NOISE_LPM
    assert left_after_own_terms(pooled, unseen) > with_units  # what the pooled fit leaves: its units' duty


def test_identical_units_need_no_terms():
    """Units that do not differ: the terms fit the noise only and the model is the pooled fit's."""
    rng = np.random.default_rng(5)
    machines = [unit(f"m{i}", rng, DUTIES[i % 3], 1.0, 1.0) for i in range(4)]
    model, terms = fit_with_units(machines, FACTS, OIL)
    x = np.concatenate([m.x for m in machines])
    pooled = fit(x, np.concatenate([m.measured for m in machines]), FACTS.motor_disp_cc, FACTS.quantity, OIL)
    for m in machines:
        shift = unit_features(m.x, OIL) @ np.array(terms.theta[m.machine])
        assert float(np.sqrt(np.mean(shift**2))) < 0.25 * NOISE_LPM, m.machine
    gap = (model.predict(x) - pooled.predict(x)) * FACTS.lpm_per_unit
    assert float(np.sqrt(np.mean(gap**2))) < 0.25 * NOISE_LPM


def test_the_type_model_records_the_unit_terms():
    rng = np.random.default_rng(7)
    machines = [unit(f"m{i}", rng, DUTIES[i % 3], 1.2 if i == 1 else 1.0, 1.0) for i in range(4)]
    res = fit_type(machines, FACTS, "mid", "test")
    ut = res.training["unit_terms"]
    assert ut["converged"] and sorted(ut["per_machine"]) == [m.machine for m in machines]
    assert ut["features"] == ["offset_lpm", "geometric_per_100lpm", "laminar_leak_lpm"]
    # the leakier unit's laminar term is the largest
    assert max(ut["per_machine"], key=lambda m: -ut["per_machine"][m][2]) == "m1"
