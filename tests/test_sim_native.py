"""The simulator's C loop (cmcan/sim/_drive_fast.c) gives the Python loop's numbers to the bit: over
random drives, inputs and start states (relief valve open, negative pressure, standstill, prescribed
and computed oil temperature, wear and bypass leakage), on shipped scenarios, and where the Python
loop raises (the C loop then leaves it to the Python loop)."""

from __future__ import annotations

import json
import math
import os
import struct
import subprocess
import sys
from collections import Counter
from dataclasses import replace
from functools import cache

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from cmcan.io import native
from cmcan.oil import Oil
from cmcan.sim import drive, run, scenario
from cmcan.sim.drive import DriveInputs, DriveState, integrate, integrate_python
from cmcan.sim.physics import BAR, TWO_PI, DriveParams, ExtraLosses, UnitLosses
from tests.conftest import ROOT


def needs_c() -> None:
    if native.LIB is None or not hasattr(native.LIB, "cmcan_drive_integrate"):
        pytest.skip("the C helpers are not built here (no C compiler at install)")


def same_bits(a, b) -> bool:
    """Equal to the bit (-0.0 is not 0.0), NaN where both are NaN whatever its payload."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        return False
    return bool(np.all((a.view(np.int64) == b.view(np.int64)) | (np.isnan(a) & np.isnan(b))))


def same_state(a: DriveState, b: DriveState) -> bool:
    bits = lambda s: [struct.pack("<d", float(v)) for v in (s.dp_pa, s.motor_speed_rad_s, s.temp_c)]  # noqa: E731
    nan = lambda s: [math.isnan(float(v)) for v in (s.dp_pa, s.motor_speed_rad_s, s.temp_c)]  # noqa: E731
    return all(x == y or (m and n) for x, y, m, n in zip(bits(a), bits(b), nan(a), nan(b), strict=True))


def same_outputs(a: drive.DriveOutputs, b: drive.DriveOutputs) -> bool:
    return (
        same_bits(a.dp_bar, b.dp_bar)
        and same_bits(a.motor_speed_rpm, b.motor_speed_rpm)
        and same_bits(a.temp_c, b.temp_c)
        and same_bits(a.extra_leak_lpm, b.extra_leak_lpm)
        and same_state(a.final, b.final)
    )


def c_and_python(p: DriveParams, u: DriveInputs, dt: float, start: DriveState):
    """(C outputs or None where the C loop left the run to Python, Python outputs or the exception)."""
    k = drive._hoisted(p)
    raw = drive._loop_native(k, u, dt, start)
    c = None if raw is None else drive._outputs(*raw)
    try:
        py: drive.DriveOutputs | Exception = integrate_python(p, u, dt, start)
    except (ArithmeticError, ValueError) as exc:
        py = exc
    return c, py


# -- random drives ----------------------------------------------------------------------------------


# The strategies are made once (hypothesis spends more time making and checking a strategy than
# drawing from it): cached makers, numpy's generator for long columns.


@cache
def pos(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


@cache
def maybe(value: float, s: st.SearchStrategy[float]) -> st.SearchStrategy[float]:
    return st.one_of(st.just(value), s)


def maybe_zero(s: st.SearchStrategy[float]) -> st.SearchStrategy[float]:
    return maybe(0.0, s)


@cache
def lists(s: st.SearchStrategy[float], lo: int, hi: int) -> st.SearchStrategy[list[float]]:
    return st.lists(s, min_size=lo, max_size=hi)


UNIT = st.builds(UnitLosses, maybe_zero(pos(1e-10, 5e-9)), maybe_zero(pos(1e-6, 3e-5)), maybe_zero(pos(0.0, 1.0)))
EXTRA = st.one_of(
    st.just(ExtraLosses()),
    st.builds(
        ExtraLosses,
        maybe_zero(pos(0.0, 10.0)),
        maybe_zero(pos(0.0, 10.0)),
        maybe_zero(pos(0.0, 10.0)),
        maybe_zero(pos(0.0, 1.0)),
        maybe_zero(pos(0.0, 10.0)),
    ),
)
OIL = st.one_of(st.just(Oil()), st.builds(Oil, pos(15.0, 100.0), pos(3.4, 11.2), pos(820.0, 900.0)))
KINDS = st.sampled_from(["constant", "steps", "free"])
SEEDS = st.integers(0, 2**32 - 1)
DT = st.sampled_from([0.001, 0.01, 0.02, 0.1, 0.5]) | pos(1e-4, 1.0)


@st.composite
def params(draw) -> DriveParams:
    base = DriveParams()
    if draw(st.booleans()):
        return base
    return replace(
        base,
        pump_disp_max_cc=draw(pos(20.0, 250.0)),
        motor_disp_max_cc=draw(pos(20.0, 250.0)),
        motor_disp_setting=draw(pos(0.2, 1.0)),
        relief_dp_bar=draw(pos(50.0, 600.0)),
        relief_gain_lpm_per_bar=draw(pos(0.5, 50.0)),
        bulk_modulus_bar=draw(pos(5000.0, 20000.0)),
        line_volume_l=draw(pos(0.2, 5.0)),
        motor_inertia_kgm2=draw(pos(0.05, 5.0)),
        motor_friction_nm=draw(maybe_zero(pos(0.0, 20.0))),
        motor_viscous_nm_per_krpm=draw(maybe_zero(pos(0.0, 10.0))),
        load_fade_rpm=draw(maybe_zero(pos(0.0, 100.0))),
        pump=draw(UNIT),
        motor=draw(UNIT),
        oil=draw(OIL),
        heat_capacity_kj_per_k=draw(pos(20.0, 500.0)),
        cooler_w_per_k=draw(maybe_zero(pos(0.0, 2000.0))),
        hm_loss_fraction=draw(maybe_zero(pos(0.0, 0.2))),
        extra=draw(EXTRA),
    )


def column(draw, n: int, values: st.SearchStrategy[float]) -> np.ndarray:
    """A constant, a few steps (set points that jump), or every step its own value: a few drawn
    values, between them or one of them at random each step (numpy's generator, seeded by the draw:
    hypothesis drawing hundreds of floats per column would take most of the test's time)."""
    kind = draw(KINDS)
    if kind == "constant":
        return np.full(n, draw(values))
    if kind == "steps":
        levels = draw(lists(values, 1, 4))
        cuts = sorted(draw(lists(st.integers(0, n), len(levels) - 1, len(levels) - 1)))
        out = np.empty(n)
        for lo, hi, v in zip([0, *cuts], [*cuts, n], levels, strict=True):
            out[lo:hi] = v
        return out
    pool = np.array(draw(lists(values, 2, 6)))
    rng = np.random.default_rng(draw(SEEDS))
    picked = pool[rng.integers(0, len(pool), n)]
    finite = pool[~np.isnan(pool)]
    between = rng.uniform(finite.min(), finite.max(), n) if len(finite) else picked
    return np.where(np.isnan(picked) | (rng.random(n) < 0.5), picked, between)


@st.composite
def cases(draw):
    p = draw(params())
    n = draw(st.integers(1, 200))
    speed = column(draw, n, maybe_zero(pos(0.0, 3500.0)))
    disp = column(draw, n, maybe_zero(pos(-1.0, 1.0))) * p.pump_disp_max_cc
    load = column(draw, n, maybe_zero(pos(-100.0, 1500.0)))
    temp = column(draw, n, maybe(math.nan, pos(-20.0, 110.0)))
    ambient = column(draw, n, pos(-20.0, 45.0))
    g_pump = column(draw, n, maybe_zero(pos(0.0, 2e-12)))
    g_motor = column(draw, n, maybe_zero(pos(0.0, 2e-12)))
    bypass = column(draw, n, maybe_zero(pos(0.0, 2e-7)))
    factor = column(draw, n, maybe(1.0, pos(0.0, 1.3)))
    u = DriveInputs(speed, disp, load, temp, ambient, g_pump, g_motor, bypass, factor)
    dt = draw(DT)
    start = DriveState(
        draw(maybe(-0.0, maybe_zero(pos(-300.0, 800.0)))) * BAR,
        draw(maybe_zero(pos(-400.0, 400.0))),
        draw(pos(-20.0, 120.0)),
    )
    return p, u, dt, start


def regimes(p: DriveParams, u: DriveInputs, start: DriveState, out: drive.DriveOutputs) -> set[str]:
    seen = set()
    if start.dp_pa > p.relief_dp_bar * BAR or np.any(out.dp_bar > p.relief_dp_bar):
        seen.add("relief valve open")
    if start.dp_pa < 0 or np.any(out.dp_bar < 0):
        seen.add("negative dp")
    if np.any((u.pump_speed_rpm == 0) & (np.abs(out.motor_speed_rpm) < 1.0)):
        seen.add("standstill")
    prescribed = ~np.isnan(u.temp_c)
    if prescribed.any() and not prescribed.all():
        seen.add("prescribed and computed oil temperature")
    elif not prescribed.any():
        seen.add("computed oil temperature only")
    if np.any(u.wear_g_pump + u.wear_g_motor > 0) and np.any(u.bypass_h > 0):
        seen.add("wear and bypass leakage")
    if np.any(np.abs(out.motor_speed_rpm) * TWO_PI / 60.0 / max(p.load_fade_rpm * TWO_PI / 60.0, 1e-3) >= 50.0):
        seen.add("sech^2 cut off")
    return seen


def test_the_c_loop_gives_the_python_loops_numbers_to_the_bit():
    needs_c()
    seen: Counter[str] = Counter()

    @settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(cases())
    def check(case):
        p, u, dt, start = case
        c, py = c_and_python(p, u, dt, start)
        if isinstance(py, Exception):
            event(f"the Python loop raises {type(py).__name__}")
            seen["the Python loop raises"] += 1
            assert c is None
            with pytest.raises(type(py)):
                integrate(p, u, dt, start)
            return
        assert c is not None, "the C loop left a run to Python that Python completes"
        assert same_outputs(c, py)
        assert same_outputs(integrate(p, u, dt, start), py)
        for r in regimes(p, u, start, py):
            event(r)
            seen[r] += 1
        seen["examples"] += 1

    check()
    for r in (
        "relief valve open",
        "negative dp",
        "standstill",
        "prescribed and computed oil temperature",
        "computed oil temperature only",
        "wear and bypass leakage",
        "sech^2 cut off",
    ):
        assert seen[r] >= 5, (r, dict(seen))


# -- where Python raises, and inputs that are not float64 arrays ------------------------------------


def steady_inputs(n: int, temp: float = 50.0, **over) -> DriveInputs:
    cols = dict(
        pump_speed_rpm=np.full(n, 2500.0),
        pump_disp_cc=np.full(n, 70.0),
        load_torque_nm=np.full(n, 300.0),
        temp_c=np.full(n, temp),
        ambient_c=np.full(n, 25.0),
        wear_g_pump=np.zeros(n),
        wear_g_motor=np.zeros(n),
        bypass_h=np.zeros(n),
        motor_disp_factor=np.ones(n),
    )
    cols.update(over)
    return DriveInputs(**cols)


@pytest.mark.parametrize(
    ("p", "u", "start", "error"),
    [
        (DriveParams(), steady_inputs(50, temp=-300.0), DriveState(0.0, 0.0, 50.0), ValueError),  # log10 below 0 K
        (DriveParams(motor_inertia_kgm2=0.0), steady_inputs(50), DriveState(0.0, 0.0, 50.0), ZeroDivisionError),
        (DriveParams(heat_capacity_kj_per_k=0.0), steady_inputs(50, math.nan), DriveState(0, 0, 50), ZeroDivisionError),
        (DriveParams(), steady_inputs(50, temp=-272.0), DriveState(0.0, 0.0, 50.0), OverflowError),  # 10.0 ** huge
    ],
)
def test_where_the_python_loop_raises_integrate_raises_the_same(p, u, start, error):
    with pytest.raises(error):
        integrate_python(p, u, 0.01, start)
    if native.LIB is not None and hasattr(native.LIB, "cmcan_drive_integrate"):
        assert drive._loop_native(drive._hoisted(p), u, 0.01, start) is None
    with pytest.raises(error):
        integrate(p, u, 0.01, start)


def test_a_late_error_is_the_python_loops_too():
    """The error at step 150 of 200: C stops there, and the Python loop raises it."""
    temp = np.full(200, 50.0)
    temp[150] = -300.0
    u = steady_inputs(200, temp_c=temp)
    with pytest.raises(ValueError):
        integrate(DriveParams(), u, 0.01, DriveState(0.0, 0.0, 50.0))


def test_inputs_that_are_not_float64_arrays_take_the_python_loop():
    needs_c()
    k = drive._hoisted(DriveParams())
    start = DriveState(100 * BAR, 100.0, 50)
    ints = steady_inputs(20, pump_speed_rpm=np.full(20, 2500))
    assert drive._loop_native(k, ints, 0.01, start) is None
    assert same_outputs(integrate(DriveParams(), ints, 0.01, start), integrate_python(DriveParams(), ints, 0.01, start))
    short = steady_inputs(20, bypass_h=np.zeros(19))
    assert drive._loop_native(k, short, 0.01, start) is None
    with pytest.raises(IndexError):
        integrate(DriveParams(), short, 0.01, start)
    longer = steady_inputs(20, bypass_h=np.zeros(25))  # the Python loop reads the first 20
    assert same_outputs(
        integrate(DriveParams(), longer, 0.01, start), integrate_python(DriveParams(), longer, 0.01, start)
    )
    assert drive._loop_native(k, steady_inputs(0), 0.01, start) is None
    f32 = DriveState(np.float32(100 * BAR), 100.0, 50.0)  # float32 arithmetic in the Python loop
    assert drive._loop_native(k, steady_inputs(20), 0.01, f32) is None
    assert drive._loop_native(k, steady_inputs(20), np.float32(0.01), start) is None
    f64 = DriveState(np.float64(100 * BAR), np.float64(100.0), np.float64(50.0))
    assert drive._loop_native(k, steady_inputs(20), np.float64(0.01), f64) is not None
    both = [f(DriveParams(), steady_inputs(20), np.float64(0.01), f64) for f in (integrate, integrate_python)]
    assert same_outputs(*both)


# -- shipped scenarios ------------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "hours"), [("run_to_failure", 24.0), ("two_set_train", 0.05)])
def test_a_shipped_scenario_simulates_the_same_both_ways(name, hours, monkeypatch, db):
    needs_c()
    s = scenario.load(scenario.resolve(name)).with_overrides(duration_h=hours)
    c = run.simulate(s, db)
    monkeypatch.setattr(run, "integrate", integrate_python)
    py = run.simulate(s, db)
    assert c.columns.keys() == py.columns.keys()
    for k in c.columns:
        assert np.array_equal(c.columns[k].view(np.int64), py.columns[k].view(np.int64)), k


def test_cmcan_native_0_simulates_with_the_python_loop(tmp_path):
    """CMCAN_NATIVE=0 in the environment: no library, the Python loop; the same run CSV."""
    needs_c()
    code = (
        "import json, sys\n"
        "from cmcan.io import native\n"
        "from cmcan.cli import main\n"
        "print(json.dumps(native.LIB is None))\n"
        "sys.stdout.flush()\n"
        "main(['simulate', 'two_set_train', '--duration-h', '0.02', '--out', sys.argv[1], '--force'])\n"
    )
    outs = {}
    for flag in ("0", "1"):
        out = tmp_path / f"run{flag}.csv"
        env = {"CMCAN_NATIVE": flag, "PYTHONPATH": str(ROOT)}
        r = subprocess.run(
            [sys.executable, "-c", code, str(out)],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=300,
            env={**os.environ, **env},
        )
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout.splitlines()[0]) is (flag == "0")
        outs[flag] = out.read_bytes()
    assert outs["0"] == outs["1"]
