"""Window sums from exact integer prefix sums are math.fsum of each window, bit for bit."""

import math

import numpy as np
from hypothesis import event, given, settings
from hypothesis import strategies as st

import cmcan.monitor.exactsum as exactsum
from cmcan.monitor.exactsum import window_fsums


def bits(xs):
    return np.asarray(xs, dtype=np.float64).view(np.int64).tolist()


near_100 = st.floats(90.0, 110.0)
anything = st.floats(allow_nan=False, allow_infinity=False)
small = st.floats(-5.0, 5.0)
leak = st.floats(1e-7, 0.5) | st.floats(-0.5, -1e-7)  # leakages: a few orders of magnitude, both signs
values = st.lists(st.one_of(near_100, small, leak, anything, st.just(0.0), st.just(-0.0)), min_size=1, max_size=80)


@settings(max_examples=500, deadline=None)
@given(values, st.data())
def test_window_sums_equal_fsum(xs, data):
    n = len(xs)
    size = data.draw(st.integers(1, n))
    hi = np.arange(1, n + 1)
    lo = np.maximum(hi - size, 0)
    try:
        want = [math.fsum(xs[a:b]) for a, b in zip(lo, hi, strict=True)]
    except OverflowError:
        event("fsum overflows")
        return
    got = window_fsums(np.array(xs), lo, hi)
    assert bits(got) == bits(want)  # bit for bit: the sign of a zero too
    e = np.frexp(np.array([x for x in xs if x != 0] or [1.0]))[1]
    spread = e.max() - e.min()
    event("exponents within 9 bits" if spread <= 9 else "within 25 bits" if spread <= 25 else "wider (big integers)")


@settings(max_examples=200, deadline=None)
@given(st.lists(near_100, min_size=1, max_size=200), st.integers(1, 50))
def test_ratios_near_100_take_the_fast_path_and_agree(xs, size):
    hi = np.arange(1, len(xs) + 1)
    lo = np.maximum(hi - size, 0)
    assert bits(window_fsums(np.array(xs), lo, hi)) == bits([math.fsum(xs[a:b]) for a, b in zip(lo, hi, strict=True)])


def test_empty_and_zero_windows():
    assert window_fsums(np.array([]), np.array([0]), np.array([0])).tolist() == [0.0]
    assert window_fsums(np.array([0.0, 0.0]), np.array([0, 1]), np.array([2, 1])).tolist() == [0.0, 0.0]


def test_leakages_over_orders_of_magnitude_take_the_limb_path_and_agree(monkeypatch):
    """Extra leakages from 1e-5 to 0.1 l/min (exponents 14 bits apart, the replay's usual filter
    window) are summed in int64 limbs, not Python integers, and each window is fsum's, bit for bit."""

    def no_big_integers(*_):
        raise AssertionError("took the big-integer path")

    rng = np.random.default_rng(7)
    for spread_decades in (4, 5.5, 7):  # 10^4 to 10^7: about 13 to 23 bits of exponent
        xs = 0.1 * 10.0 ** -rng.uniform(0, spread_decades, 3000) * rng.choice([-1.0, 1.0], 3000)
        e = np.frexp(xs)[1]
        assert 9 < e.max() - e.min() <= exactsum._SPREAD_BITS
        hi = np.arange(1, len(xs) + 1)
        lo = np.maximum(hi - 250, 0)
        want = [math.fsum(xs[a:b].tolist()) for a, b in zip(lo, hi, strict=True)]
        with monkeypatch.context() as m:
            m.setattr(exactsum, "_python_sums", no_big_integers)
            got = window_fsums(xs, lo, hi)
        assert bits(got) == bits(want)
