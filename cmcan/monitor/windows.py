"""Trailing-window statistics of a role's samples: the one definition, streaming and batched.

A role's samples are exact integers (the raw values a frame carries, or a difference of two of them)
with an affine map to the role's unit: value = raw * a + b. A window's mean and spread follow from
the exact integer sums S1 = sum(raw) and S2 = sum(raw^2):

    mean = (S1 / n) * a + b        std = |a| * sqrt(n S2 - S1^2) / n

The monitor keeps the sums as samples come and go (:class:`RoleWindow`); a batched reader computes
them from cumulative sums (:func:`window_sums`). Integer sums are exact, and the few floating-point
operations after them are the same in both, so both give the same bits: a replay over arrays and the
daemon frame by frame evaluate the very same operating points.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.codec import layout

# Timestamps come from logs with microsecond resolution and from floats near 1.7e9 s (one ulp is
# 0.24 us): a sample within half a microsecond of a tick or a window edge counts as on it, so the
# same log gives the same windows whatever its format's time base.
TIME_EPS_S = 5e-7


@dataclass(frozen=True)
class Affine:
    """value = raw * a + b."""

    a: float = 1.0
    b: float = 0.0

    def mean(self, s1: int, n: int) -> float:
        return (s1 / n) * self.a + self.b

    def std(self, s1: int, s2: int, n: int) -> float:
        num = n * s2 - s1 * s1
        return abs(self.a) * math.sqrt(float(num)) / n if num > 0 else 0.0


class RoleWindow:
    """One role's samples in arrival order, with running exact sums; trimmed from the front."""

    __slots__ = ("last_t", "rs", "s1", "s2", "ts")

    def __init__(self) -> None:
        self.ts: deque[float] = deque()
        self.rs: deque[int] = deque()
        self.s1 = 0
        self.s2 = 0
        self.last_t = -math.inf

    def add(self, t: float, raw: int) -> None:
        self.ts.append(t)
        self.rs.append(raw)
        self.s1 += raw
        self.s2 += raw * raw
        if t > self.last_t:
            self.last_t = t

    def shift(self, delta_s: float) -> None:
        """The samples moved onto a time base ``delta_s`` later (a wall-clock step)."""
        self.ts = deque(t + delta_s for t in self.ts)
        self.last_t += delta_s

    def clear(self) -> None:
        self.ts.clear()
        self.rs.clear()
        self.s1 = self.s2 = 0
        self.last_t = -math.inf

    def trim(self, t_end: float, window_s: float) -> int:
        """Drop samples at or before t_end - window_s (from the front); the count left."""
        ts, rs = self.ts, self.rs
        cut = t_end - window_s + TIME_EPS_S
        while ts and ts[0] <= cut:
            ts.popleft()
            r = rs.popleft()
            self.s1 -= r
            self.s2 -= r * r
        return len(rs)

    def stats(self, t_end: float, window_s: float, f: Affine) -> tuple[float, float, int]:
        n = self.trim(t_end, window_s)
        if n == 0:
            return math.nan, math.nan, 0
        return f.mean(self.s1, n), f.std(self.s1, self.s2, n), n


def window_sums(
    ts: NDArray[np.float64], raw: NDArray[np.int64] | NDArray[np.float64], t_eval: NDArray[np.float64], window_s: float
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """For time-sorted samples: (S1, S2, n, time of the newest sample) of the window
    ``t - window_s < ts <= t`` at each evaluation time (-inf where nothing came before). Exact for
    integer raw values; for floats, centre them first."""
    hi = np.searchsorted(ts, t_eval + TIME_EPS_S, side="right")
    lo = np.searchsorted(ts, t_eval - window_s + TIME_EPS_S, side="right")
    c1 = np.concatenate([np.zeros(1, raw.dtype), np.cumsum(raw)])
    c2 = np.concatenate([np.zeros(1, raw.dtype), np.cumsum(raw * raw)])
    newest = np.where(hi > 0, ts[np.maximum(hi - 1, 0)] if len(ts) else 0.0, -np.inf)
    return c1[hi] - c1[lo], c2[hi] - c2[lo], hi - lo, newest


def mean_std(
    s1: NDArray[np.int64], s2: NDArray[np.int64], n: NDArray[np.int64], f: Affine
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:meth:`Affine.mean` and :meth:`Affine.std` over arrays (NaN where a window is empty)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (s1.astype(np.float64) / n) * f.a + f.b
        num = n * s2 - s1 * s1
        std = np.where(num > 0, abs(f.a) * np.sqrt(np.maximum(num, 0).astype(np.float64)) / n, 0.0)
    return np.where(n > 0, mean, np.nan), np.where(n > 0, std, np.nan)


def role_affine(msg: Any, signal: str, scale: float = 1.0, offset: float = 0.0) -> Affine:
    """A role's value from its DBC signal's raw value: (raw * s_dbc + o_dbc) * scale + offset."""
    lay = layout(msg, signal)
    return Affine(lay.scale * scale, lay.offset * scale + offset)


def dp_affine(high: Affine, low: Affine) -> tuple[Affine, int, int] | None:
    """dp = high - low as ``Affine`` over raw_dp = p * raw_high - q * raw_low, or None when the two
    resolutions are not in a small integer ratio."""
    pq = commensurate(high.a, low.a)
    if pq is None:
        return None
    p, q, step = pq
    return Affine(step, high.b - low.b), p, q


def dp_raw(
    t_high: NDArray[np.float64],
    raw_high: NDArray[np.int64],
    t_low: NDArray[np.float64],
    raw_low: NDArray[np.int64],
    p: int,
    q: int,
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """dp samples at the high-pressure samples with the newest low-pressure sample at or before
    each (time-sorted inputs), as the monitor forms them frame by frame."""
    idx = np.searchsorted(t_low, t_high, side="right") - 1
    keep = idx >= 0
    return t_high[keep], p * raw_high[keep] - q * raw_low[idx[keep]]


def commensurate(a_high: float, a_low: float, max_den: int = 1000) -> tuple[int, int, float] | None:
    """Integers (p, q) and a step c with a_high = p c and a_low = q c, when the two resolutions
    are in a small ratio: then high - low = c (p r_high - q r_low) + const is exact in integers."""
    if a_high == 0 or a_low == 0:
        return None
    from fractions import Fraction

    ratio = Fraction(a_high / a_low).limit_denominator(max_den)
    if abs(float(ratio) - a_high / a_low) > 1e-12 * abs(a_high / a_low):
        return None
    p, q = ratio.numerator, ratio.denominator
    return p, q, a_high / p
