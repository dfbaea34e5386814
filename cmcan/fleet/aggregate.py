"""Per-log reductions of the evaluation ticks, chunk by chunk: memory bounded by a chunk, not a log.

- :class:`Downsampler` turns the 10 Hz ticks into rows at a coarser rate (1 Hz by default): one row
  per bin of ``1 / rate_hz`` seconds of frame time that has ticks, with means, last values and the
  worst warning level. Which reduction a tick field gets is a table (:data:`REDUCTIONS`); a field
  the table does not name (a column added to ``TickColumns`` later) gets a default by its type, so
  the timeline grows with the monitor without code here.
- :class:`LogStats` keeps what a log's summary needs: ratio percentiles (a fixed 0.01 % histogram),
  the least-squares trend of the ratio and of the extra leakage over the log's hours, first and
  last filtered ratio.
- :class:`FitWindow` keeps the evaluated ratios of the log's first hours for the fit check
  (:mod:`cmcan.fitcheck`), and no more.

Both are pure (arrays in, arrays out); :mod:`cmcan.fleet.task` wires them to the replay as sinks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.gating import EVALUATED
from cmcan.monitor.tick import BASELINE_PROGRESS, OPERATING_POINT, PROGNOSIS_CODES, PROGNOSIS_HOURS, TickColumns

_EVALUATED = np.array(sorted(int(g) for g in EVALUATED), dtype=np.int8)  # a ratio, inside the envelope or not

# How each tick field becomes a timeline column (name, reduction):
#   mean_eval   mean over the evaluated ticks of the bin (NaN if none): quantities only defined there
#   mean        mean over all ticks of the bin
#   last        the bin's last tick
#   last_valid  the last tick whose filtered ratio is valid (NaN if none)
#   max         the largest value (for the warning level: the worst of the bin)
#   share       share of ticks where the flag is set
REDUCTIONS: dict[str, tuple[str, str]] = {
    "gate": ("gate", "last"),
    # the output quantity (motor speed in rpm or flow in l/min, as the log's configuration says)
    "measured": ("measured", "mean"),
    "predicted": ("predicted", "mean_eval"),
    "whitebox": ("whitebox", "mean_eval"),
    "ratio_raw_pct": ("cm_ratio_raw_pct", "mean_eval"),
    "ratio_filt_pct": ("cm_ratio_filt_pct", "last_valid"),
    "extra_leak_lpm": ("extra_leak_lpm", "last_valid"),
    "filt_valid": ("cm_filt_valid", "last"),
    "level": ("warning_level", "max"),
    "reason": ("warning_reason", "last"),
    "time_below_s": ("time_below_threshold_s", "last"),
    # the operating point of the evaluated ticks: what a type model trains on (``cmcan fleet train``)
    **{role: (role, "mean_eval") for role in OPERATING_POINT},
    "baseline_state": ("baseline_state", "last"),
    **{name: (name, "last") for name in BASELINE_PROGRESS},
    **{name: (name, "last") for name in PROGNOSIS_CODES},
    **{name: (name, "last") for name in PROGNOSIS_HOURS},
}


def reduction_of(name: str, dtype: np.dtype) -> tuple[str, str]:
    """A field's column and reduction: from the table, else by type (float mean, flag share, else last)."""
    if name in REDUCTIONS:
        return REDUCTIONS[name]
    if dtype == np.bool_:
        return f"{name}_share", "share"
    if np.issubdtype(dtype, np.floating):
        return name, "mean"
    return name, "last"


# Not a timeline column: the clock's steps undone, which only the rows' log time takes (RUN_SHIFT)
_NOT_COLUMNS = ("t_s", "run_shift_s")
RUN_SHIFT = "_run_shift_s"


def _fields(c: TickColumns) -> list[str]:
    return [f.name for f in fields(c) if f.name not in _NOT_COLUMNS]


def _slice(c: TickColumns, a: int, b: int | None = None) -> TickColumns:
    return type(c)(**{f.name: getattr(c, f.name)[a:b] for f in fields(c)})


def reduce_runs(c: TickColumns, rate_hz: float) -> dict[str, NDArray[Any]]:
    """One row per run of consecutive ticks in the same bin of ``1 / rate_hz`` s: ``time_s`` (the
    bin's start), ``ticks``, ``evaluated`` and a column per tick field (see :data:`REDUCTIONS`)."""
    n = len(c)
    if n == 0:
        return {}
    bins = np.floor(c.t_s * rate_hz + 1e-9)
    starts = np.concatenate([[0], np.flatnonzero(np.diff(bins) != 0) + 1])
    ends = np.append(starts[1:], n)
    count = (ends - starts).astype(np.int64)
    ev = np.isin(c.gate, _EVALUATED)
    n_ev = np.add.reduceat(ev.astype(np.int64), starts)
    valid = c.filt_valid.astype(bool)
    # index of the last valid tick at or before each position (-1: none yet)
    last_valid_idx = np.maximum.accumulate(np.where(valid, np.arange(n), -1))
    out: dict[str, NDArray[Any]] = {
        "time_s": bins[starts] / rate_hz,
        "ticks": count,
        "evaluated": n_ev,
        # time_s + this: the row on the log's continuous time base (the wall clock's steps undone)
        RUN_SHIFT: c.run_shift_s[ends - 1],
    }
    for name in _fields(c):
        x = getattr(c, name)
        col, how = reduction_of(name, x.dtype)
        if how == "last":
            out[col] = x[ends - 1]
        elif how == "max":
            out[col] = np.maximum.reduceat(x, starts)
        elif how == "share":
            out[col] = np.add.reduceat(x.astype(np.float64), starts) / count
        elif how == "mean":
            xf = x.astype(np.float64)
            ok = np.isfinite(xf)
            s = np.add.reduceat(np.where(ok, xf, 0.0), starts)
            k = np.add.reduceat(ok.astype(np.int64), starts)
            with np.errstate(invalid="ignore", divide="ignore"):
                out[col] = np.where(k > 0, s / np.maximum(k, 1), np.nan)
        elif how == "mean_eval":
            xf = x.astype(np.float64)
            s = np.add.reduceat(np.where(ev, xf, 0.0), starts)
            out[col] = np.where(n_ev > 0, s / np.maximum(n_ev, 1), np.nan)
        elif how == "last_valid":
            j = last_valid_idx[ends - 1]
            inside = j >= starts
            out[col] = np.where(inside, x.astype(np.float64)[np.maximum(j, 0)], np.nan)
        else:  # a typo in REDUCTIONS
            raise ValueError(f"unknown reduction {how!r} for tick field {name!r}")
    return out


class Downsampler:
    """Rows at ``rate_hz`` from tick chunks; a bin cut by a chunk boundary waits for the next chunk."""

    def __init__(self, rate_hz: float) -> None:
        if not (math.isfinite(rate_hz) and 0 < rate_hz <= 100):
            raise ValueError(f"timeline rate must be in (0, 100] Hz, got {rate_hz}")
        self.rate_hz = rate_hz
        self.pending: TickColumns | None = None

    def add(self, chunk: TickColumns) -> dict[str, NDArray[Any]]:
        """Rows of the bins this chunk completes (all but its last bin, which may go on)."""
        c = type(chunk).concat([self.pending, chunk]) if self.pending is not None else chunk
        if len(c) == 0:
            return {}
        bins = np.floor(c.t_s * self.rate_hz + 1e-9)
        last = int(np.flatnonzero(bins != bins[-1])[-1]) + 1 if np.any(bins != bins[-1]) else 0
        self.pending = _slice(c, last)
        return reduce_runs(_slice(c, 0, last), self.rate_hz) if last else {}

    def finish(self) -> dict[str, NDArray[Any]]:
        c, self.pending = self.pending, None
        return reduce_runs(c, self.rate_hz) if c is not None and len(c) else {}


RATIO_HIST_MAX_PCT = 250.0  # the CM_RATIO signal's range
RATIO_HIST_STEP_PCT = 0.01  # its resolution
PERCENTILES = (1, 5, 50, 95, 99)


@dataclass
class _Fit:
    """Running least-squares line y = a + b x (sums of centred values, numerically tame)."""

    n: int = 0
    sx: float = 0.0
    sy: float = 0.0
    sxx: float = 0.0
    sxy: float = 0.0

    def add(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> None:
        ok = np.isfinite(x) & np.isfinite(y)
        x, y = x[ok], y[ok]
        self.n += len(x)
        self.sx += float(x.sum())
        self.sy += float(y.sum())
        self.sxx += float((x * x).sum())
        self.sxy += float((x * y).sum())

    @property
    def slope(self) -> float:
        if self.n < 2:
            return math.nan
        d = self.n * self.sxx - self.sx * self.sx
        return (self.n * self.sxy - self.sx * self.sy) / d if d > 1e-12 * max(1.0, self.n * self.sxx) else math.nan

    @property
    def mean_y(self) -> float:
        return self.sy / self.n if self.n else math.nan


@dataclass
class LogStats:
    """What a log's summary row needs from its ticks, kept in O(1) memory."""

    t0: float = 0.0
    hist: NDArray[np.int64] = field(
        default_factory=lambda: np.zeros(round(RATIO_HIST_MAX_PCT / RATIO_HIST_STEP_PCT) + 1, np.int64)
    )
    ratio_fit: _Fit = field(default_factory=_Fit)
    leak_fit: _Fit = field(default_factory=_Fit)
    filt_first: float = math.nan
    filt_last: float = math.nan
    filt_min: float = math.nan
    filt_max: float = math.nan
    leak_last: float = math.nan

    def add(self, c: TickColumns) -> None:
        ev = np.isin(c.gate, _EVALUATED)
        if not ev.any():
            return
        t_run = c.t_run_s  # operating hours: the wall clock's steps undone
        h = (t_run[ev] - self.t0) / 3600.0
        r = c.ratio_raw_pct[ev]
        idx = np.clip(np.rint(r / RATIO_HIST_STEP_PCT), 0, len(self.hist) - 1).astype(np.int64)
        self.hist += np.bincount(idx, minlength=len(self.hist))
        self.ratio_fit.add(h, r)
        fv = ev & c.filt_valid.astype(bool)
        if fv.any():
            f = c.ratio_filt_pct[fv]
            leak = c.extra_leak_lpm[fv]
            self.leak_fit.add((t_run[fv] - self.t0) / 3600.0, leak)
            if math.isnan(self.filt_first):
                self.filt_first = float(f[0])
            self.filt_last = float(f[-1])
            self.leak_last = float(leak[-1])
            self.filt_min = float(np.nanmin([self.filt_min, f.min()]))
            self.filt_max = float(np.nanmax([self.filt_max, f.max()]))

    def percentile(self, q: float) -> float:
        """The q-th percentile of the evaluated raw ratios (nearest rank, to 0.01 %)."""
        n = int(self.hist.sum())
        if n == 0:
            return math.nan
        rank = max(1, math.ceil(q / 100.0 * n))
        return round(float(np.searchsorted(np.cumsum(self.hist), rank)) * RATIO_HIST_STEP_PCT, 2)

    def row(self) -> dict[str, float]:
        out = {f"cm_ratio_p{q:02d}_pct": self.percentile(q) for q in PERCENTILES}
        out.update(
            cm_ratio_mean_pct=self.ratio_fit.mean_y,
            cm_ratio_trend_pct_per_h=self.ratio_fit.slope,
            cm_ratio_filt_first_pct=self.filt_first,
            cm_ratio_filt_last_pct=self.filt_last,
            cm_ratio_filt_min_pct=self.filt_min,
            cm_ratio_filt_max_pct=self.filt_max,
            extra_leak_mean_lpm=self.leak_fit.mean_y,
            extra_leak_last_lpm=self.leak_last,
            extra_leak_trend_lpm_per_h=self.leak_fit.slope,
        )
        return out
