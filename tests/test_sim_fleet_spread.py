"""Unit-to-unit variation in the simulated fleet (issue 29): machines of one type that differ."""

from __future__ import annotations

import json
from dataclasses import asdict, replace

import numpy as np
import pytest

from cmcan.cli import main
from cmcan.cli.errors import EX_USAGE
from cmcan.sim import fleet as sf
from cmcan.sim import scenario as scn
from cmcan.sim.physics import DriveParams
from cmcan.sim.run import simulate
from tests.conftest import run_cli

SPREAD = sf.UnitSpread()


def draws(p: sf.MachinePlan) -> tuple:
    """What the plan's own stream draws for a machine (the variation must not move any of it)."""
    t = p.truth
    return (p.type.name, t["duty"], t["oil_temp_c"], t["oil_swing_c"], t["start_epoch_s"], p.scenario.seed,
            t["degradation"], json.dumps(t["events"]), dict(p.scenario.duty))  # fmt: skip


def test_the_default_fleet_is_unchanged():
    spec = sf.FleetSpec(machines=7, hours=100, seed=3)
    same = sf.FleetSpec(
        machines=7, hours=100, seed=3, types=("compact", "mid", "large"), oil_temp_c=(45.0, 70.0),
        oil_swing_c=(5.0, 20.0), spread=None, arriving_leaks=0, arriving_leak_pct=(4.0, 8.0),
    )  # fmt: skip
    a, b = sf.plan_fleet(spec), sf.plan_fleet(same)
    assert [(p.truth, dict(p.scenario.document)) for p in a] == [(p.truth, dict(p.scenario.document)) for p in b]
    assert all("unit" not in p.truth and not p.scenario.sensors.errors for p in a)
    ref = DriveParams()
    assert all(p.scenario.params.pump == ref.pump and p.scenario.params.motor == ref.motor for p in a)
    # the draws as they were before the variation existed (seed 3, read off the plan of commit 4381985)
    got = [(p.type.name, t["duty"], t["oil_temp_c"], t["oil_swing_c"], p.scenario.seed, t["degradation"])
           for p, t in ((p, p.truth) for p in a[:4])]  # fmt: skip
    assert got == [
        ("compact", "wheel_loader", 57.0, 7.4, 1484806553, None),
        ("mid", "excavator", 57.9, 11.5, 1260140336, "motor_wear"),
        ("large", "excavator", 52.3, 5.0, 299072409, "pump_wear"),
        ("compact", "wheel_loader", 56.8, 16.6, 65167555, None),
    ]
    # the sidecar states the spec as before: the new fields only when set
    assert sf.spec_record(spec).keys() == {
        "machines", "hours", "seed", "degrading_share", "burst_s", "every_min", "log_hours", "start_epoch_s",
    }  # fmt: skip
    assert sf.spec_record(replace(spec, arriving_leaks=1))["arriving_leaks"] == 1


def test_variation_moves_nothing_else_the_seed_draws():
    spec = sf.FleetSpec(machines=9, hours=100, seed=5)
    plain = sf.plan_fleet(spec)
    varied = sf.plan_fleet(replace(spec, spread=SPREAD, arriving_leaks=2))
    assert [draws(p) for p in plain] == [draws(p) for p in varied]
    assert [p.degrading for p in plain] == [p.degrading for p in varied]


def units(spec: sf.FleetSpec) -> list[dict]:
    return [p.truth["unit"] for p in sf.plan_fleet(spec)]


def test_draws_are_reproducible_per_seed_and_differ_between_machines():
    spec = sf.FleetSpec(machines=6, hours=50, seed=11, types=("mid",), spread=SPREAD)
    a = units(spec)
    assert a == units(spec)
    assert units(replace(spec, seed=12)) != a
    for key in ("pump_disp_max_cc", "motor_disp_max_cc"):
        assert len({u[key] for u in a}) == len(a)
    assert len({u["leak_factor"]["pump"] for u in a}) == len(a)
    assert len({u["sensors"]["high_pressure_bar"]["offset"] for u in a}) == len(a)
    # a scaled spread moves the same machines the same way, only farther
    wide = units(replace(spec, spread=SPREAD.scaled(2.0)))
    nominal = sf.TYPES["mid"].motor_disp_max_cc
    for u, w in zip(a, wide, strict=True):
        assert w["motor_disp_max_cc"] - nominal == pytest.approx(2 * (u["motor_disp_max_cc"] - nominal), abs=1e-3)


@pytest.mark.parametrize("spread", [SPREAD, SPREAD.scaled(2.5), replace(SPREAD, leak_sigma=0.05, temp_offset_c=0.0)])
def test_draws_lie_within_the_tolerances_and_reach_the_scenario(spread):
    plans = sf.plan_fleet(sf.FleetSpec(machines=60, hours=50, seed=2, spread=spread))
    lo, hi = spread.leak_factor_bounds
    ref = DriveParams()
    used = {"disp": 0.0, "offset": 0.0}
    for p in plans:
        t, u, params = p.type, p.truth["unit"], p.scenario.params
        e_pump = abs(u["pump_disp_max_cc"] / t.pump_disp_max_cc - 1) * 100
        e_motor = abs(u["motor_disp_max_cc"] / t.motor_disp_max_cc - 1) * 100
        assert e_pump <= spread.pump_disp_pct + 1e-6 and e_motor <= spread.motor_disp_pct + 1e-6
        used["disp"] = max(used["disp"], e_motor / spread.motor_disp_pct)
        assert params.pump_disp_max_cc == u["pump_disp_max_cc"] and params.motor_disp_max_cc == u["motor_disp_max_cc"]
        assert u["motor_disp_cc"] == pytest.approx(params.motor_disp_cc, abs=1e-4)
        assert p.truth["motor_disp_cc"] == t.motor_disp_cc  # what the configuration says: nominal
        for unit, base in (("pump", ref.pump), ("motor", ref.motor)):
            k = u["leak_factor"][unit]
            assert lo - 1e-4 <= k <= hi + 1e-4
            assert getattr(params, unit).laminar_cs == pytest.approx(base.laminar_cs * k)
            assert getattr(params, unit).turbulent_ct == pytest.approx(base.turbulent_ct * k)
        bounds = spread.sensor_bounds(t)
        assert u["sensors"].keys() == set(scn.SENSOR_CHANNELS)
        for ch, e in u["sensors"].items():
            off_max, gain_max = bounds[ch]
            assert abs(e["offset"]) <= off_max + 1e-4 and abs(e["gain_pct"]) <= gain_max + 1e-4
            err = p.scenario.sensors.errors.get(ch)
            assert (err.offset if err else 0.0) == e["offset"]
            if ch != "pump_disp_cc":
                assert (err.gain_pct if err else 0.0) == e["gain_pct"]
        # a pressure transducer's offset and gain together stay within its accuracy at full scale
        hp = u["sensors"]["high_pressure_bar"]
        used["offset"] = max(used["offset"], abs(hp["offset"]) / bounds["high_pressure_bar"][0])
        fs = spread.pressure_fs_bar
        assert abs(hp["offset"] + hp["gain_pct"] / 100 * fs) <= spread.pressure_pct_fs / 100 * fs + 1e-3
        assert u["sensors"]["pump_speed_rpm"]["offset"] == 0.0 and u["sensors"]["temp_c"]["gain_pct"] == 0.0
    assert used["disp"] > 0.8 and used["offset"] > 0.8  # the draws fill the band, not a corner of it


def test_the_pump_displacement_sensor_reads_the_catalogue_scale():
    """A pump 1 % larger than its catalogue figure delivers 1 % more at the same swash angle; the bus
    carries the angle scaled by the catalogue figure, so the monitor cannot see the difference."""
    t = sf.TYPES["mid"]
    unit = replace(sf.nominal_unit(t), pump_disp_max_cc=t.pump_disp_max_cc * 1.01)
    doc = sf.apply_unit(small_raw(t), t, unit)
    s = scn.from_dict(doc)
    r = simulate(s)
    assert np.median(r["pump_disp_cc"]) == pytest.approx(0.8 * t.pump_disp_max_cc, abs=0.02)
    nominal = simulate(scn.from_dict(small_raw(t)))
    more = np.mean(r["true_motor_speed_rpm"][100:]) / np.mean(nominal["true_motor_speed_rpm"][100:])
    assert more == pytest.approx(1.01, abs=0.002)


def test_arriving_leaks_from_hour_0_on_healthy_machines_only():
    spec = sf.FleetSpec(machines=12, hours=200, seed=4, arriving_leaks=3)
    plans = sf.plan_fleet(spec)
    leaking = [p for p in plans if p.truth["unit"]["arriving_leak_lpm"] > 0]
    assert len(leaking) == 3
    assert sum(p.degrading for p in plans) == spec.degrading_count == 6
    for p in plans:
        leaks = [e for e in p.scenario.events if e["type"] == "leakage"]
        if p in leaking:
            assert not p.degrading and p.truth["degradation"] is None and p.truth["failures"] == []
            (ev,) = leaks
            assert ev["start_h"] == 0.0 and ev["ramp_h"] == 0.0 and ev["ref_dp_bar"] == sf.ARRIVING_LEAK_REF_DP_BAR
            share = ev["extra_lpm"] / p.type.rated_flow_lpm() * 100
            assert spec.arriving_leak_pct[0] - 0.01 <= share <= spec.arriving_leak_pct[1] + 0.01
            assert ev["extra_lpm"] == p.truth["unit"]["arriving_leak_lpm"]
            assert p.truth["events"] == [] and "arriving with a" in p.scenario.document["description"]
        else:
            assert leaks == []
        # without a spread the machines are otherwise their type
        assert p.truth["unit"]["motor_disp_max_cc"] == p.type.motor_disp_max_cc
        assert p.truth["unit"]["leak_factor"] == {"pump": 1.0, "motor": 1.0} and not p.scenario.sensors.errors
    # which machines leak is the seed's, not the spread's
    again = sf.plan_fleet(replace(spec, spread=SPREAD))
    assert [p.machine for p in leaking] == [p.machine for p in again if p.truth["unit"]["arriving_leak_lpm"] > 0]
    # every healthy machine can arrive leaking, no more
    assert len([p for p in sf.plan_fleet(replace(spec, arriving_leaks=6)) if p.truth["unit"]["arriving_leak_lpm"]]) == 6
    with pytest.raises(ValueError, match="between 0 and the 6 healthy machines"):
        sf.plan_fleet(replace(spec, arriving_leaks=7))


def test_a_fleet_of_one_type_with_mixed_duty_and_oil_from_cold_to_hot():
    oil = {"oil_temp_c": (55.0, 60.0), "oil_swing_c": (30.0, 35.0)}
    spec = sf.FleetSpec(machines=20, hours=150, seed=8, types=("mid",), **oil)
    plans = sf.plan_fleet(spec)
    assert {p.type.name for p in plans} == {"mid"}
    assert {p.truth["duty"] for p in plans} == set(sf.DUTIES)
    for p in plans:
        oil = p.scenario.oil
        assert oil["model"] == "prescribed" and 55.0 <= oil["temp_c"] <= 60.0 and 30.0 <= oil["swing_c"] <= 35.0
        assert 20.0 <= oil["temp_c"] - oil["swing_c"] <= 30.0 and 85.0 <= oil["temp_c"] + oil["swing_c"] <= 95.0


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"types": ("mid", "tiny")}, "unknown machine type 'tiny'"),
        ({"types": ()}, "at least one machine type"),
        ({"oil_temp_c": (70.0, 45.0)}, "oil temperature range"),
        ({"oil_swing_c": (5.0, 60.0)}, "oil swing range"),
        ({"oil_temp_c": (80.0, 90.0), "oil_swing_c": (20.0, 40.0)}, r"from 40 to 130 C, outside -30 \.\. 120 C"),
        ({"arriving_leaks": -1}, "arriving leaks"),
        ({"arriving_leaks": 1.5}, "arriving leaks"),
        ({"arriving_leak_pct": (0.0, 5.0)}, "arriving leak range"),
        ({"spread": replace(SPREAD, leak_sigma=-0.1)}, "leak_sigma must be a number >= 0"),
        ({"spread": SPREAD.scaled(20.0)}, "pump_disp_pct must be at most 10"),
        ({"spread": replace(SPREAD, temp_offset_c=float("nan"))}, "temp_offset_c must be a number"),
    ],
)
def test_bad_specs_are_refused(change, message):
    with pytest.raises(ValueError, match=message):
        replace(sf.FleetSpec(machines=4, hours=10), **change).check()


def small_raw(t: sf.MachineType) -> dict:
    """A short steady run of a type's drive (no noise: the comparison is of the physics)."""
    return {
        "name": "unit",
        "seed": 3,
        "duration_h": 0.005,
        "drive": t.drive(),
        "oil": {"model": "prescribed", "temp_c": 50.0},
        "duty": {"kind": "constant", "pump_speed_rpm": 2000, "pump_disp_pct": 80, "dp_bar": 250},
        "events": [],
        "sensors": {"noise": {k: 0.0 for k in scn.SENSOR_CHANNELS}},
    }


def test_a_larger_motor_really_turns_slower():
    """The configuration keeps the nominal V_M; a machine whose motor is 2 % larger turns about 2 %
    slower for the same flow, and the bus says so."""
    t = sf.TYPES["mid"]
    nominal = simulate(scn.from_dict(sf.apply_unit(small_raw(t), t, sf.nominal_unit(t))))
    plain = simulate(scn.from_dict(small_raw(t)))
    assert np.array_equal(nominal["motor_speed_rpm"], plain["motor_speed_rpm"])  # a nominal unit is its type
    big = replace(sf.nominal_unit(t), motor_disp_max_cc=t.motor_disp_max_cc * 1.02)
    larger = simulate(scn.from_dict(sf.apply_unit(small_raw(t), t, big)))
    steady = slice(len(plain) // 2, None)
    ratio = np.mean(larger["true_motor_speed_rpm"][steady]) / np.mean(nominal["true_motor_speed_rpm"][steady])
    assert ratio == pytest.approx(1 / 1.02, abs=0.002)
    measured = np.mean(larger["motor_speed_rpm"][steady]) / np.mean(nominal["motor_speed_rpm"][steady])
    assert measured == pytest.approx(1 / 1.02, abs=0.002)


def test_a_fleet_machine_with_its_draws_runs():
    """A fleet machine's scenario with variation and an arriving leak simulates (a few bursts), and its
    leak shows in the truth columns from the first sample."""
    spec = sf.FleetSpec(machines=4, hours=50, seed=6, types=("compact",), spread=SPREAD, arriving_leaks=1)
    p = next(p for p in sf.plan_fleet(spec) if p.truth["unit"]["arriving_leak_lpm"] > 0)
    r = simulate(p.scenario.with_overrides(duration_h=0.7))
    assert r.meta["bursts"] == 3
    assert r.meta["motor_disp_cc"] == pytest.approx(p.truth["unit"]["motor_disp_cc"], abs=1e-4)
    moving = r["true_dp_bar"] > 50
    assert moving.any() and (r["true_extra_leak_lpm"][moving] > 0).all()


def fleet_cli(*extra: str) -> int:
    return main(["simulate", "fleet", "--machines", "4", "--hours", "10", "--out", "/nonexistent/never", *extra])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--unit-spread", "-1"), "--unit-spread SCALE must be >= 0"),
        (("--unit-spread", "nan"), "--unit-spread SCALE must be >= 0"),
        (("--unit-spread", "30"), "must be at most 10"),
        (("--arriving-leaks", "3"), "between 0 and the 2 healthy machines"),
        (("--arriving-leak-pct", "5"), "--arriving-leak-pct expects LO,HI"),
        (("--arriving-leak-pct", "8,4"), "arriving leak range"),
        (("--types", "mid,tiny"), "unknown machine type 'tiny'"),
        (("--oil-c", "cold,hot"), "--oil-c expects LO,HI"),
        (("--oil-swing-c", "10,inf"), "--oil-swing-c expects finite numbers"),
    ],
)
def test_cli_refuses_bad_values(args, message, capsys):
    assert fleet_cli(*args) == EX_USAGE
    assert message in capsys.readouterr().err


def test_cli_argparse_errors_and_fleet_only_options(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        fleet_cli("--unit-spread", "wide")
    assert exc.value.code == EX_USAGE
    with pytest.raises(SystemExit) as exc:
        fleet_cli("--arriving-leaks", "1.5")
    assert exc.value.code == EX_USAGE
    capsys.readouterr()
    assert main(["simulate", "single_set_healthy", "--out", str(tmp_path / "r.csv"), "--unit-spread"]) == EX_USAGE
    assert "--unit-spread only apply to `cmcan simulate fleet`" in capsys.readouterr().err


def test_cli_writes_a_varied_fleet_of_one_type(tmp_path):
    out = tmp_path / "f"
    r = run_cli(
        "simulate", "fleet", "--machines", "2", "--hours", "4", "--types", "mid", "--unit-spread",
        "--arriving-leaks", "1", "--arriving-leak-pct", "5,6", "--oil-c", "40,50", "--burst-s", "2",
        "--every-min", "60", "--out", str(out), "--json",
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["types"] == ["mid"] and summary["arriving_leaks"] == 1 and summary["degrading"] == 1
    truth = json.loads((out / "truth.json").read_text())
    assert truth["spec"]["spread"] == asdict(SPREAD)
    assert truth["spec"]["types"] == ["mid"] and truth["spec"]["oil_temp_c"] == [40.0, 50.0]
    (leaky,) = [m for m in truth["machines"] if m["unit"]["arriving_leak_lpm"] > 0]
    assert not leaky["degrading"] and 5.0 <= leaky["unit"]["arriving_leak_lpm"] / 156.0 * 100 <= 6.0
    assert all(m["unit"]["motor_disp_cc"] != m["motor_disp_cc"] for m in truth["machines"])
    assert sorted(p.name for p in (out / "types").iterdir()) == ["mid"]


def test_degradations_and_their_earliest_onset_are_options_that_move_no_draw():
    spec = sf.FleetSpec(machines=9, hours=150, seed=4, types=("mid",), degrading_share=1 / 3)
    plain = sf.plan_fleet(spec)
    late = sf.plan_fleet(replace(spec, degradations=("motor_wear", "pump_wear"), onset_min_h=60.0))
    assert [p.degrading for p in plain] == [p.degrading for p in late]
    kinds = [p.truth["degradation"] for p in late if p.degrading]
    assert kinds == ["motor_wear", "pump_wear", "motor_wear"]
    for a, b in zip(plain, late, strict=True):
        assert a.scenario.seed == b.scenario.seed and a.truth["duty"] == b.truth["duty"]
        for ea, eb in zip(a.truth["events"], b.truth["events"], strict=True):
            assert eb["fail_h"] == ea["fail_h"] and eb["start_h"] == max(ea["start_h"], 60.0)
    rec = sf.spec_record(replace(spec, onset_min_h=60.0))
    assert rec["onset_min_h"] == 60.0 and "degradations" not in rec
    for bad in ({"degradations": ()}, {"degradations": ("rust",)}, {"onset_min_h": -1.0}, {"onset_min_h": 104.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            replace(spec, **bad).check()
