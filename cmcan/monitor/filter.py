"""The moving average of the last N evaluated CM ratios and leakage estimates.

One value at a time (:meth:`RatioFilter.add`), or the values of a stretch of ticks at once
(:meth:`RatioFilter.add_columns`) with the average at every tick: ``math.fsum`` over the ring, kept
as exact partials one value at a time and from exact prefix sums over a stretch
(:mod:`cmcan.monitor.exactsum`), bit for bit the same.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.exactsum import RingSum, window_fsums


class RatioFilter:
    __slots__ = ("_leaks", "_ratios", "min_samples", "samples")

    def __init__(
        self, samples: int, min_samples: int, ratios: Iterable[float] = (), leaks: Iterable[float] = ()
    ) -> None:
        self.samples = samples
        self.min_samples = min_samples
        self._ratios = RingSum(samples, ratios)  # a saved filter, oldest first
        self._leaks = RingSum(samples, leaks)

    @property
    def ratios(self) -> deque[float]:
        return self._ratios.ring

    @property
    def leaks(self) -> deque[float]:
        return self._leaks.ring

    def add(self, ratio_pct: float, leak_lpm: float) -> None:
        self._ratios.append(ratio_pct)
        self._leaks.append(leak_lpm)

    def __len__(self) -> int:
        return len(self._ratios.ring)

    @property
    def valid(self) -> bool:
        return len(self._ratios.ring) >= self.min_samples

    @property
    def ratio_pct(self) -> float:
        n = len(self._ratios.ring)
        return self._ratios.total() / n if n else 0.0

    @property
    def leak_lpm(self) -> float:
        n = len(self._leaks.ring)
        return self._leaks.total() / n if n else 0.0

    def saved(self) -> tuple[list[float], list[float]]:
        """The ring's contents, oldest first (for the state file)."""
        return list(self.ratios), list(self.leaks)

    def add_columns(
        self, ratios: NDArray[np.float64], leaks: NDArray[np.float64], e_idx: NDArray[np.int64], n_ticks: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        """Over ``n_ticks`` ticks, the values of the evaluated ones (at ticks ``e_idx``) added in turn:
        the filtered ratio, leakage and validity after each tick, as :attr:`ratio_pct`,
        :attr:`leak_lpm` and :attr:`valid` read after adding one by one."""
        size = self.samples
        all_r = list(self.ratios) + ratios.tolist()
        all_l = list(self.leaks) + leaks.tolist()
        # the ring after each tick: the last `size` of the values evaluated so far
        done = np.searchsorted(e_idx, np.arange(n_ticks), side="right") + len(self.ratios)
        lo = np.maximum(done - size, 0)
        cnt = done - lo
        sum_r = window_fsums(np.array(all_r), lo, done)
        sum_l = window_fsums(np.array(all_l), lo, done)
        with np.errstate(invalid="ignore", divide="ignore"):
            filt = np.where(cnt > 0, sum_r / np.maximum(cnt, 1), 0.0)
            filt_leak = np.where(cnt > 0, sum_l / np.maximum(cnt, 1), 0.0)
        self._ratios = RingSum(size, all_r[-size:])
        self._leaks = RingSum(size, all_l[-size:])
        return filt, filt_leak, cnt >= self.min_samples
