"""Effects inside the dynamic simulator: extra loss terms, sensor errors, the oil by grade."""

import hashlib

import numpy as np
import pytest

from cmcan.oil import Oil, oil_from_grade
from cmcan.schema import SchemaError
from cmcan.sim import run, scenario
from cmcan.sim.drive import DriveInputs, DriveState, integrate
from cmcan.sim.physics import DriveParams, ExtraLosses, steady_motor_speed_rpm
from cmcan.sim.sensors import SensorError, first_order_lag
from tests.conftest import small_scenario


def _digest(r):
    h = hashlib.sha256()
    for k in sorted(r.columns):
        h.update(k.encode())
        h.update(np.ascontiguousarray(r.columns[k]).tobytes())
    return h.hexdigest()


def test_zero_effects_change_no_bit():
    """Sections that switch nothing on leave the run bit for bit as without them."""
    plain = run.simulate(scenario.from_dict(small_scenario(duty={"kind": "wheel_loader"})))
    doc = small_scenario(
        duty={"kind": "wheel_loader"},
        losses={"extra": {"laminar_lpm": 0, "pressure_lpm": 0, "turbulent_lpm": 0, "compress_factor": 0}},
        sensors={"errors": {"temp_c": {"offset": 0.0, "gain_pct": 0.0, "lag_s": 0.0}}},
        fluid={"grade": "VG46"},
    )
    assert _digest(run.simulate(scenario.from_dict(doc))) == _digest(plain)


@pytest.mark.parametrize(
    "extra",
    [
        ExtraLosses(laminar_lpm=3.0),
        ExtraLosses(pressure_lpm=2.0),
        ExtraLosses(turbulent_lpm=4.0),
        ExtraLosses(compress_factor=0.5),
        ExtraLosses(filling_lpm=3.0),
    ],
)
def test_extra_losses_settle_where_the_flow_balance_says(extra):
    """The integrator with an extra term, held at one operating point, ends at the steady law's speed."""
    p = DriveParams(extra=extra)
    n = 3000
    u = DriveInputs(
        *(np.full(n, v) for v in (2500.0, 70.0)),
        load_torque_nm=np.full(n, 250.0),
        temp_c=np.full(n, 55.0),
        ambient_c=np.full(n, 25.0),
        wear_g_pump=np.zeros(n),
        wear_g_motor=np.zeros(n),
        bypass_h=np.zeros(n),
        motor_disp_factor=np.ones(n),
    )
    out = integrate(p, u, 0.01, DriveState(0.0, 0.0, 55.0))
    law = float(steady_motor_speed_rpm(p, 2500, 70, out.dp_bar[-1], 55.0))
    assert out.motor_speed_rpm[-1] == pytest.approx(law, rel=2e-4)
    base = float(steady_motor_speed_rpm(DriveParams(), 2500, 70, out.dp_bar[-1], 55.0))
    assert law < base - 5.0  # the term takes flow: the motor is slower


def test_extra_leak_is_stated_at_300_bar_and_50_c():
    p0, p1 = DriveParams(), DriveParams(extra=ExtraLosses(laminar_lpm=2.0))
    v_m = p0.motor_disp_cc / 1000.0 * (1 + p0.motor.compress_factor * 300.0 / p0.bulk_modulus_bar)  # l/rev at 300 bar
    lost = (steady_motor_speed_rpm(p0, 2000, 60, 300.0, 50.0) - steady_motor_speed_rpm(p1, 2000, 60, 300.0, 50.0)) * v_m
    assert float(lost) == pytest.approx(2.0, rel=1e-9)  # l/min


def test_sensor_errors_reach_the_measured_columns():
    doc = small_scenario(
        duration_h=0.01,
        sensors={
            "noise": dict.fromkeys(
                (
                    "pump_speed_rpm",
                    "pump_disp_cc",
                    "high_pressure_bar",
                    "low_pressure_bar",
                    "temp_c",
                    "motor_speed_rpm",
                ),
                0.0,
            ),
            "errors": {"temp_c": {"offset": 6.0}, "pump_speed_rpm": {"gain_pct": 2.0}},
        },
    )
    r = run.simulate(scenario.from_dict(doc))
    assert np.all(np.abs(r["temp_c"] - (r["true_temp_c"] + 6.0)) <= 0.06)  # DBC resolution
    assert np.median(r["pump_speed_rpm"]) == pytest.approx(2000 * 1.02, abs=0.5)
    assert np.median(r["true_motor_speed_rpm"]) == pytest.approx(np.median(r["motor_speed_rpm"]), abs=1.0)


def test_a_sensor_lag_is_a_first_order_filter():
    x = np.r_[np.zeros(10), np.ones(300)]
    y = SensorError(lag_s=0.5).apply(x, 0.01, [(0, len(x))])
    assert y[9] == 0.0 and y[10] == pytest.approx(1 - np.exp(-0.02), rel=1e-12)
    assert y[10 + 50] == pytest.approx(1 - np.exp(-51 * 0.01 / 0.5), rel=1e-9)
    # each burst starts settled at its own first value
    z = first_order_lag(np.r_[np.zeros(5), np.full(5, 7.0)], 0.01, 1.0, [(0, 5), (5, 10)])
    assert z[5:].tolist() == [7.0] * 5


def test_the_fluid_section_names_the_oil():
    assert scenario.from_dict(small_scenario(fluid={"grade": "ISO VG 32"})).params.oil == oil_from_grade("VG32")
    s = scenario.from_dict(small_scenario(fluid={"nu40_cst": 40.0, "nu100_cst": 6.0, "density15_kg_m3": 880}))
    assert s.params.oil == Oil(nu40_cst=40.0, nu100_cst=6.0, density15_kg_m3=880.0)
    for fluid, msg in [
        ({"grade": "VG33"}, "fluid.grade: unknown oil grade 'VG33'"),
        ({"grade": "VG46", "nu40_cst": 40}, "fluid.nu40_cst: give either grade or nu40_cst"),
        ({"nu40_cst": 40}, "fluid.nu100_cst: nu40_cst and nu100_cst go together"),
        ({"nu40_cst": 40, "nu100_cst": 50}, "fluid.nu100_cst: must be lower than nu40_cst"),
    ]:
        with pytest.raises(SchemaError, match=msg):
            scenario.from_dict(small_scenario(fluid=fluid))


def test_drive_files_state_the_machine(tmp_path):
    f = tmp_path / "rig.yaml"
    f.write_text(
        "drive: {pump_disp_max_cc: 4.6}\nfluid: {grade: VG68}\n"
        "losses: {motor: {laminar: {enabled: false}}, extra: {pressure_lpm: 0.2}}\n"
    )
    p = scenario.load_drive(f)
    assert p.pump_disp_max_cc == 4.6 and p.oil == oil_from_grade("VG68")
    assert p.motor.laminar_cs == 0.0 and p.extra.pressure_lpm == 0.2
    f.write_text("drive: {pump_disp_max_cc: 4.6}\nduty: {kind: constant}\n")
    with pytest.raises(SchemaError, match=r"rig\.yaml: duty: unknown field"):
        scenario.load_drive(f)


# -- degradation laws beyond the laminar power law (issue 40) -------------------------------------------


def _wear(**over):
    ev = {"type": "wear", "component": "motor", "start_h": 10.0, "fail_h": 60.0, "fail_extra_lpm": 30.0}
    return scenario.from_dict(small_scenario(duration_h=70.0, events=[{**ev, **over}])).events[0]


def test_an_orifice_wear_leaks_with_sqrt_dp_and_not_with_the_oil():
    from cmcan.sim.degradation import evaluate

    t = np.array([50.0])
    thin, thick = oil_from_grade("VG32"), oil_from_grade("VG68")
    lam, ori = _wear(), _wear(law="orifice")
    d_ori = evaluate([ori], t, thin)
    assert d_ori.wear_g_motor[0] == 0.0 and d_ori.bypass_h[0] > 0.0  # an orifice, not a gap
    assert evaluate([ori], t, thick).bypass_h[0] == d_ori.bypass_h[0]  # whatever the oil
    d_lam = evaluate([lam], t, thin)
    assert d_lam.bypass_h[0] == 0.0 and 0.0 < d_lam.wear_g_motor[0] != evaluate([lam], t, thick).wear_g_motor[0]
    # at the reference point both leak the curve's value: F (40/50)^3
    from cmcan.sim.physics import BAR, LPM

    q_ori = d_ori.bypass_h[0] * np.sqrt(480.0 * BAR) / LPM
    assert q_ori == pytest.approx(30.0 * 0.8**3, rel=1e-12)


def test_staged_damage_and_a_change_of_pace_keep_the_failure_hour():
    from cmcan.sim.degradation import wear_lpm, wear_progress

    t = np.linspace(0.0, 70.0, 701)
    steps = _wear(growth="steps", steps=3, shape=1.0)
    x = wear_lpm(steps, t)
    assert sorted(set(np.round(x[t < 60.0], 9))) == pytest.approx([0.0, 10.0, 20.0])  # two jumps before failure
    faster = _wear(rate_change_h=30.0, rate_factor=3.0)
    s = wear_progress(faster, t)
    assert s[t == 30.0][0] == pytest.approx(20.0 / (20.0 + 3.0 * 30.0))  # slow until the change
    assert np.all(np.diff(s) >= 0) and s[t == 60.0][0] == pytest.approx(1.0)  # then 3x, failing on time
    with pytest.raises(SchemaError, match="rate_change_h"):
        _wear(rate_change_h=70.0)


def test_a_duty_change_moves_the_operating_point_at_its_hour():
    doc = small_scenario(
        duration_h=0.2,
        duty={
            "kind": "change",
            "at_h": 0.1,
            "before": {"kind": "constant", "pump_speed_rpm": 1800, "pump_disp_pct": 60, "dp_bar": 150},
            "after": {"kind": "constant", "pump_speed_rpm": 2400, "pump_disp_pct": 90, "dp_bar": 400},
        },
    )
    r = run.simulate(scenario.from_dict(doc))
    h, dp = r["operating_h"], r["true_dp_bar"]
    assert np.median(dp[(h > 0.05) & (h < 0.095)]) < 200 < 350 < np.median(dp[h > 0.15])
