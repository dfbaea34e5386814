"""Where the gap lies: by region, the dominant region, the trend a residual keeps, the time lag."""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.context import REGION_VARS, Context, rmse
from cmcan.gap.data import GapData
from cmcan.gap.result import (
    Bin,
    DominantRegion,
    PartStat,
    Regions,
    TimeLag,
    Where,
)

STRUCTURE_BINS = 10


def _bins(v: NDArray[np.float64], k: int) -> tuple[NDArray[np.int64], list[tuple[float, float]]]:
    """Equal-count bins of ``v`` (k of them, fewer where values repeat): bin index per point, edges."""
    edges = np.unique(np.quantile(v, np.linspace(0, 1, k + 1)))
    if len(edges) < 2:
        return np.zeros(len(v), dtype=np.int64), [(float(v[0]), float(v[0]))] if len(v) else []
    idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, len(edges) - 2)
    return idx.astype(np.int64), [(float(a), float(b)) for a, b in itertools.pairwise(edges)]


def regions(d: GapData, gap: NDArray[np.float64], mask: NDArray[np.bool_]) -> Regions:
    """The gap by operating region: quartile bins of each input, steady against transient."""
    g, total = gap[mask], float(np.sum(gap[mask] ** 2)) or 1.0
    out: dict[str, tuple[Bin, ...]] = {}
    for var in REGION_VARS:
        v = getattr(d.x, var)[mask]
        if not len(v):
            out[var] = ()
            continue
        idx, edges = _bins(v, 4)
        out[var] = tuple(
            Bin(a, b, int(sel.sum()), float(g[sel].mean()), rmse(g[sel]), float(np.sum(g[sel] ** 2) / total))
            for k, (a, b) in enumerate(edges)
            if (sel := idx == k).any()
        )
    st = d.steady[mask]

    def part(m: NDArray[np.bool_]) -> PartStat:
        return PartStat(int(m.sum()), rmse(g[m]), float(np.sum(g[m] ** 2) / total))

    return Regions(out, part(st), part(~st))


def _decile_means(v: NDArray[np.float64], g: NDArray[np.float64]) -> tuple[NDArray[np.float64], list]:
    idx, edges = _bins(v, 10)
    counts = np.bincount(idx, minlength=len(edges))
    sums = np.bincount(idx, weights=g, minlength=len(edges))
    means = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)
    return means, [(a, b, int(c)) for (a, b), c in zip(edges, counts, strict=True)]


def varying(d: GapData) -> list[str]:
    return [v for v in REGION_VARS if np.ptp(getattr(d.x, v)) > 0.0]


def dominant_region(d: GapData, gap: NDArray[np.float64]) -> DominantRegion | None:
    """The input whose decile means explain most of the squared gap, and the stretch of its range that
    holds most of the gap: the fewest top deciles (by share) that together hold 80 % of it."""
    total = float(np.sum(gap**2)) or 1.0
    best = None
    for var in varying(d):
        means, bins = _decile_means(getattr(d.x, var), gap)
        explained = float(sum(m * m * n for m, (_, _, n) in zip(means, bins, strict=True))) / total
        if best is None or explained > best[0]:
            best = (explained, var, means, bins)
    if best is None:
        return None
    explained, var, means, bins = best
    shares = np.array([m * m * n for m, (_, _, n) in zip(means, bins, strict=True)]) / total
    keep, acc = [], 0.0
    for k in np.argsort(shares)[::-1]:
        keep.append(int(k))
        acc += shares[k]
        if acc >= 0.8 * explained:
            break
    lo, hi = min(bins[k][0] for k in keep), max(bins[k][1] for k in keep)
    return DominantRegion(var, lo, hi, float(acc), explained)


def residual_structure(d: GapData, resid: NDArray[np.float64], noise: float) -> dict[str, float]:
    """The trend a residual keeps along each varying input, in noise levels: the point-weighted RMS of
    its means in equal-width bins of the input, less what noise alone puts there. What a right effect
    leaves is noise (near zero here), what a stand-in leaves is a trend. Equal widths, not equal
    counts: many points at one value (full stroke) split by their noise would feign a trend."""
    out = {}
    n = len(resid)
    noise = max(noise, 1e-12)
    for var in varying(d):
        v = getattr(d.x, var)
        lo, hi = float(v.min()), float(v.max())
        idx = np.clip(((v - lo) / (hi - lo) * STRUCTURE_BINS).astype(np.int64), 0, STRUCTURE_BINS - 1)
        cnt = np.bincount(idx, minlength=STRUCTURE_BINS)
        sums = np.bincount(idx, weights=resid, minlength=STRUCTURE_BINS)
        used = cnt > 0
        raw = float(np.sum(sums[used] ** 2 / cnt[used])) / n
        out[var] = float(np.sqrt(max(raw - used.sum() * noise**2 / n, 0.0))) / noise
    return out


def time_lag(d: GapData, y_sim: NDArray[np.float64]) -> TimeLag | None:
    """Delay of the measured behind the simulated output, from the cross-correlation of their rates."""
    if not d.has_time or len(d.y) < 3:
        return None
    dt = float(np.median(np.diff(d.x.t_s)))
    same = np.r_[False, d.x.segment[1:] == d.x.segment[:-1]]
    a = np.where(same, np.diff(d.y, prepend=d.y[0]), 0.0)
    b = np.where(same, np.diff(y_sim, prepend=y_sim[0]), 0.0)
    if not a.any() or not b.any():
        return TimeLag(0.0, 0.0)
    best_k, best_c = 0, -np.inf
    for k in range(0, 11):  # up to 1 s at 10 Hz
        c = float(np.dot(a[k:], b[: len(b) - k]))
        if c > best_c:
            best_k, best_c = k, c
    norm = float(np.sqrt(np.dot(a, a) * np.dot(b, b))) or 1.0
    return TimeLag(best_k * dt, best_c / norm)


def where(ctx: Context) -> Where:
    """The gap by region over the points the simulator can follow; the dominant region from the points
    static effects are judged on (transients add the dynamics' own scatter)."""
    g0 = ctx.d.y - ctx.y0
    st = ctx.static_pts
    return Where(
        regions(ctx.d, g0, ctx.dynamic_pts),
        dominant_region(ctx.d.subset(st), g0[st]) if st.any() else None,
        time_lag(ctx.d, ctx.y0),
    )
