"""Where the simulator departs from measured data, which unmodelled effect causes it, and how far
the gap shrinks once that effect is added, judged on data withheld from the fit.

Every candidate effect is fitted (scipy's least squares, within its plausible range on this machine)
on the fit part and scored by the share of the gap it removes on the withheld part. A candidate earns
its place only with a real withheld improvement and a parameter well above its uncertainty; the best
fit over all judged points is named, together with every rival the data cannot tell from it (its
advantage is not consistent over stretches of the data). A second effect is sought on what the first
leaves, and pairs are fitted jointly when no single effect explains the gap. How sure the answer is
(high, medium, low) is decided from figures calibrated on the gap bench (docs/gap.md).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.data import GapData
from cmcan.gap.effects import LIBRARY, OUTPUT_UNIT, Effect, Scale, output_scale, simulate
from cmcan.gap.result import (
    HIGH,
    LOW,
    MEDIUM,
    After,
    Arrays,
    Bin,
    CandidateFit,
    Confidence,
    Diagnosis,
    DominantRegion,
    FittedEffect,
    Flag,
    GapStats,
    Holdout,
    ParamFit,
    PartStat,
    Regions,
    Round,
    TimeLag,
    Where,
)
from cmcan.sim.physics import DriveParams

REGION_VARS = ("dp_bar", "temp_c", "pump_speed_rpm", "pump_disp_cc")
MIN_REDUCTION = 0.3  # share of the remaining withheld gap a candidate must remove to be named
MIN_SIGMAS = 5.0  # fitted parameter / its standard uncertainty
GAP_OVER_NOISE = 1.5  # a gap below this many noise levels is no gap
MIN_GAP_SHARE = 0.0025  # ... nor is one below this share of the output
MAX_EFFECTS = 2
MAX_FIT_POINTS = 40_000
CHUNKS = 20  # stretches of the data over which a candidate's advantage over a rival must hold
TOLD_APART_EFFECT = 0.05  # a rival leaving this much more squared residual, in noise variances,
TOLD_APART_T = 2.0  # ... consistently over the stretches (t statistic), is told apart from the best
SAME_SHAPE = 0.05  # ... unless their contributions differ by less than this share of their size
PAIR_REFINE = 4  # pairs fitted jointly after the linearized screening
PAIR_GAIN = 0.2  # a pair is named only where it removes this much more of the withheld gap than one effect
LEFT_FOR_PAIRS = 2.5  # a single effect leaving more than this many noise levels: try pairs
RELIEF_MARGIN = 0.9  # points whose pressure reaches this share of the relief setting are not judged
MIN_STEADY = 200  # fewer steady points than this: judge static effects on every followable point
STRUCTURE_BINS = 10

# Confidence (calibrated on `cmcan gap bench`, see docs/gap.md): "high" needs all of these.
HIGH_REDUCTION = 0.6  # withheld gap removed by the selection
HIGH_ROBUST = 0.5  # ... and in every region withheld in turn
HIGH_RESIDUAL = 2.5  # withheld residual, in noise levels
HIGH_STRUCTURE = 0.1  # trend left along any input, in noise levels (beyond what noise puts there)
HIGH_SEPARATION = 0.1  # the nearest rival outside the answer leaves this much more (noise variances)
MEDIUM_ROBUST = 0.3


def _rmse(e: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


# ---------------------------------------------------------------------------------------------------
# The data: withheld part, judged points, noise


def holdout_mask(d: GapData, spec: str | None) -> tuple[NDArray[np.bool_], str]:
    """Withheld points by operating region (default: the hottest quarter, or the highest-pressure
    quarter where the oil temperature hardly varies) so an added effect must extrapolate."""
    x = d.x
    if spec is None:
        spec = "temp_c:top25" if np.ptp(x.temp_c) >= 15.0 else "dp_bar:top25"
        if np.ptp(getattr(x, spec.split(":")[0])) == 0.0:
            spec = "time:last25"
    if spec == "random25":
        return np.random.default_rng(0).random(len(d.y)) < 0.25, spec
    try:
        var, side = spec.split(":")
        share = float(side[-2:]) / 100.0
        end = side[:-2]
        values = x.t_s if var == "time" else getattr(x, var) if var in REGION_VARS else None
        if values is None:
            raise ValueError
    except (ValueError, AttributeError):
        raise ValueError(
            f"--holdout {spec!r}: expected VAR:topNN or VAR:bottomNN with VAR one of "
            f"{', '.join((*REGION_VARS, 'time'))}, or random25"
        ) from None
    if end not in ("top", "bottom", "last", "first") or not 0 < share < 1:
        raise ValueError(f"--holdout {spec!r}: expected top/bottom/last/first and a share in 01..99")
    if np.ptp(values) == 0.0:
        raise ValueError(f"--holdout {spec!r}: {var} does not vary in these data; withhold by another variable")
    q = np.quantile(values, 1 - share) if end in ("top", "last") else np.quantile(values, share)
    mask = values >= q if end in ("top", "last") else values <= q
    if mask.all():  # a variable with many equal values: take the share by rank
        order = np.argsort(values, kind="stable")
        k = max(1, round(share * len(values)))
        mask = np.zeros(len(values), dtype=bool)
        mask[order[-k:] if end in ("top", "last") else order[:k]] = True
    return mask, spec


def noise_level(g: NDArray[np.float64], steady: NDArray[np.bool_], segment: NDArray[np.int64]) -> float:
    """Point-to-point noise of the gap from successive steady points (robust MAD estimate)."""
    both = steady[1:] & steady[:-1] & (segment[1:] == segment[:-1])
    d = np.diff(g)[both] if both.sum() > 20 else np.diff(g)
    return float(np.median(np.abs(d - np.median(d))) / 0.6745 / np.sqrt(2)) if len(d) else 0.0


def followable(d: GapData, p: DriveParams) -> NDArray[np.bool_]:
    """Points where the simulator on measured inputs can follow the machine: not at the relief valve
    (its flow changes by tens of l/min per bar, more than a pressure reading resolves) and not with
    the loop's other side high (negative delta pressure, which a high-side sensor does not show)."""
    return (d.dp_lo_bar > 0.0) & (d.dp_hi_bar < RELIEF_MARGIN * p.relief_dp_bar)


def chunks(n: int, k: int = CHUNKS) -> NDArray[np.int64]:
    """Contiguous stretches of the points in data order, of (nearly) equal size."""
    return (np.arange(n) * k // max(n, 1)).astype(np.int64)


@dataclass(frozen=True)
class Context:
    """Everything the search needs about the data, computed once."""

    d: GapData
    p: DriveParams
    scale: Scale
    candidates: dict[str, Effect]
    hold: NDArray[np.bool_]
    spec: str
    static_pts: NDArray[np.bool_]  # where static effects are fitted and judged
    dynamic_pts: NDArray[np.bool_]  # where a time constant is (every followable point)
    y0: NDArray[np.float64]
    sigma: float  # point-to-point noise of the gap at steady points
    sigma_dynamic: float  # ... and over every followable point (transients scatter more)
    floor: float
    mean_y: float
    chunk: NDArray[np.int64]

    def judged(self, with_time: bool) -> NDArray[np.bool_]:
        return self.dynamic_pts if with_time else self.static_pts

    def noise(self, with_time: bool) -> float:
        return max(self.sigma_dynamic if with_time else self.sigma, 1e-12)

    def sim(self, effects: Sequence[tuple[Effect, NDArray[np.float64]]], x=None) -> NDArray[np.float64]:
        return simulate(self.p, self.d.x if x is None else x, list(effects), self.d.quantity)


def prepare(
    d: GapData, p: DriveParams, holdout: str | None = None, candidates: dict[str, Effect] | None = None
) -> Context:
    hold, spec = holdout_mask(d, holdout)
    lib = candidates or LIBRARY
    cands = {
        k: e
        for k, e in lib.items()
        if d.quantity in e.quantities and (d.has_time or not e.needs_time) and _varies_for(e, d)
    }
    fol = followable(d, p)
    steady = d.steady & fol
    static_pts = steady if steady.sum() >= MIN_STEADY or not d.has_time else fol
    y0 = simulate(p, d.x, [], d.quantity)
    sigma = noise_level(d.y - y0, static_pts, d.x.segment)
    sigma_dyn = max(noise_level(d.y - y0, fol, d.x.segment), sigma)
    mean_y = float(np.mean(np.abs(d.y))) or 1.0
    # Below this a gap is within sensor noise or too small to matter.
    floor = max(GAP_OVER_NOISE * sigma, MIN_GAP_SHARE * mean_y)
    return Context(
        d,
        p,
        Scale.of(p, d.x, d.y),
        cands,
        hold,
        spec,
        static_pts,
        fol,
        y0,
        sigma,
        sigma_dyn,
        floor,
        mean_y,
        chunks(len(d.y)),
    )


def _varies_for(e: Effect, d: GapData) -> bool:
    """A gain on an input that is zero throughout cannot show; everything else may."""
    return not (e.name == "pressure_sensor_gain" and not np.any(d.x.dp_bar))


# ---------------------------------------------------------------------------------------------------
# Fitting


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


def _param_fits(ctx: Context, e: Effect, th: NDArray[np.float64], sg: NDArray[np.float64]) -> tuple[ParamFit, ...]:
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
    before = _rmse((ctx.d.y - y_base)[h])
    reduction = 1.0 - _rmse((ctx.d.y - s.y)[h]) / before if before > 0 else 0.0
    significant = bool(all(abs(v) >= MIN_SIGMAS * u for v, u in zip(th, sg, strict=True)))
    judged_rmse = _rmse((ctx.d.y - s.y)[ctx.dynamic_pts])
    eligible = significant and reduction >= MIN_REDUCTION
    return CandidateFit(e.name, e.kind, _param_fits(ctx, e, th, sg), reduction, judged_rmse, significant, eligible)


# ---------------------------------------------------------------------------------------------------
# Telling candidates apart


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
    size = _rmse((a.y - y0)[m])
    return size > 0 and _rmse((a.y - b.y)[m]) < SAME_SHAPE * size


# ---------------------------------------------------------------------------------------------------
# The search


@dataclass(frozen=True)
class Search:
    rounds: tuple[Round, ...]
    groups: tuple[tuple[str, ...], ...]
    final: SetFit | None
    separation: float  # the nearest rival's extra squared residual, in noise variances (inf: no rival)


class Fits:
    """Joint fits by the names of their effects, each made once: the search, the pair screening and the
    regrouping at the end ask for the same sets."""

    def __init__(self, ctx: Context) -> None:
        self.ctx = ctx
        self.sets: dict[tuple[str, ...], SetFit] = {}

    def get(self, names: tuple[str, ...], start: Sequence[NDArray[np.float64] | None] = ()) -> SetFit:
        if names not in self.sets:
            self.sets[names] = fit_set(self.ctx, tuple(self.ctx.candidates[n] for n in names), start)
        return self.sets[names]


def _no_gap(ctx: Context, y: NDArray[np.float64]) -> bool:
    """No gap left, neither at steady points (fit and withheld part) nor in withheld transients."""
    g = ctx.d.y - y
    return _rmse(g[ctx.static_pts]) <= ctx.floor and _rmse(g[ctx.hold & ctx.dynamic_pts]) <= ctx.floor


def _round(ctx: Context, fits: Fits, base: SetFit | None, exclude: set[str]) -> list[CandidateFit]:
    out = []
    for name in ctx.candidates:
        if name in exclude:
            continue
        s = fits.get((*base.names, name) if base else (name,), start=base.theta if base else ())
        out.append(judge(ctx, base, s))
    return out


def _pick(fits: list[CandidateFit]) -> CandidateFit | None:
    """The best eligible candidate: the smallest residual over every judged point; one that sits on
    a bound of its plausible range only where no other is eligible."""
    ok = [f for f in fits if f.eligible]
    inside = [f for f in ok if not f.at_bound]
    pool = inside or ok
    return min(pool, key=lambda f: f.judged_rmse) if pool else None


def search(ctx: Context) -> Search:
    fits = Fits(ctx)
    rounds: list[Round] = []
    names: list[str] = []
    base: SetFit | None = None
    while len(names) < MAX_EFFECTS:
        if _no_gap(ctx, base.y if base else ctx.y0):
            break
        cands = _round(ctx, fits, base, set(names))
        rounds.append(Round(base.names if base else (), tuple(cands)))
        best = _pick(cands)
        if base is None:
            pair = _try_pairs(ctx, fits, best)
            if pair is not None:
                base, names = pair, list(pair.names)
                break
        if best is None:
            break
        names.append(best.name)
        base = fits.get(tuple(names))
    if base is None or not names:
        return Search(tuple(rounds), (), None, np.nan)
    groups, sep = _regroup(ctx, fits, base)
    return Search(tuple(rounds), groups, base, sep)


def _regroup(ctx: Context, fits: Fits, final: SetFit) -> tuple[tuple[tuple[str, ...], ...], float]:
    """Each effect of the answer with every candidate that, put in its place (the others refitted with
    it), fits as well: the data cannot tell them apart. Also the smallest disadvantage (in noise
    variances) of a replacement the data do tell apart: how close the nearest rival comes."""
    groups, sep = [], np.inf
    for i, name in enumerate(final.names):
        others = final.names[:i] + final.names[i + 1 :]
        without = fits.get(others, final.theta[:i] + final.theta[i + 1 :]) if others else None
        group = [name]
        for rival in ctx.candidates:
            if rival in final.names:
                continue
            start = (*final.theta[:i], None, *final.theta[i + 1 :])
            s = fits.get((*final.names[:i], rival, *final.names[i + 1 :]), start)
            f = judge_member(ctx, without, s, i)
            t, size = advantage(ctx, final.y, s.y)
            if f.eligible and not f.at_bound and (same_shape(ctx, final, s, without) or not told_apart(t, size)):
                group.append(rival)
            elif f.heldout_reduction >= MIN_REDUCTION / 2:
                sep = min(sep, size if t >= TOLD_APART_T else 0.0)
        groups.append(tuple(group))
    return tuple(groups), sep


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


def _sensitivities(ctx: Context, names: list[str]) -> NDArray[np.float64]:
    """Each candidate's change of the output per unit of its parameter (a secant at a tenth of its
    plausible range): the linearized model the pair screening works on."""
    cols = []
    for n in names:
        e = ctx.candidates[n]
        lo, hi = e.params[0].plausible(ctx.scale)
        probe = 0.1 * (hi if abs(hi) >= abs(lo) else lo)
        cols.append((ctx.sim([(e, np.array([probe]))]) - ctx.y0) / probe)
    return np.column_stack(cols)


def _try_pairs(ctx: Context, fits: Fits, best: CandidateFit | None) -> SetFit | None:
    """Two effects can hide each other (one slows the motor, the other speeds it up): where no single
    effect leaves little but noise, every pair is screened on the linearized model and the most
    promising few are fitted jointly."""
    if best is not None:
        b = fits.get((best.name,))
        if _rmse((ctx.d.y - b.y)[ctx.hold & b.judged]) <= LEFT_FOR_PAIRS * max(ctx.sigma, 1e-12):
            return None
    names = [n for n, e in ctx.candidates.items() if not e.needs_time and len(e.params) == 1]
    if len(names) < 2:
        return None
    jac = _sensitivities(ctx, names)
    g = ctx.d.y - ctx.y0
    fm, hm = ~ctx.hold & ctx.static_pts, ctx.hold & ctx.static_pts
    jf, jh = jac[fm], jac[hm]
    gram_f, rhs_f = jf.T @ jf, jf.T @ g[fm]
    gram_h, rhs_h, gg_h = jh.T @ jh, jh.T @ g[hm], float(g[hm] @ g[hm])
    bounds = [ctx.candidates[n].params[0].plausible(ctx.scale) for n in names]
    screened = []
    for a, b in itertools.combinations(range(len(names)), 2):
        ix = [a, b]
        m = gram_f[np.ix_(ix, ix)]
        if abs(np.linalg.det(m)) <= 1e-12 * abs(m[0, 0] * m[1, 1]) + 1e-300:
            continue  # the two cannot be told apart at all: no pair
        th = np.linalg.solve(m, rhs_f[ix])
        if not all(bounds[k][0] <= v <= bounds[k][1] for k, v in zip(ix, th, strict=True)):
            continue
        rss_h = gg_h - 2 * th @ rhs_h[ix] + th @ gram_h[np.ix_(ix, ix)] @ th
        screened.append((rss_h, names[a], names[b]))
    found = None
    base_h = max(_rmse(g[hm]), 1e-12)
    for _, a, b in sorted(screened)[:PAIR_REFINE]:
        s = fits.get((a, b))
        fb = judge_member(ctx, fits.get((a,)), s, 1)
        fa = judge_member(ctx, fits.get((b,)), s, 0)
        total = 1.0 - _rmse((ctx.d.y - s.y)[ctx.hold & s.judged]) / base_h
        if fa.eligible and fb.eligible and not (fa.at_bound or fb.at_bound) and (found is None or total > found[0]):
            found = (total, s)
    if found is None:
        return None
    single = 0.0
    if best is not None:
        b = fits.get((best.name,))
        single = 1.0 - _rmse((ctx.d.y - b.y)[hm]) / base_h
    return found[1] if found[0] >= single + PAIR_GAIN else None


# ---------------------------------------------------------------------------------------------------
# Where


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
            Bin(a, b, int(sel.sum()), float(g[sel].mean()), _rmse(g[sel]), float(np.sum(g[sel] ** 2) / total))
            for k, (a, b) in enumerate(edges)
            if (sel := idx == k).any()
        )
    st = d.steady[mask]

    def part(m: NDArray[np.bool_]) -> PartStat:
        return PartStat(int(m.sum()), _rmse(g[m]), float(np.sum(g[m] ** 2) / total))

    return Regions(out, part(st), part(~st))


def _decile_means(v: NDArray[np.float64], g: NDArray[np.float64]) -> tuple[NDArray[np.float64], list]:
    idx, edges = _bins(v, 10)
    counts = np.bincount(idx, minlength=len(edges))
    sums = np.bincount(idx, weights=g, minlength=len(edges))
    means = np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)
    return means, [(a, b, int(c)) for (a, b), c in zip(edges, counts, strict=True)]


def _varying(d: GapData) -> list[str]:
    return [v for v in REGION_VARS if np.ptp(getattr(d.x, v)) > 0.0]


def dominant_region(d: GapData, gap: NDArray[np.float64]) -> DominantRegion | None:
    """The input whose decile means explain most of the squared gap, and the stretch of its range that
    holds most of the gap: the fewest top deciles (by share) that together hold 80 % of it."""
    total = float(np.sum(gap**2)) or 1.0
    best = None
    for var in _varying(d):
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
    for var in _varying(d):
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


# ---------------------------------------------------------------------------------------------------
# How sure


ROBUSTNESS_SPLITS = (
    "temp_c:top25",
    "dp_bar:top25",
    "pump_speed_rpm:top25",
    "pump_speed_rpm:bottom25",
    "pump_disp_cc:bottom25",
)


def robustness(ctx: Context, final: SetFit) -> dict[str, float]:
    """Withheld gap reduction of the selection refitted with each operating region withheld in turn:
    an effect that really is there extrapolates in every direction, a stand-in does not."""
    out = {}
    varying = set(_varying(ctx.d))
    for spec in ROBUSTNESS_SPLITS:
        if spec.split(":")[0] not in varying:
            continue
        hold, _ = holdout_mask(ctx.d, spec)
        h = hold & final.judged
        if h.all() or not h.any():
            continue
        base_h = _rmse((ctx.d.y - ctx.y0)[h])
        if base_h <= GAP_OVER_NOISE * ctx.sigma:
            continue  # no gap in that region to extrapolate to
        s = fit_set(ctx, final.effects, final.theta, fit_mask=~hold)
        out[spec] = 1.0 - _rmse((ctx.d.y - s.y)[h]) / base_h
    return out


def bound_flags(ctx: Context, final: SetFit) -> tuple[Flag, ...]:
    """Every fitted value of the final (joint) fit checked against its plausible range."""
    flags = []
    for e, th, sg in zip(final.effects, final.theta, final.sigma, strict=True):
        for q in _param_fits(ctx, e, th, sg):
            if q.at_bound:
                flags.append(
                    Flag(
                        "bound",
                        f"{e.name}.{q.name} = {q.value:.4g} {q.unit} is on a bound of its plausible range "
                        f"[{q.plausible[0]:.4g}, {q.plausible[1]:.4g}] on this machine",
                    )
                )
    return tuple(flags)


def confidence(
    ctx: Context,
    final: SetFit,
    sep: float,
    robust: dict[str, float],
    structure: dict[str, float],
    flags: tuple[Flag, ...],
) -> Confidence:
    sigma = ctx.noise(final.with_time)
    h = ctx.hold & final.judged
    base_h = _rmse((ctx.d.y - ctx.y0)[h])
    left = _rmse((ctx.d.y - final.y)[h])
    checks = {
        "heldout_reduction": 1.0 - left / base_h if base_h > 0 else 0.0,
        "robust_min": min(robust.values(), default=1.0),
        "residual_over_noise": left / sigma,
        "structure_over_noise": max(structure.values(), default=0.0),
        "separation": float(sep),
    }
    reasons = []
    if flags:
        reasons.append("a fitted value is on a bound of its plausible range")
    if checks["heldout_reduction"] < HIGH_REDUCTION:
        reasons.append(f"removes less than {100 * HIGH_REDUCTION:.0f} % of the withheld gap")
    if checks["robust_min"] < HIGH_ROBUST:
        reasons.append(f"removes less than {100 * HIGH_ROBUST:.0f} % in some region withheld in turn")
    if checks["residual_over_noise"] > HIGH_RESIDUAL:
        reasons.append(f"leaves more than {HIGH_RESIDUAL} noise levels on the withheld part")
    if checks["structure_over_noise"] > HIGH_STRUCTURE:
        reasons.append("leaves a trend along an input")
    if not sep >= HIGH_SEPARATION:
        reasons.append("a rival outside the answer fits nearly as well")
    if not reasons:
        return Confidence(HIGH, (), checks)
    if flags or checks["robust_min"] < MEDIUM_ROBUST or checks["heldout_reduction"] < MIN_REDUCTION:
        return Confidence(LOW, tuple(reasons), checks)
    return Confidence(MEDIUM, tuple(reasons), checks)


# ---------------------------------------------------------------------------------------------------
# The whole diagnosis


def _stats(ctx: Context, y: NDArray[np.float64], h: NDArray[np.bool_]) -> tuple[float, float, float, float]:
    g = ctx.d.y - y
    return _rmse(g), 100 * _rmse(g) / ctx.mean_y, float(g.mean()), _rmse(g[h])


def _verdict(ctx: Context, s: Search, conf: Confidence | None, flags: tuple[Flag, ...]) -> str:
    if s.groups:
        text = {HIGH: "explained", MEDIUM: "explained (medium confidence)", LOW: "partly explained (low confidence)"}
        v = text[conf.level if conf else LOW]
        for g in s.groups:
            if len(g) > 1:
                v += f"; {' and '.join(g)} cannot be told apart on these data"
        if flags:
            v += "; a fitted value is on a bound of its plausible range"
        return v
    return "no significant gap" if _no_gap(ctx, ctx.y0) else "unexplained"


def _judged_on(ctx: Context, judged: NDArray[np.bool_]) -> str:
    if not ctx.d.has_time:
        return "every operating point"
    if judged is ctx.static_pts and not (ctx.static_pts == ctx.dynamic_pts).all():
        return "steady points"
    return "every point the simulator can follow"


def diagnose(
    d: GapData, p: DriveParams, holdout: str | None = None, candidates: dict[str, Effect] | None = None
) -> tuple[Diagnosis, Arrays]:
    """The diagnosis, and the arrays behind its plots (simulated output before and after)."""
    ctx = prepare(d, p, holdout, candidates)
    found = search(ctx)
    final = found.final
    robust: dict[str, float] = {}
    structure: dict[str, float] = {}
    flags: tuple[Flag, ...] = ()
    conf = None
    y1 = final.y if final is not None else ctx.y0
    if final is not None and found.groups:
        robust = robustness(ctx, final)
        resid = (d.y - y1)[final.judged]
        structure = residual_structure(d.subset(final.judged), resid, ctx.noise(final.with_time))
        flags = bound_flags(ctx, final)
        conf = confidence(ctx, final, found.separation, robust, structure, flags)
    judged = final.judged if final is not None and found.groups else ctx.static_pts
    h = ctx.hold & judged
    b = _stats(ctx, ctx.y0, h)
    a = _stats(ctx, y1, h)
    g0, g1 = d.y - ctx.y0, d.y - y1
    diag = Diagnosis(
        source=d.source,
        quantity=d.quantity,
        unit=d.unit,
        data_kind=d.kind,
        points=len(d.y),
        noise_level=ctx.sigma,
        before=GapStats(*b),
        where=where(ctx),
        candidates=found.rounds[0].candidates if found.rounds else (),
        rounds=found.rounds,
        groups=found.groups,
        fitted=tuple(
            FittedEffect(e.name, _param_fits(ctx, e, th, sg))
            for e, th, sg in (zip(final.effects, final.theta, final.sigma, strict=True) if final else ())
        )
        if found.groups
        else (),
        confidence=conf,
        flags=flags,
        verdict=_verdict(ctx, found, conf, flags),
        after=After(a[0], a[1], a[3], 1 - a[3] / b[3] if b[3] > 0 else 0.0, regions(d, g1, h)),
        holdout=Holdout(
            ctx.spec,
            int(ctx.hold.sum()),
            int(h.sum()),
            _judged_on(ctx, judged),
            regions(d, g0, h),
        ),
        robustness=robust,
        residual_structure=structure,
    )
    return diag, Arrays(ctx.y0, y1, ctx.hold)


__all__ = ["REGION_VARS", "diagnose", "holdout_mask", "output_scale"]
