"""Window statistics and gate rules (property tests against a naive reference)."""

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from cmcan.monitor.gating import (
    EVALUATED,
    REFERENCE_MOTOR_DISP_CC,
    Gate,
    GateLimits,
    eval_times,
    gate,
    gate_columns,
    gate_point,
    scaled,
    table_stats,
    window_stats,
)
from cmcan.monitor.windows import TIME_EPS_S


@settings(max_examples=80, deadline=None)
@given(
    gaps=st.lists(st.floats(0.001, 0.5), min_size=1, max_size=60),
    values=st.lists(st.floats(-1e4, 1e4), min_size=60, max_size=60),
    window=st.floats(0.05, 2.0),
    probes=st.lists(st.floats(-0.5, 20.0), min_size=1, max_size=10),
)
def test_window_stats_match_a_naive_computation(gaps, values, window, probes):
    ts = np.cumsum(gaps)
    vs = np.array(values[: len(ts)])
    t_eval = np.array(sorted(probes))
    s = window_stats({"x": (ts, vs)}, t_eval, window)
    for k, t in enumerate(t_eval):
        inside = (ts > t - window + TIME_EPS_S) & (ts <= t + TIME_EPS_S)
        assert s.count["x"][k] == inside.sum()
        if inside.any():
            assert s.mean["x"][k] == pytest.approx(vs[inside].mean(), abs=1e-6 * (1 + abs(vs).max()))
            assert s.std["x"][k] == pytest.approx(vs[inside].std(), abs=1e-4 * (1 + abs(vs).max()))
            assert s.age_s["x"][k] == pytest.approx(t - ts[inside][-1])
        earlier = ts <= t + TIME_EPS_S
        if not earlier.any():
            assert s.age_s["x"][k] == np.inf


def stats_for(t_eval=1.5, **means):
    base = {"pump_speed_rpm": 2000.0, "pump_disp_cc": 60.0, "dp_bar": 300.0, "temp_c": 50.0, "motor_speed_rpm": 2600.0}
    base.update(means)
    series = {}
    t = np.arange(0, 2, 0.01)
    for k, v in base.items():
        series[k] = (t, np.full_like(t, v))
    return window_stats(series, np.array([t_eval]), 1.0)


def test_a_steady_plausible_point_is_evaluated():
    assert gate(stats_for(), GateLimits())[0] == Gate.EVALUATING


@pytest.mark.parametrize(
    ("over", "expected"),
    [
        ({"pump_speed_rpm": 500.0}, Gate.LOW_SPEED),
        ({"pump_disp_cc": 5.0}, Gate.LOW_DISPLACEMENT),
        ({"motor_speed_rpm": 250.0}, Gate.LOW_FLOW),
        ({"temp_c": 400.0}, Gate.IMPLAUSIBLE_INPUT),
        ({"motor_speed_rpm": float("nan")}, Gate.IMPLAUSIBLE_INPUT),
    ],
)
def test_rules(over, expected):
    assert gate(stats_for(**over), GateLimits())[0] == expected


def test_outside_the_envelope_is_evaluated_and_marked_extrapolated():
    env = {"dp_bar": (20.0, 560.0)}
    assert gate(stats_for(dp_bar=600.0), GateLimits(), envelope=env)[0] == Gate.EXTRAPOLATED
    assert gate(stats_for(dp_bar=560.0), GateLimits(), envelope=env)[0] == Gate.EVALUATING  # bounds included
    assert Gate.EXTRAPOLATED in EVALUATED and Gate.EVALUATING in EVALUATED
    # every refusal still wins over the envelope: an extrapolated point is a steady, plausible one
    assert gate(stats_for(dp_bar=600.0, pump_speed_rpm=500.0), GateLimits(), envelope=env)[0] == Gate.LOW_SPEED


def test_envelope_and_staleness():
    late = stats_for(t_eval=1.555)  # 5 ms after the newest sample
    assert gate(late, GateLimits(), max_age_s={"dp_bar": 0.004})[0] == Gate.STALE_INPUT
    assert gate(late, GateLimits(), max_age_s={"dp_bar": 0.006})[0] == Gate.EVALUATING


def test_transient_detected_from_spread():
    t = np.arange(0, 2, 0.01)
    series = {
        k: (t, np.full_like(t, v))
        for k, v in {"pump_speed_rpm": 2000.0, "pump_disp_cc": 60.0, "dp_bar": 300.0, "temp_c": 50.0}.items()
    }
    series["motor_speed_rpm"] = (t, 2000 + 200 * t)  # accelerating
    assert gate(window_stats(series, np.array([1.5]), 1.0), GateLimits())[0] == Gate.TRANSIENT


def test_eval_times_are_period_multiples_inside_the_span():
    t = eval_times(1767225600.03, 1767225601.0, 10.0)
    assert t[0] == pytest.approx(1767225600.1) and t[-1] == pytest.approx(1767225601.0)
    assert np.allclose(np.diff(t), 0.1)


def test_scaled_limits_are_the_reference_for_the_reference_drive():
    ref = scaled("motor_speed_rpm", REFERENCE_MOTOR_DISP_CC / 1000.0)
    assert ref == GateLimits()


def test_scaled_limits_follow_a_small_flow_machine():
    # a 4.6 cm3/rev pump at 1450 rpm delivering into a flow meter: 6.67 l/min nominal
    lim = scaled("flow_lpm", 1.0, 1450.0, 4.6)
    assert lim.output_role == "flow_lpm"
    assert lim.min_pump_speed_rpm == pytest.approx(700.0 * 1450 / 3000)
    assert lim.min_pump_disp_cc == pytest.approx(20.0 * 4.6 / 78)
    # the reference's 300 rpm x 44 cm3/rev = 13.2 l/min of 234 l/min nominal, as a share of 6.67 l/min
    assert lim.min_output == pytest.approx(13.2 * 6.67 / 234.0)
    assert lim.max_std["flow_lpm"] == pytest.approx(8.0 * 0.044 * 6.67 / 234.0)
    assert "motor_speed_rpm" not in lim.max_std and "motor_speed_rpm" not in lim.plausible
    means = {"pump_speed_rpm": 1450.0, "pump_disp_cc": 4.6, "dp_bar": 160.0, "temp_c": 40.0, "flow_lpm": 6.6}
    stats = table_stats({k: np.array([v]) for k, v in means.items()})
    assert gate(stats, lim)[0] == Gate.EVALUATING
    # the reference drive's limits refuse the same point (the "only 0 steady points")
    ref = scaled("flow_lpm", 1.0)
    assert gate(stats, ref)[0] == Gate.LOW_DISPLACEMENT


def test_table_points_skip_staleness_and_steadiness_but_not_the_rules():
    lim = scaled("flow_lpm", 1.0, 1450.0, 4.6)
    base = {"pump_speed_rpm": 1450.0, "pump_disp_cc": 4.6, "dp_bar": 160.0, "temp_c": 40.0}
    rows = [
        {**base, "flow_lpm": 6.6},
        {**base, "flow_lpm": 0.1},  # pump off at this cycle
        {**base, "flow_lpm": float("nan")},
        {**base, "temp_c": 500.0, "flow_lpm": 6.6},
    ]
    stats = table_stats({k: np.array([r[k] for r in rows]) for k in rows[0]})
    assert gate(stats, lim).tolist() == [Gate.EVALUATING, Gate.LOW_FLOW, Gate.IMPLAUSIBLE_INPUT, Gate.IMPLAUSIBLE_INPUT]


# -- reverse travel, and the two implementations of the rules ----------------------------------------

FORWARD = {"pump_speed_rpm": 2000.0, "pump_disp_cc": 60.0, "dp_bar": 300.0, "temp_c": 50.0, "motor_speed_rpm": 2600.0}
FLOW_LIMITS = scaled("flow_lpm", 1.0, 1450.0, 4.6)  # a small open circuit: a flow meter, 6.67 l/min nominal
FLOW_FORWARD = {"pump_speed_rpm": 1450.0, "pump_disp_cc": 4.6, "dp_bar": 160.0, "temp_c": 40.0, "flow_lpm": 6.6}


def both_gates(points, limits, std=None, count=None, age=None, max_age_s=None, envelope=None) -> list[int]:
    """The gate of each point by gate_point, after checking that gate_columns gives the same."""
    roles = list(points[0])
    std = std or [dict.fromkeys(roles, 0.0) for _ in points]
    count = count or [dict.fromkeys(roles, 100) for _ in points]
    age = age or [dict.fromkeys(roles, 0.0) for _ in points]
    one = [
        int(gate_point(m, s, c, a, limits, max_age_s, envelope))
        for m, s, c, a in zip(points, std, count, age, strict=True)
    ]
    col = gate_columns(
        {r: np.array([p[r] for p in points], dtype=np.float64) for r in roles},
        {r: np.array([p[r] for p in std], dtype=np.float64) for r in roles},
        {r: np.array([p[r] for p in count], dtype=np.int64) for r in roles},
        {r: np.array([p[r] for p in age], dtype=np.float64) for r in roles},
        limits,
        max_age_s,
        envelope,
    )
    assert col.tolist() == one
    return one


@pytest.mark.parametrize(
    ("over", "expected"),
    [
        ({}, Gate.EVALUATING),
        ({"motor_speed_rpm": -2600.0}, Gate.REVERSE),  # signed motor speed, magnitude displacement
        ({"pump_disp_cc": -60.0}, Gate.REVERSE),  # signed displacement, magnitude motor speed
        ({"pump_disp_cc": -60.0, "motor_speed_rpm": -2600.0}, Gate.REVERSE),  # both signed
        ({"motor_speed_rpm": -9000.0}, Gate.REVERSE),  # the plausible range judges the magnitude
        ({"pump_disp_cc": -20.0}, Gate.REVERSE),  # exactly the minimum displacement, backwards
        ({"motor_speed_rpm": -300.0}, Gate.REVERSE),  # exactly the minimum output, backwards
        ({"motor_speed_rpm": -20000.0}, Gate.IMPLAUSIBLE_INPUT),
        ({"motor_speed_rpm": -9000.25}, Gate.IMPLAUSIBLE_INPUT),
        ({"motor_speed_rpm": 20000.0}, Gate.IMPLAUSIBLE_INPUT),
        ({"pump_disp_cc": -1000.5}, Gate.IMPLAUSIBLE_INPUT),
        ({"pump_disp_cc": -60.0, "temp_c": 400.0}, Gate.IMPLAUSIBLE_INPUT),  # reversing, a broken sensor
        ({"motor_speed_rpm": float("-inf")}, Gate.IMPLAUSIBLE_INPUT),
        ({"motor_speed_rpm": float("nan")}, Gate.IMPLAUSIBLE_INPUT),
        # near zero (a window about a change of direction, a machine at neutral): as before
        ({"pump_disp_cc": -5.0}, Gate.LOW_DISPLACEMENT),
        ({"pump_disp_cc": -0.0, "motor_speed_rpm": -0.0}, Gate.LOW_DISPLACEMENT),
        ({"motor_speed_rpm": -250.0}, Gate.LOW_FLOW),
        ({"motor_speed_rpm": 250.0}, Gate.LOW_FLOW),
        ({"pump_disp_cc": 5.0}, Gate.LOW_DISPLACEMENT),
        # reverse wins over the minimums (reversing with the engine at idle)
        ({"pump_disp_cc": -60.0, "pump_speed_rpm": 500.0}, Gate.REVERSE),
        ({"pump_speed_rpm": 500.0}, Gate.LOW_SPEED),
    ],
)
def test_reverse_travel_is_its_own_gate_in_both_implementations(over, expected):
    assert both_gates([{**FORWARD, **over}], GateLimits()) == [expected]


def test_reverse_comes_after_freshness_and_before_steadiness_and_the_envelope():
    back = {**FORWARD, "pump_disp_cc": -60.0, "motor_speed_rpm": -2600.0}
    roles = list(back)
    assert both_gates(
        [back], GateLimits(), age=[{**dict.fromkeys(roles, 0.0), "dp_bar": 0.9}], max_age_s={"dp_bar": 0.5}
    ) == [Gate.STALE_INPUT]
    assert both_gates([back], GateLimits(), count=[{**dict.fromkeys(roles, 100), "dp_bar": 2}]) == [Gate.WARMING_UP]
    assert both_gates([back], GateLimits(), std=[{**dict.fromkeys(roles, 0.0), "motor_speed_rpm": 50.0}]) == [
        Gate.REVERSE
    ]
    env = {"pump_disp_cc": (10.0, 78.0), "dp_bar": (20.0, 560.0)}
    assert both_gates([back], GateLimits(), envelope=env) == [Gate.REVERSE]
    assert both_gates([FORWARD], GateLimits(), envelope=env) == [Gate.EVALUATING]


def test_reverse_on_a_flow_machine():
    assert both_gates([FLOW_FORWARD], FLOW_LIMITS) == [Gate.EVALUATING]
    assert both_gates([{**FLOW_FORWARD, "flow_lpm": -6.6}], FLOW_LIMITS) == [Gate.REVERSE]
    assert both_gates([{**FLOW_FORWARD, "pump_disp_cc": -4.6}], FLOW_LIMITS) == [Gate.REVERSE]
    hi = FLOW_LIMITS.plausible["flow_lpm"][1]
    assert both_gates([{**FLOW_FORWARD, "flow_lpm": -1.01 * hi}], FLOW_LIMITS) == [Gate.IMPLAUSIBLE_INPUT]


def _pool(role: str, limits: GateLimits) -> list[float]:
    """Values of a role around every edge of the rules, both signs, and the non-finite ones."""
    lo, hi = limits.plausible[role]
    mins = {
        "pump_speed_rpm": limits.min_pump_speed_rpm,
        "pump_disp_cc": limits.min_pump_disp_cc,
        limits.output_role: limits.min_output,
    }
    edges = [lo, hi, np.nextafter(hi, np.inf), np.nextafter(lo, -np.inf), 0.0, -0.0, np.nan, np.inf, -np.inf]
    if role in mins:
        m = mins[role]
        edges += [m, np.nextafter(m, 0.0), 4 * m]
    edges += [-v for v in edges]
    typical = {**FORWARD, **FLOW_FORWARD}[role]
    return [float(v) for v in edges] + [typical] * 6 + [-typical] * 3


@st.composite
def random_points(draw):
    limits = draw(st.sampled_from([GateLimits(), FLOW_LIMITS]))
    roles = ["pump_speed_rpm", "pump_disp_cc", "dp_bar", "temp_c", limits.output_role]
    n = draw(st.integers(1, 12))
    points, stds, counts, ages = [], [], [], []
    for _ in range(n):
        m, s, c, a = {}, {}, {}, {}
        # Mostly fresh, steady points with one or two values off their typical forward value: the
        # gates past freshness and steadiness are reached too, not only STALE_INPUT.
        stale, short, unsteady = (draw(st.integers(0, 9)) == 0 for _ in range(3))
        for r in roles:
            hi = limits.plausible[r][1]
            typical = {**FORWARD, **FLOW_FORWARD}[r]
            m[r] = draw(
                st.one_of(
                    st.just(typical),
                    st.just(typical),
                    st.sampled_from(_pool(r, limits)),
                    st.floats(-2 * hi - 1, 2 * hi + 1),
                )
            )
            s[r] = draw(st.sampled_from([0.1, 100.0, np.nan])) if unsteady else 0.0
            c[r] = draw(st.sampled_from([limits.min_samples, limits.min_samples - 1, 0])) if short else 100
            a[r] = draw(st.sampled_from([0.3, 0.6, np.inf])) if stale else 0.0
        points.append(m)
        stds.append(s)
        counts.append(c)
        ages.append(a)
    max_age = draw(st.sampled_from([None, dict.fromkeys(roles, 0.5)]))
    env = draw(st.sampled_from([None, {"pump_disp_cc": (10.0, 78.0), "dp_bar": (20.0, 560.0)}]))
    return points, limits, stds, counts, ages, max_age, env


def test_gate_point_and_gate_columns_agree_on_random_points():
    """The streaming core's rules and the columnar engine's give the same gate for the same means,
    and the random points reach the gates that matter here (counted, not hoped for)."""
    from collections import Counter

    seen: Counter[str] = Counter()

    @settings(max_examples=400, deadline=None, derandomize=True, database=None)
    @given(random_points())
    def prop(drawn):
        points, limits, stds, counts, ages, max_age, env = drawn
        gates = both_gates(points, limits, stds, counts, ages, max_age, env)
        for g in set(gates):
            event(Gate(g).name)
        seen.update(Gate(g).name for g in gates)

    prop()
    for g in (Gate.REVERSE, Gate.IMPLAUSIBLE_INPUT, Gate.EVALUATING, Gate.LOW_FLOW, Gate.EXTRAPOLATED):
        assert seen[g.name] > 10, (g.name, dict(seen))
