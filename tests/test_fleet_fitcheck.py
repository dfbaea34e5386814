"""The fit check: a machine whose ratio sits far from 100 % from its first hour is read with the wrong
configuration or model (cmcan.fitcheck, a pure function both the fleet and replay use)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st

from cmcan.fitcheck import (
    DOES_NOT_FIT,
    FIT_BAND_PCT,
    FIT_MIN_POINTS,
    FIT_WINDOW_H,
    FITS,
    UNKNOWN,
    check_fit,
    first_points,
)


def hours(n: int, span_h: float) -> np.ndarray:
    return np.linspace(0.0, span_h, n)


@pytest.mark.parametrize(
    ("level", "want"),
    [(100.0, FITS), (98.5, FITS), (104.9, FITS), (137.5, DOES_NOT_FIT), (54.8, DOES_NOT_FIT), (94.0, DOES_NOT_FIT)],
)
def test_the_median_of_the_first_hour_against_the_band(level, want):
    rng = np.random.default_rng(1)
    v = check_fit(hours(2000, 0.9), level + rng.normal(0, 0.8, 2000))
    assert v.verdict == want
    assert v.median_pct == pytest.approx(level, abs=0.2)
    assert v.points == 2000 and v.window_h == FIT_WINDOW_H
    assert ("does not fit" in v.describe()) == (want == DOES_NOT_FIT)


def test_only_the_first_hour_is_judged_so_later_wear_is_not_a_misfit():
    h = hours(20000, 50.0)  # a drive that wears from 100 % to 60 % over 50 h
    r = 100.0 - 0.8 * h
    v = check_fit(h, r)
    assert v.verdict == FITS
    assert v.points == int(np.searchsorted(h, 1.0, side="right"))


def test_too_few_points_in_the_first_hour_take_the_first_min_points():
    h = np.concatenate([hours(100, 0.9), 2.0 + hours(1000, 5.0)])  # a time-lapse: sparse data
    r = np.full(len(h), 130.0)
    v = check_fit(h, r)
    assert v.points == FIT_MIN_POINTS and v.verdict == DOES_NOT_FIT and v.window_h > FIT_WINDOW_H
    few = check_fit(hours(FIT_MIN_POINTS - 1, 10.0), np.full(FIT_MIN_POINTS - 1, 130.0))
    assert few.verdict == UNKNOWN and few.fits is None and "not judged" in few.describe()
    none = check_fit([], [])
    assert none.verdict == UNKNOWN and math.isnan(none.median_pct) and none.points == 0


def test_nan_points_are_left_out_and_lengths_must_agree():
    h = hours(1000, 0.5)
    r = np.full(1000, 100.0)
    r[::2] = np.nan
    assert check_fit(h, r).points == 500
    with pytest.raises(ValueError, match="differ in length"):
        check_fit(h, r[:10])


@settings(max_examples=80, deadline=None)
@given(
    st.floats(40.0, 160.0),
    st.integers(0, 3000),
    st.floats(0.1, 5.0),
)
def test_verdict_is_the_median_inside_the_band(level, n, span_h):
    h = hours(n, span_h)
    r = np.full(n, level)
    v = check_fit(h, r)
    judged = first_points(h)
    event(f"verdict {v.verdict}")
    assert v.points == judged
    if judged < FIT_MIN_POINTS:
        assert v.verdict == UNKNOWN
    else:
        lo, hi = FIT_BAND_PCT
        assert v.verdict == (FITS if lo <= level <= hi else DOES_NOT_FIT)
