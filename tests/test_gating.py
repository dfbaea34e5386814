"""Window statistics and gate rules (property tests against a naive reference)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.monitor.gating import Gate, GateLimits, eval_times, gate, window_stats
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
        ({"pump_disp_cc": 5.0}, Gate.LOW_SPEED),
        ({"temp_c": 400.0}, Gate.IMPLAUSIBLE_INPUT),
        ({"motor_speed_rpm": float("nan")}, Gate.IMPLAUSIBLE_INPUT),
    ],
)
def test_rules(over, expected):
    assert gate(stats_for(**over), GateLimits())[0] == expected


def test_envelope_and_staleness():
    s = stats_for(dp_bar=600.0)
    assert gate(s, GateLimits(), envelope={"dp_bar": (20.0, 560.0)})[0] == Gate.OUTSIDE_ENVELOPE
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
