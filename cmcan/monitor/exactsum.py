"""``math.fsum`` over many windows of one array at once, bit for bit.

The streaming filter averages its ring with ``math.fsum`` (the correctly rounded sum). The columnar
replay needs that sum at every tick, over windows of a long array: prefix sums of the values as exact
integers give every window's exact sum, rounded once at the end.

Each float is an integer times a power of two. When the values' exponents lie within 25 bits of
each other (the usual case: ratios near 100 %, leakages of a few orders of magnitude), each value is
that integer shifted onto a common base, cut into three 26-bit limbs held in int64, whose prefix sums
cannot overflow; a window's exact sum is its limb sums with the carries propagated, and the two
lower limbs together (below 2^52) and the top one are exact floats, so one float addition rounds the
exact sum once, as ``fsum`` does. Anything else (zeros aside: they add nothing; wider exponent
ranges, subnormal results, non-finite values) takes Python's big integers, which are exact for all
finite floats.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

_SPREAD_BITS = 25  # a 53-bit mantissa shifted by at most this fits three 26-bit limbs
_LIMB = 26
_LIMB_MASK = (1 << _LIMB) - 1
_MIN_NORMAL_EXP = -1021  # frexp exponent of the smallest normal float
_MAX_LEN = 1 << 20  # prefix sums of up to this many limbs, and any window's, stay below 2^48


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
    shift = np.where(nz, expo - e_min, 0)  # value = ints * 2^shift * 2^base, shift <= 25
    sign = np.sign(ints)
    mag = np.abs(ints)  # < 2^53, as a low part of 26 bits and a high part of 27, each shifted < 2^52
    a = (mag & _LIMB_MASK) << shift
    b = (mag >> _LIMB) << shift  # weighs 2^26 more than a
    limbs = (
        sign * (a & _LIMB_MASK),
        sign * ((a >> _LIMB) + (b & _LIMB_MASK)),
        sign * (b >> _LIMB),
    )  # the value * 2^-base = limbs[0] + limbs[1] * 2^26 + limbs[2] * 2^52, each |limb| < 2^27
    w = []
    for limb in limbs:  # prefix sums below 2^47 (up to 2^20 values): a window's limb sums are exact
        prefix = np.concatenate([[0], np.cumsum(limb)])
        w.append(prefix[hi] - prefix[lo])
    w0, w1, w2 = w
    carry = w0 >> _LIMB  # the carries up (floor: the lower limbs become 0..2^26-1)
    w0 = w0 - (carry << _LIMB)
    w1 = w1 + carry
    carry = w1 >> _LIMB
    w1 = w1 - (carry << _LIMB)
    w2 = w2 + carry
    low = w1.astype(np.float64) * float(1 << _LIMB) + w0.astype(np.float64)  # exact: below 2^52
    total = w2.astype(np.float64) * float(1 << (2 * _LIMB)) + low  # exact terms: the one rounding
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


def _grow(partials: list[float], x: float) -> None:
    """Add ``x`` to the non-overlapping partials exactly (Shewchuk's algorithm, as ``math.fsum``
    keeps them): afterwards the partials sum to the old exact sum plus ``x``, with no rounding."""
    i = 0
    for y in partials:
        if abs(x) < abs(y):
            x, y = y, x
        hi = x + y
        lo = y - (hi - x)
        if lo:
            partials[i] = lo
            i += 1
        x = hi
    partials[i:] = [x]


class RingSum:
    """The last ``size`` values appended, and ``math.fsum`` of them bit for bit, kept as the exact
    sum's partials while values come and go: a handful of float operations per value where a sum over
    the whole ring (300 values) would cost microseconds at every tick. Non-finite values (and a sum
    beyond the float range) are left to ``math.fsum`` over the ring, which says what they make."""

    __slots__ = ("_odd", "_partials", "ring")

    def __init__(self, size: int, values: Iterable[float] = ()) -> None:
        self.ring: deque[float] = deque(values, maxlen=size)
        self._partials: list[float] | None = None  # made when first asked for
        self._odd = 0  # non-finite values in the ring

    def append(self, x: float) -> None:
        ring = self.ring
        if self._partials is not None:
            if len(ring) == ring.maxlen:
                self._take(ring[0], -1)
            self._take(x, 1)
        ring.append(x)

    def _take(self, x: float, sign: int) -> None:
        if math.isfinite(x):
            _grow(self._partials, -x if sign < 0 else x)  # type: ignore[arg-type]
        else:
            self._odd += sign

    def total(self) -> float:
        """``math.fsum(ring)``."""
        p = self._partials
        if p is None:
            p = self._partials = []
            self._odd = 0
            for v in self.ring:
                self._take(v, 1)
        if self._odd or (p and not math.isfinite(p[-1])):
            if p and not math.isfinite(p[-1]):
                self._partials = None  # an overflow: made afresh the next time
            return math.fsum(self.ring)
        return math.fsum(p)
