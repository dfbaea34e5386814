"""The prognosis benchmark's metrics (bench/prognostics_metrics.py) against NASA's progpy on random estimate
profiles: alpha-lambda, the prognostic horizon and relative accuracy as progpy computes them."""

from __future__ import annotations

import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from bench import prognostics_metrics as mx

progpy_metrics = pytest.importorskip("progpy.metrics")
from progpy.predictors import ToEPredictionProfile  # noqa: E402
from progpy.uncertain_data import ScalarData  # noqa: E402

ALPHA = 0.2


@st.composite
def profiles(draw):
    """Estimates every ``step`` hours up to end of life, each off the truth by a random share (some
    within alpha, some not), and the true end of life."""
    eol = draw(st.floats(30.0, 300.0))
    first = draw(st.floats(0.0, eol * 0.8))
    step = draw(st.floats(0.5, 10.0))
    est, t = [], first
    while t < eol:
        rul = eol - t
        # off by a share, never alpha to the last bit (where rounding, not the rule, would decide)
        err = draw(st.floats(-0.6, 0.6).filter(lambda x: abs(abs(x) - ALPHA) > 1e-6))
        p50 = max(0.0, rul * (1.0 + err))
        est.append(mx.Estimate(t, p50 * 0.7, p50, p50 * 1.4))
        t += step
    return est, eol


def _profile(est: list[mx.Estimate]) -> ToEPredictionProfile:
    p = ToEPredictionProfile()
    for e in est:
        p.add_prediction(e.at_h, ScalarData({"eol": e.at_h + e.p50}))
    return p


@settings(max_examples=200, deadline=None)
@given(profiles(), st.sampled_from([0.5, 0.75]))
def test_alpha_lambda_is_progpys(case, lam):
    est, eol = case
    t_p = est[0].at_h
    t_l = t_p + lam * (eol - t_p)
    theirs = progpy_metrics.alpha_lambda(_profile(est), {"eol": eol}, t_l, ALPHA, 0.5)
    ours = mx.alpha_lambda(est, eol, lam, ALPHA)
    event("no estimate at lambda" if theirs is None else ("hit" if ours else "miss"))
    assert ours == (theirs is not None and theirs["eol"])


@settings(max_examples=200, deadline=None)
@given(profiles())
def test_the_prognostic_horizon_is_progpys(case):
    est, eol = case

    def criteria(tte, gt_tte):
        return {k: abs(tte.mean[k] - v) <= ALPHA * v for k, v in gt_tte.items()}

    theirs = progpy_metrics.prognostic_horizon(_profile(est), criteria, {"eol": eol})["eol"]
    ours = mx.horizon_first(est, eol, ALPHA)
    event("never within" if theirs is None else "within at some point")
    assert ours == pytest.approx(theirs if theirs is not None else 0.0, abs=1e-9)
    assert mx.horizon_stays(est, eol, ALPHA) <= ours  # staying within starts no sooner than entering


@settings(max_examples=100, deadline=None)
@given(profiles())
def test_relative_accuracy_is_progpys(case):
    est, eol = case
    for e in est:
        rul = eol - e.at_h
        theirs = ScalarData({"eol": e.p50}).relative_accuracy({"eol": rul})["eol"]
        assert mx.relative_accuracy(e, eol) == pytest.approx(theirs, rel=1e-12, abs=1e-12)


def test_late_and_coverage_on_a_hand_made_profile():
    est = [mx.Estimate(10.0, 60.0, 80.0, 85.0), mx.Estimate(80.0, 10.0, 26.0, 30.0), mx.Estimate(90.0, 5, 9, 12)]
    eol = 100.0
    assert mx.lateness(est, eol, 20.0) == "late"  # at 80 h: 26 h promised, 20 true, +30 %
    assert mx.lateness(est, eol, 10.0) == "ok"  # at 90 h: 9 of 10
    assert mx.lateness(est, eol, 95.0) == "none"  # nothing before 5 h
    assert mx.coverage(est, eol) == (2, 3)  # 90 h left at 10 h: not in [60, 85]; 20 in [10, 30]; 10 in [5, 12]
