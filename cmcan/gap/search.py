"""The search: candidates round by round, pairs where effects hide each other, the groups the data
cannot tell apart."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.context import Context, rmse
from cmcan.gap.fit import (
    MIN_REDUCTION,
    TOLD_APART_T,
    SetFit,
    advantage,
    fit_set,
    judge,
    judge_member,
    same_shape,
    told_apart,
)
from cmcan.gap.result import (
    CandidateFit,
    PairFit,
    PairSearch,
    Round,
)

MAX_EFFECTS = 2
PAIR_REFINE = 4  # pairs fitted jointly after the linearized screening
PAIR_GAIN = 0.2  # a pair is named only where it removes this much more of the withheld gap than one effect
LEFT_FOR_PAIRS = 2.5  # a single effect leaving more than this many noise levels: try pairs


@dataclass(frozen=True)
class Search:
    rounds: tuple[Round, ...]
    groups: tuple[tuple[str, ...], ...]
    final: SetFit | None
    separation: float  # the nearest rival's extra squared residual, in noise variances (inf: no rival)
    pairs: PairSearch | None = None  # the pair search, where it ran


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


def no_gap(ctx: Context, y: NDArray[np.float64]) -> bool:
    """No gap left, neither at steady points (fit and withheld part) nor in withheld transients."""
    g = ctx.d.y - y
    return rmse(g[ctx.static_pts]) <= ctx.floor and rmse(g[ctx.hold & ctx.dynamic_pts]) <= ctx.floor


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
    pairs: PairSearch | None = None
    while len(names) < MAX_EFFECTS:
        if no_gap(ctx, base.y if base else ctx.y0):
            break
        cands = _round(ctx, fits, base, set(names))
        rounds.append(Round(base.names if base else (), tuple(cands)))
        best = _pick(cands)
        if base is None:
            pair, pairs = _try_pairs(ctx, fits, best)
            if pair is not None:
                base, names = pair, list(pair.names)
                break
        if best is None:
            break
        names.append(best.name)
        base = fits.get(tuple(names))
    if base is None or not names:
        return Search(tuple(rounds), (), None, np.nan, pairs)
    groups, sep = _regroup(ctx, fits, base)
    return Search(tuple(rounds), groups, base, sep, pairs)


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


def _try_pairs(ctx: Context, fits: Fits, best: CandidateFit | None) -> tuple[SetFit | None, PairSearch | None]:
    """Two effects can hide each other (one slows the motor, the other speeds it up): where no single
    effect leaves little but noise, every pair is screened on the linearized model and the most
    promising few are fitted jointly. The pair named (or None), and what the search tried."""
    if best is not None:
        b = fits.get((best.name,))
        if rmse((ctx.d.y - b.y)[ctx.hold & b.judged]) <= LEFT_FOR_PAIRS * max(ctx.sigma, 1e-12):
            return None, None
    names = [n for n, e in ctx.candidates.items() if not e.needs_time and len(e.params) == 1]
    if len(names) < 2:
        return None, None
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
    base_h = max(rmse(g[hm]), 1e-12)
    tried = []
    for _, a, b in sorted(screened)[:PAIR_REFINE]:
        s = fits.get((a, b))
        fb = judge_member(ctx, fits.get((a,)), s, 1)
        fa = judge_member(ctx, fits.get((b,)), s, 0)
        total = 1.0 - rmse((ctx.d.y - s.y)[ctx.hold & s.judged]) / base_h
        ok = fa.eligible and fb.eligible and not (fa.at_bound or fb.at_bound)
        tried.append(PairFit((a, b), (fa, fb), total, ok))
        if ok and (found is None or total > found[0]):
            found = (total, s)
    single = 0.0
    if best is not None:
        b1 = fits.get((best.name,))
        single = 1.0 - rmse((ctx.d.y - b1.y)[hm]) / base_h
    chosen = found[1] if found is not None and found[0] >= single + PAIR_GAIN else None
    report = PairSearch(
        best.name if best is not None else None,
        single,
        single + PAIR_GAIN,
        tuple(tried),
        (chosen.names[0], chosen.names[1]) if chosen is not None else None,
    )
    return chosen, report
