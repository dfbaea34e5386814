"""What the gap report's figures show, computed apart from drawing them: the point sets with their
legend labels and counts, the axis limits, the heat map's cells. ``cmcan.plots`` draws these; tests
check them here, not in pixels.

The figures show what the diagnosis judges. Points it does not judge (at the relief valve, with the
delta pressure at or below zero, transients for an answer judged on steady points) are drawn apart in
grey and do not set the axis, so a few hundred rpm of gap at the relief valve cannot flatten the gap
the answer removes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.context import REGION_VARS
from cmcan.gap.data import GapData
from cmcan.gap.result import Arrays, Diagnosis

HEATMAP_BINS = 8  # quantile bins of each axis
PAD = 0.06  # of the judged points' span, above and below


@dataclass(frozen=True)
class PointSet:
    """One kind of point in every panel: which points, which gap (before or after), its legend."""

    key: str  # before_fit, before_withheld, after_withheld, not_judged
    label: str  # with its count
    mask: NDArray[np.bool_]
    gap: NDArray[np.float64]  # measured - simulated at every point; drawn where ``mask``


@dataclass(frozen=True)
class VariablesFigure:
    variables: tuple[str, ...]  # one panel each
    x: dict[str, NDArray[np.float64]]  # each variable's values at every point
    sets: tuple[PointSet, ...]  # drawn in this order
    ylim: tuple[float, float]  # covers every judged point's gap, before and after
    title: str


@dataclass(frozen=True)
class HeatmapFigure:
    dp_edges: NDArray[np.float64]
    temp_edges: NDArray[np.float64]
    mean: NDArray[np.float64]  # [dp bin, temp bin]: mean gap of the judged points; NaN: no judged point
    counts: NDArray[np.int64]
    lim: float  # the colour scale is -lim..lim (0, no gap, in the middle)
    title: str

    @property
    def empty_cells(self) -> int:
        return int((self.counts == 0).sum())


def _ylim(values: list[NDArray[np.float64]]) -> tuple[float, float]:
    v = np.concatenate([x[np.isfinite(x)] for x in values]) if values else np.empty(0)
    if not len(v):
        return -1.0, 1.0
    lo, hi = float(min(v.min(), 0.0)), float(max(v.max(), 0.0))  # the zero line always shows
    pad = PAD * (hi - lo) or 1.0
    return lo - pad, hi + pad


def variables_figure(diag: Diagnosis, d: GapData, arrays: Arrays) -> VariablesFigure:
    """The gap against each input: before the fit (fit part and withheld part) and after it (withheld
    part) at the judged points; the unjudged points apart, counted, off the axis where they lie beyond
    the judged points' gaps."""
    g0, g1 = d.y - arrays.y_before, d.y - arrays.y_after
    hold, judged = arrays.holdout, arrays.judged
    fit_j, hold_j, out = ~hold & judged, hold & judged, ~judged
    ylim = _ylim([g0[judged], g1[hold_j]])
    sets = [
        PointSet("before_fit", f"before, fit part ({int(fit_j.sum())})", fit_j, g0),
        PointSet("before_withheld", f"before, withheld ({int(hold_j.sum())})", hold_j, g0),
        PointSet("after_withheld", f"after, withheld ({int(hold_j.sum())})", hold_j, g1),
    ]
    if out.any():
        beyond = int(np.sum(out & ((g0 < ylim[0]) | (g0 > ylim[1]))))
        cov = diag.judged
        why = f": {cov.why()}" if cov is not None and cov.why() else ""
        sets.insert(
            0,
            PointSet(
                "not_judged",
                f"not judged, before ({int(out.sum())}{why}; {beyond} beyond the axis)",
                out,
                g0,
            ),
        )
    added = ", ".join(f.name for f in diag.fitted) or "nothing"
    n = int(judged.sum())
    of = f" of {len(d.y)}" if n < len(d.y) else ""
    title = f"measured minus simulated at the {n}{of} judged points, before and after adding {added}"
    x = {v: getattr(d.x, v) for v in REGION_VARS}
    return VariablesFigure(REGION_VARS, x, tuple(sets), ylim, title)


def heatmap_figure(d: GapData, arrays: Arrays) -> HeatmapFigure | None:
    """Mean gap before the fit over delta pressure x oil temperature at the judged points (None where
    either does not vary among them). A cell with no judged point is NaN: drawn as "no data", never as
    the colour of no gap."""
    j = arrays.judged
    dp, temp = d.x.dp_bar[j], d.x.temp_c[j]
    if not len(dp) or np.ptp(dp) == 0 or np.ptp(temp) == 0:
        return None
    g0 = (d.y - arrays.y_before)[j]
    xe = np.unique(np.quantile(dp, np.linspace(0, 1, HEATMAP_BINS + 1)))
    ye = np.unique(np.quantile(temp, np.linspace(0, 1, HEATMAP_BINS + 1)))
    sums, _, _ = np.histogram2d(dp, temp, bins=[xe, ye], weights=g0)
    counts, _, _ = np.histogram2d(dp, temp, bins=[xe, ye])
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    lim = float(np.nanmax(np.abs(mean))) if np.isfinite(mean).any() else 1.0
    n = int(j.sum())
    of = f" of {len(d.y)}" if n < len(d.y) else ""
    title = f"gap by operating region ({n}{of} judged points)"
    return HeatmapFigure(xe, ye, mean, counts.astype(np.int64), lim or 1.0, title)
