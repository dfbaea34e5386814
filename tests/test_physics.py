"""The drive's physics against hand calculation."""

import math

import numpy as np
import pytest

from cmcan.sim.drive import DriveInputs, DriveState, integrate, load_torque_for_dp, steady_state
from cmcan.sim.physics import (
    BAR,
    CC,
    LPM,
    DriveParams,
    UnitLosses,
    laminar_leak_m3s,
    steady_motor_speed_rpm,
    turbulent_leak_m3s,
)

P = DriveParams()


def inputs(n, speed=2500.0, disp=70.0, dp=300.0, temp=50.0, p=P, **deg):
    z = np.zeros(n)
    return DriveInputs(
        np.full(n, speed),
        np.full(n, disp),
        np.full(n, float(load_torque_for_dp(p, dp))),
        np.full(n, temp),
        np.full(n, 25.0),
        deg.get("gp", z),
        deg.get("gm", z),
        deg.get("hb", z),
        deg.get("mf", np.ones(n)),
    )


@pytest.mark.parametrize(("speed", "disp", "dp", "temp"), [(3000, 78, 480, 60), (900, 10, 50, 20), (2000, 40, 300, 95)])
def test_lossless_motor_speed_is_the_ideal_law(speed, disp, dp, temp):
    p = P.lossless()
    hand = speed * disp / (110 * 0.40)
    assert float(steady_motor_speed_rpm(p, speed, disp, dp, temp)) == pytest.approx(hand, rel=1e-12)
    start = steady_state(p, speed, disp, float(load_torque_for_dp(p, dp)), temp)
    out = integrate(p, inputs(500, speed, disp, dp, temp, p), 0.01, start)
    assert out.motor_speed_rpm[-1] == pytest.approx(hand, rel=1e-6)


def test_reference_rig_point_gives_about_5100_rpm():
    n = float(steady_motor_speed_rpm(P, 3000, 78, 480, 60))
    assert 5000 < n < 5200


def test_wilson_laminar_leakage_by_hand():
    # Q = Cs * V/(2 pi) * dp / mu with Cs = 1e-9, V = 78 cm3, dp = 350 bar, mu = 0.04 Pa s
    q = laminar_leak_m3s(350 * BAR, 0.04, 78 * CC / (2 * math.pi), 1e-9)
    assert q == pytest.approx(1e-9 * 78e-6 / (2 * math.pi) * 350e5 / 0.04, rel=1e-12)


def only_laminar(cs=2e-9):
    return DriveParams(pump=UnitLosses(laminar_cs=cs), motor=UnitLosses())


def laminar_loss_lpm(p, dp, temp, speed=2500.0, disp=70.0):
    ideal_flow = speed * disp * CC / 60.0
    motor_flow = float(steady_motor_speed_rpm(p, speed, disp, dp, temp)) / 60.0 * p.motor_disp_cc * CC
    return (ideal_flow - motor_flow) / LPM


def test_laminar_leakage_scales_with_dp():
    p = only_laminar()
    q100, q200, q400 = (laminar_loss_lpm(p, dp, 50.0) for dp in (100, 200, 400))
    assert q200 / q100 == pytest.approx(2.0, rel=1e-9)
    assert q400 / q100 == pytest.approx(4.0, rel=1e-9)


def test_laminar_leakage_scales_with_inverse_viscosity():
    p = only_laminar()
    mu40, mu80 = p.oil.dynamic_viscosity_pa_s([40.0, 80.0])
    ratio = laminar_loss_lpm(p, 300, 80.0) / laminar_loss_lpm(p, 300, 40.0)
    assert ratio == pytest.approx(mu40 / mu80, rel=1e-9)


def test_turbulent_leakage_scales_with_sqrt_dp():
    q1 = turbulent_leak_m3s(100 * BAR, 870.0, 78 * CC, 1e-5)
    q4 = turbulent_leak_m3s(400 * BAR, 870.0, 78 * CC, 1e-5)
    assert q4 / q1 == pytest.approx(2.0, rel=1e-12)
    assert turbulent_leak_m3s(-100 * BAR, 870.0, 78 * CC, 1e-5) == pytest.approx(-q1)


def test_compressibility_loss_is_n_v_dp_over_k():
    p = DriveParams(pump=UnitLosses(compress_factor=1.0), motor=UnitLosses())
    speed, disp, dp = 3000.0, 78.0, 350.0
    loss = laminar_loss_lpm(p, dp, 50.0, speed, disp)
    hand = speed * disp * CC / 60.0 * (dp / p.bulk_modulus_bar) / LPM
    assert loss == pytest.approx(hand, rel=1e-9)


@pytest.mark.parametrize("dp", [80.0, 250.0, 450.0])
def test_steady_pressure_balances_the_load_torque(dp):
    load = float(load_torque_for_dp(P, dp))
    start = steady_state(P, 2500.0, 70.0, load, 50.0)
    out = integrate(P, inputs(3000, dp=dp), 0.01, DriveState(start.dp_pa * 0.7, start.motor_speed_rad_s * 0.9, 50.0))
    speed_rpm = out.motor_speed_rpm[-1]
    d_m = P.motor_disp_cc * CC / (2 * math.pi)
    torque_hand = load + P.motor_friction_nm + P.motor_viscous_nm_per_krpm * speed_rpm / 1000.0
    # tanh fade of the load is 1 to 1e-12 at these speeds
    assert out.dp_bar[-1] * BAR * d_m == pytest.approx(torque_hand, rel=1e-4)


def test_integrator_settles_to_the_quasi_static_law():
    out = integrate(P, inputs(3000), 0.01, DriveState(200 * BAR, 100.0, 50.0))
    law = float(steady_motor_speed_rpm(P, 2500, 70, out.dp_bar[-1], 50.0))
    assert out.motor_speed_rpm[-1] == pytest.approx(law, rel=1e-5)


def test_relief_valve_caps_pressure():
    out = integrate(P, inputs(2000, dp=700.0), 0.01, DriveState(100 * BAR, 300.0, 50.0))
    assert out.dp_bar.max() < P.relief_dp_bar + 30
    assert out.motor_speed_rpm[-1] < 50  # the load is stronger than the relief allows: the motor stalls


def test_heat_balance_settles_where_losses_equal_cooling():
    n = 30_000
    u = inputs(n)
    u = DriveInputs(**{**u.__dict__, "temp_c": np.full(n, np.nan)})
    start = steady_state(P, 2500.0, 70.0, float(load_torque_for_dp(P, 300)), 30.0)
    out = integrate(P, u, 0.1, start)
    t_end = out.temp_c[-1]
    assert abs(out.temp_c[-1] - out.temp_c[-100]) < 0.01  # settled (time constant ~400 s)
    assert 30.0 < t_end < 120.0


def test_extra_leakage_ground_truth_is_the_flow_it_takes():
    n = 2000
    h = 5.0 * LPM / math.sqrt(300 * BAR)  # orifice: 5 l/min at 300 bar
    out = integrate(
        P,
        inputs(n, hb=np.full(n, h)),
        0.01,
        steady_state(P, 2500, 70, float(load_torque_for_dp(P, 300)), 50.0, bypass_h=h),
    )
    assert out.extra_leak_lpm[-1] == pytest.approx(5.0 * math.sqrt(out.dp_bar[-1] / 300.0), rel=1e-6)
    healthy = integrate(P, inputs(n), 0.01, steady_state(P, 2500, 70, float(load_torque_for_dp(P, 300)), 50.0))
    lost_lpm = (healthy.motor_speed_rpm[-1] - out.motor_speed_rpm[-1]) * P.motor_disp_cc * 1e-3
    assert lost_lpm == pytest.approx(out.extra_leak_lpm[-1], rel=0.03)
