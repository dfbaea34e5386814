"""Window sums from exact integer prefix sums are math.fsum of each window, bit for bit."""

import math
from fractions import Fraction

import numpy as np
import pytest
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
element = st.one_of(near_100, small, leak, anything, st.just(0.0), st.just(-0.0))
values = st.lists(element, min_size=1, max_size=80)


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


nonfinite = st.sampled_from([math.inf, -math.inf, math.nan])
huge = st.floats(1e307, 1.79e308) | st.floats(-1.79e308, -1e307)  # two of them: beyond the float range


def _fsum_or_error(xs):
    try:
        return math.fsum(xs)
    except (OverflowError, ValueError) as exc:  # a sum beyond the range, inf + -inf
        return type(exc)


@settings(max_examples=500, deadline=None)
@given(st.lists(element | nonfinite | huge, min_size=1, max_size=120), st.data())
def test_a_ring_sum_kept_value_by_value_is_fsum_of_the_ring(xs, data):
    """RingSum (the streaming filter's) after every append is math.fsum of the ring, bit for bit
    (zeros' signs, non-finite values and overflows as fsum has them); whether it was first asked
    for before the ring filled, after, or at the start with saved values."""
    size = data.draw(st.integers(1, 40))
    first = data.draw(st.integers(0, len(xs)))  # the first total asked for after this many appends
    saved = data.draw(st.integers(0, min(size, len(xs))))
    ring = exactsum.RingSum(size, xs[:saved])
    for i, x in enumerate(xs[saved:], start=saved):
        ring.append(x)
        window = xs[max(0, i + 1 - size) : i + 1]
        assert list(ring.ring) == window or any(v != v for v in window)
        if i + 1 < first:
            continue
        want = _fsum_or_error(window)
        try:
            got = ring.total()
        except (OverflowError, ValueError) as exc:
            got = type(exc)
        if isinstance(want, float) and isinstance(got, float):
            assert bits([got]) == bits([want]) or (want != want and got != got)
        elif want is OverflowError and isinstance(got, float):
            # fsum gives up on an intermediate overflow its order of adding met; the partials may
            # not meet it: then the sum is the exact one, rounded (and not beyond the range)
            assert got == float(sum(map(Fraction, window)))
        else:
            assert got == want
        event("non-finite in the ring" if not all(math.isfinite(v) for v in window) else "finite ring")
        event("the sum overflows" if want is OverflowError else "the sum is a float or inf + -inf")
        event("ring full" if i + 1 > size else "ring filling")


def test_a_ring_sum_past_the_float_range_and_back():
    """Two huge values overflow the sum (fsum raises, as the ring's fsum did); once one has left
    the ring the sum is exact again."""
    ring = exactsum.RingSum(2)
    for x in (1.0, 1.7e308, 1.7e308, 3.0, 0.5):
        ring.append(x)
        try:
            want = math.fsum(ring.ring)
        except OverflowError:
            want = None
        if want is None:
            with pytest.raises(OverflowError):
                ring.total()
        else:
            assert ring.total() == want
    assert ring.total() == 3.5
