"""Does the configuration and model fit this machine at all? A verdict from its first operating hour.

A healthy drive with the right configuration and model reads close to 100 %: the shipped and the
simulated fleet's models have a residual of about 1 rpm (their D_tst ratios lie within 99.7-100.3 %
from percentile 1 to 99), and a new drive's displacement tolerance adds a percent or two. Wear and a
mispositioned displacement move the ratio later in a machine's life and slowly: the warning
thresholds sit at 98 and 102 %. A machine whose evaluated ratios sit far from 100 % *from its first
hour* is therefore read with the wrong configuration (another drive size: a motor displacement of
another machine type gives 55 % or 137 %) or the wrong model, or was already worn when monitoring
began; the ratio says nothing about its wear then, and it must not be ranked as a worn drive.

The band is :data:`FIT_BAND_PCT` (95-105 %): two and a half times the warning thresholds' distance
from 100 %, wide enough that a healthy drive and the model's error never leave it, narrow enough that
one step of a motor's displacement setting or one drive size (20 % and more) always does.

Pure: arrays in, a verdict out. ``cmcan fleet`` judges each machine's first log with it and
``cmcan replay`` a log's first hour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cmcan.monitor.gating import EVALUATED
from cmcan.monitor.tick import TickColumns

_EVALUATED = np.array(sorted(int(g) for g in EVALUATED), dtype=np.int8)

FIT_BAND_PCT = (95.0, 105.0)
FIT_WINDOW_H = 1.0  # the machine's first operating hour...
FIT_MIN_POINTS = 300  # ...or its first 300 evaluated ticks (30 s: the filter's default length) if that is longer

FITS = "fits"
DOES_NOT_FIT = "does_not_fit"
UNKNOWN = "unknown"  # too few evaluated points to judge


@dataclass(frozen=True)
class FitVerdict:
    verdict: str  # FITS, DOES_NOT_FIT or UNKNOWN
    median_pct: float  # median of the judged ratios (NaN without any)
    points: int  # evaluated ticks judged
    window_h: float  # operating hours they span from the start
    band_pct: tuple[float, float] = FIT_BAND_PCT

    @property
    def fits(self) -> bool | None:
        return None if self.verdict == UNKNOWN else self.verdict == FITS

    def describe(self) -> str:
        lo, hi = self.band_pct
        if self.verdict == UNKNOWN:
            return f"fit not judged: {self.points} evaluated points in the first hours (needs {FIT_MIN_POINTS})"
        if self.verdict == FITS:
            return f"median ratio {self.median_pct:.1f} % in the first {self.window_h:.2f} h: within {lo:g}-{hi:g} %"
        return (
            f"configuration or model does not fit: median ratio {self.median_pct:.1f} % over the first "
            f"{self.window_h:.2f} operating hours ({self.points} evaluated points), outside {lo:g}-{hi:g} %; "
            "the ratio says nothing about wear until the configuration (drive size, V_M) and model are right"
        )


def first_points(op_h: ArrayLike, min_points: int = FIT_MIN_POINTS, window_h: float = FIT_WINDOW_H) -> int:
    """How many of the evaluated points (``op_h``: their operating hours since the start, ascending)
    the verdict judges: those of the first ``window_h`` hours, or the first ``min_points`` if the
    window holds fewer."""
    h = np.asarray(op_h, dtype=np.float64)
    in_window = int(np.searchsorted(h, window_h, side="right"))
    return min(len(h), max(in_window, min_points))


def check_fit(
    op_h: ArrayLike,
    ratio_pct: ArrayLike,
    band_pct: tuple[float, float] = FIT_BAND_PCT,
    window_h: float = FIT_WINDOW_H,
    min_points: int = FIT_MIN_POINTS,
) -> FitVerdict:
    """The verdict over evaluated ticks (``op_h`` hours since the machine's start, ascending, and
    their raw CM ratios in %): the median of the first points (:func:`first_points`) inside
    ``band_pct`` fits, outside does not; fewer than ``min_points`` is unknown."""
    h = np.asarray(op_h, dtype=np.float64)
    r = np.asarray(ratio_pct, dtype=np.float64)
    if h.shape != r.shape:
        raise ValueError(f"op_h and ratio_pct differ in length ({h.size} and {r.size})")
    ok = np.isfinite(h) & np.isfinite(r)
    h, r = h[ok], r[ok]
    n = first_points(h, min_points, window_h)
    h, r = h[:n], r[:n]
    span = float(h[-1]) if n else 0.0
    if n == 0:
        return FitVerdict(UNKNOWN, math.nan, 0, span, band_pct)
    median = median_of_finite(r)
    if n < min_points:
        return FitVerdict(UNKNOWN, median, n, span, band_pct)
    lo, hi = band_pct
    return FitVerdict(FITS if lo <= median <= hi else DOES_NOT_FIT, median, n, max(span, window_h), band_pct)


def median_of_finite(r: NDArray[np.float64]) -> float:
    """``np.median`` of a 1-D array of finite values (not empty), to the bit: np.median checks its
    result for NaN through ``np.ma``, a 45 ms import a replay otherwise pays for this one number."""
    s = np.sort(r)
    k = s.size // 2
    return float(s[k]) if s.size % 2 else float((s[k - 1] + s[k]) / 2.0)


class FitWindow:
    """The evaluated raw ratios of a log's first operating hours, as :func:`cmcan.fitcheck.check_fit`
    judges them; stops collecting once past both its window and its minimum of points."""

    def __init__(self, t0: float = 0.0) -> None:
        self.t0 = t0
        self._h: list[NDArray[np.float64]] = []
        self._r: list[NDArray[np.float64]] = []
        self._n = 0
        self.full = False

    def add(self, c: TickColumns) -> None:
        if self.full:
            return
        ev = np.isin(c.gate, _EVALUATED)
        if not ev.any():
            return
        h = (c.t_run_s[ev] - self.t0) / 3600.0
        self._h.append(h)
        self._r.append(c.ratio_raw_pct[ev].astype(np.float64))
        self._n += len(h)
        if self._n >= FIT_MIN_POINTS and h[-1] > FIT_WINDOW_H:
            self.full = True

    # as a replay's sink (ticks only)
    wants_ticks = True
    wants_frames = False

    def start(self, t0: float) -> None:
        self.t0 = t0

    def ticks(self, chunk: TickColumns) -> None:
        self.add(chunk)

    def frames(self, frames: object) -> None:
        pass

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass

    def verdict(self) -> FitVerdict:
        h = np.concatenate(self._h) if self._h else np.zeros(0)
        r = np.concatenate(self._r) if self._r else np.zeros(0)
        return check_fit(h, r)
