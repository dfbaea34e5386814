"""``math.fsum`` over many windows of one array at once, bit for bit.

The streaming filter averages its ring with ``math.fsum`` (the correctly rounded sum). The columnar
replay needs that sum at every tick, over windows of a long array: prefix sums of the values as exact
integers give every window's exact sum, rounded once at the end.

Each float is an integer times a power of two. When the values' exponents lie within a few bits of
each other (the usual case: ratios near 100 %, leakages of one order) those integers fit int64 split
into 32-bit halves, whose prefix sums cannot overflow, and the window's exact sum ``hi * 2^32 + lo``
is rounded by one float addition of two exactly representable parts. Anything else (zeros aside:
they add nothing; wide exponent ranges, subnormal results, non-finite values) takes Python's big
integers, which are exact for all finite floats.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

_SPREAD_BITS = 9  # mantissa (53 bits) shifted by at most this stays below 2^62
_MIN_NORMAL_EXP = -1021  # frexp exponent of the smallest normal float
_MAX_LEN = 1 << 20  # prefix sums of up to this many halves, and any window's, stay below 2^53


def window_fsums(values: NDArray[np.float64], lo: NDArray[np.int64], hi: NDArray[np.int64]) -> NDArray[np.float64]:
    """``math.fsum(values[lo[i]:hi[i]])`` for every i."""
    values = np.asarray(values, dtype=np.float64)
    lo = np.asarray(lo, dtype=np.int64)
    hi = np.asarray(hi, dtype=np.int64)
    if not len(values):
        return np.zeros(len(lo))
    if len(values) >= _MAX_LEN or not np.isfinite(values).all():
        return _python_sums(values, lo, hi)
    mant, expo = np.frexp(values)
    ints = (mant * float(1 << 53)).astype(np.int64)  # exact: value = ints * 2^(expo - 53)
    nz = ints != 0
    if not nz.any():
        return np.zeros(len(lo))
    e_min, e_max = int(expo[nz].min()), int(expo[nz].max())
    if e_max - e_min > _SPREAD_BITS or e_min - 53 < _MIN_NORMAL_EXP - 53:
        return _python_sums(values, lo, hi)
    base = e_min - 53
    x = ints << np.where(nz, expo - e_min, 0)  # value = x * 2^base, |x| < 2^62
    # 32-bit halves (hi half signed, lo half in [0, 2^32)): their prefix sums stay far from overflow
    x_hi = x >> 32
    x_lo = x & 0xFFFFFFFF
    p_hi = np.concatenate([[0], np.cumsum(x_hi)])
    p_lo = np.concatenate([[0], np.cumsum(x_lo)])
    s_hi = (p_hi[hi] - p_hi[lo]).astype(np.float64) * float(1 << 32)  # exact (|s_hi| < 2^53)
    s_lo = (p_lo[hi] - p_lo[lo]).astype(np.float64)  # exact (< 2^53)
    total = s_hi + s_lo  # the one rounding of the exact sum
    out = np.ldexp(total, base)
    # scaling by a power of two is exact unless the result leaves the normal range
    tiny = (out != 0.0) & (np.abs(out) < np.finfo(np.float64).tiny)
    if tiny.any() or not np.isfinite(out).all():
        return _python_sums(values, lo, hi)
    return out


def _python_sums(values: NDArray[np.float64], lo: NDArray[np.int64], hi: NDArray[np.int64]) -> NDArray[np.float64]:
    """The same with Python integers: any finite floats; non-finite ones as fsum treats them."""
    import math

    if not np.isfinite(values).all():
        vals = values.tolist()
        return np.array([math.fsum(vals[a:b]) for a, b in zip(lo.tolist(), hi.tolist(), strict=True)])
    mant, expo = np.frexp(values)
    ints = (mant * float(1 << 53)).astype(np.int64)
    shift = expo - 53
    base = int(shift.min())
    exact = np.empty(len(values) + 1, dtype=object)
    exact[0] = 0
    exact[1:] = [int(i) << int(s - base) for i, s in zip(ints.tolist(), shift.tolist(), strict=True)]
    prefix = np.cumsum(exact)
    sums = prefix[hi] - prefix[lo]
    if base >= 0:
        return np.array([float(s << base) for s in sums.tolist()])
    scale = 2 ** (-base)
    return np.array([s / scale for s in sums.tolist()])
