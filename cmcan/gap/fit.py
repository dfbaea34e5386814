"""Fitting sets of effects jointly within their plausible ranges, judging them, telling them apart."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.context import Context, rmse
from cmcan.gap.effects import OUTPUT_UNIT, Effect
from cmcan.gap.result import (
    CandidateFit,
    ParamFit,
)

MIN_REDUCTION = 0.3  # share of the remaining withheld gap a candidate must remove to be named
MIN_SIGMAS = 5.0  # fitted parameter / its standard uncertainty
MAX_FIT_POINTS = 40_000
TOLD_APART_EFFECT = 0.05  # a rival leaving this much more squared residual, in noise variances,
TOLD_APART_T = 2.0  # ... consistently over the stretches (t statistic), is told apart from the best
SAME_SHAPE = 0.05  # ... unless their contributions differ by less than this share of their size


@dataclass(frozen=True)
class SetFit:
    """A set of effects fitted jointly: parameters, uncertainties, output on every point."""

    effects: tuple[Effect, ...]
    theta: tuple[NDArray[np.float64], ...]
    sigma: tuple[NDArray[np.float64], ...]
    y: NDArray[np.float64]
    judged: NDArray[np.bool_]

    @property
    def pairs(self) -> list[tuple[Effect, NDArray[np.float64]]]:
        return list(zip(self.effects, self.theta, strict=True))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects)

    @property
    def with_time(self) -> bool:
        return any(e.needs_time for e in self.effects)


def _bounds(ctx: Context, effects: Sequence[Effect]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    lo, hi = [], []
    for e in effects:
        for q in e.params:
            a, b = q.plausible(ctx.scale)
            lo.append(max(a, q.bound_lo))
            hi.append(b)
    return np.array(lo), np.array(hi)


def fit_set(
    ctx: Context,
    effects: Sequence[Effect],
    start: Sequence[NDArray[np.float64] | None] = (),
    fit_mask: NDArray[np.bool_] | None = None,
) -> SetFit:
    """Fit ``effects`` jointly on the fit part (or ``fit_mask``) within their plausible ranges."""
    from scipy.optimize import least_squares

    effects = tuple(effects)
    with_time = any(e.needs_time for e in effects)
    judged = ctx.judged(with_time)
    fm = (~ctx.hold if fit_mask is None else fit_mask) & judged
    idx = np.flatnonzero(fm)
    if len(idx) > MAX_FIT_POINTS:  # an even thinning keeps every region and the time structure
        fm = np.zeros_like(fm)
        fm[idx[:: int(np.ceil(len(idx) / MAX_FIT_POINTS))]] = True
    lo, hi = _bounds(ctx, effects)
    starts = list(start) + [None] * (len(effects) - len(start))
    x0 = np.concatenate(
        [
            s if s is not None else np.array([q.x0(ctx.scale) for q in e.params])
            for e, s in zip(effects, starts, strict=True)
        ]
    )
    pad = 1e-6 * (hi - lo)
    x0 = np.clip(x0, lo + pad, hi - pad)
    sizes = [len(e.params) for e in effects]
    xf = ctx.d.x if with_time else ctx.d.x.subset(fm)  # a lag needs the whole time series
    yf = ctx.d.y[fm]

    def split(theta: NDArray[np.float64]) -> list[tuple[Effect, NDArray[np.float64]]]:
        out, k = [], 0
        for e, n in zip(effects, sizes, strict=True):
            out.append((e, theta[k : k + n]))
            k += n
        return out

    def resid(theta: NDArray[np.float64]) -> NDArray[np.float64]:
        y = ctx.sim(split(theta), xf)
        return (y[fm] if with_time else y) - yf

    res = least_squares(resid, x0, bounds=(lo, hi), method="trf", x_scale="jac")
    theta = res.x
    sigma = _uncertainty(res.jac, res.fun, len(theta), ctx.d.x.segment[fm])
    fitted = split(theta)
    k, sig = 0, []
    for n in sizes:
        sig.append(sigma[k : k + n])
        k += n
    return SetFit(effects, tuple(th for _, th in fitted), tuple(sig), ctx.sim(fitted), judged)


def _uncertainty(
    jac: NDArray[np.float64], r: NDArray[np.float64], n_par: int, segment: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Standard uncertainties from the Jacobian, widened for residuals correlated from point to point
    (a residual that is mostly a slow trend carries fewer independent points than it has)."""
    dof = max(len(r) - n_par, 1)
    s2 = float(np.sum(r**2)) / dof
    same = segment[1:] == segment[:-1]
    rho = 0.0
    if same.sum() > 10 and s2 > 0:
        rho = float(np.sum(r[1:][same] * r[:-1][same]) / np.sum(r**2))
    inflate = (1 + rho) / (1 - rho) if 0 < rho < 0.99 else (100.0 if rho >= 0.99 else 1.0)
    try:
        cov = np.linalg.pinv(jac.T @ jac) * s2 * inflate
        return np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        return np.full(n_par, np.inf)


def param_fits(ctx: Context, e: Effect, th: NDArray[np.float64], sg: NDArray[np.float64]) -> tuple[ParamFit, ...]:
    out = []
    for q, v, s in zip(e.params, th, sg, strict=True):
        lo, hi = q.plausible(ctx.scale)
        lo = max(lo, q.bound_lo)
        tol = 1e-3 * (hi - lo)
        unit = ctx.d.unit if q.unit == OUTPUT_UNIT else q.unit
        out.append(ParamFit(q.name, unit, float(v), float(s), (lo, hi), bool(v <= lo + tol or v >= hi - tol)))
    return tuple(out)


def judge(ctx: Context, base: SetFit | None, s: SetFit) -> CandidateFit:
    """The last effect of ``s`` (fitted on top of ``base``) judged: withheld reduction, significance."""
    e, th, sg = s.effects[-1], s.theta[-1], s.sigma[-1]
    y_base = base.y if base is not None else ctx.y0
    h = ctx.hold & s.judged
    before = rmse((ctx.d.y - y_base)[h])
    reduction = 1.0 - rmse((ctx.d.y - s.y)[h]) / before if before > 0 else 0.0
    significant = bool(all(abs(v) >= MIN_SIGMAS * u for v, u in zip(th, sg, strict=True)))
    judged_rmse = rmse((ctx.d.y - s.y)[ctx.dynamic_pts])
    eligible = significant and reduction >= MIN_REDUCTION
    return CandidateFit(e.name, e.kind, param_fits(ctx, e, th, sg), reduction, judged_rmse, significant, eligible)


def advantage(ctx: Context, best: NDArray[np.float64], rival: NDArray[np.float64]) -> tuple[float, float]:
    """How consistently ``best`` fits better than ``rival`` over stretches of the followable points:
    (t statistic of the per-stretch advantage in squared residual, mean advantage in noise variances).
    A rival whose advantage is not consistent over the data cannot be told apart from the best."""
    m = ctx.dynamic_pts
    diff = (ctx.d.y - rival)[m] ** 2 - (ctx.d.y - best)[m] ** 2
    ch = ctx.chunk[m]
    k = int(ch.max()) + 1 if len(ch) else 0
    per = np.bincount(ch, weights=diff, minlength=k) / np.maximum(np.bincount(ch, minlength=k), 1)
    per = per[np.bincount(ch, minlength=k) > 0]
    mean = float(np.mean(diff)) if len(diff) else 0.0
    size = mean / max(ctx.sigma**2, 1e-12)
    if len(per) < 3:
        return (np.inf if size > TOLD_APART_EFFECT else 0.0), size
    sd = float(np.std(per, ddof=1))
    t = float(np.mean(per)) / (sd / np.sqrt(len(per))) if sd > 0 else (np.inf if np.mean(per) > 0 else 0.0)
    return t, size


def told_apart(t: float, size: float) -> bool:
    return t >= TOLD_APART_T and size >= TOLD_APART_EFFECT


def same_shape(ctx: Context, a: SetFit, b: SetFit, without: SetFit | None) -> bool:
    """Two answers whose contributions differ by less than SAME_SHAPE of their size: telling them apart
    would rest on the simulator's own loss terms being exact to a few %, which no real machine's are."""
    m = a.judged & b.judged
    y0 = without.y if without is not None else ctx.y0
    size = rmse((a.y - y0)[m])
    return size > 0 and rmse((a.y - b.y)[m]) < SAME_SHAPE * size


def judge_member(ctx: Context, without: SetFit | None, s: SetFit, i: int) -> CandidateFit:
    """Effect ``i`` of ``s`` judged as if fitted last, on top of the others (``without``)."""
    order = [*(k for k in range(len(s.effects)) if k != i), i]
    moved = SetFit(
        tuple(s.effects[k] for k in order),
        tuple(s.theta[k] for k in order),
        tuple(s.sigma[k] for k in order),
        s.y,
        s.judged,
    )
    return judge(ctx, without, moved)
