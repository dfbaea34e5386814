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

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.confidence import bound_flags, confidence, robustness
from cmcan.gap.context import REGION_VARS, RELIEF_MARGIN, Context, Reach, holdout_mask, holdout_reach, prepare, rmse
from cmcan.gap.data import GapData
from cmcan.gap.effects import Effect
from cmcan.gap.fit import param_fits
from cmcan.gap.result import (
    HIGH,
    LOW,
    MEDIUM,
    After,
    Arrays,
    Confidence,
    Coverage,
    Diagnosis,
    FittedEffect,
    Flag,
    GapStats,
    Holdout,
)
from cmcan.gap.search import Search, no_gap, search
from cmcan.gap.where import regions, residual_structure, where
from cmcan.sim.physics import DriveParams


def _stats(ctx: Context, y: NDArray[np.float64], judged: NDArray[np.bool_], h: NDArray[np.bool_]) -> GapStats:
    """The gap at the judged points (the headline), on their withheld part, and at every point."""
    g = ctx.d.y - y
    gj = g[judged]
    return GapStats(
        rmse(gj), 100 * rmse(gj) / ctx.mean_y, float(gj.mean()) if len(gj) else float("nan"), rmse(g[h]), rmse(g)
    )


def _coverage(ctx: Context, judged: NDArray[np.bool_]) -> Coverage:
    d, out = ctx.d, ~judged
    relief = out & (d.dp_hi_bar >= RELIEF_MARGIN * ctx.p.relief_dp_bar)
    zero = out & ~relief & (d.dp_lo_bar <= 0.0)
    return Coverage(
        int(judged.sum()),
        len(d.y),
        _judged_on(ctx, judged),
        int(relief.sum()),
        int(zero.sum()),
        int((out & ctx.dynamic_pts).sum()),
    )


def _verdict(ctx: Context, s: Search, conf: Confidence | None, flags: tuple[Flag, ...], reach: Reach | None) -> str:
    if s.groups:
        text = {HIGH: "explained", MEDIUM: "explained (medium confidence)", LOW: "partly explained (low confidence)"}
        v = text[conf.level if conf else LOW]
        for g in s.groups:
            if len(g) > 1:
                v += f"; {' and '.join(g)} cannot be told apart on these data"
        if flags:
            v += "; a fitted value is on a bound of its plausible range"
    else:
        v = "no significant gap" if no_gap(ctx, ctx.y0) else "unexplained"
    if reach is not None and reach.degenerate:
        v += "; the withheld part hardly differs from the fit part (a degenerate hold-out: see holdout.degenerate)"
    return v


def _judged_on(ctx: Context, judged: NDArray[np.bool_]) -> str:
    if not ctx.d.has_time:
        return "every operating point"
    if judged is ctx.static_pts and not (ctx.static_pts == ctx.dynamic_pts).all():
        return "steady points"
    return "every point the simulator can follow"


@dataclass(frozen=True)
class Judgement:
    """How sure the answer is, and why: empty where nothing is named."""

    confidence: Confidence | None = None
    flags: tuple[Flag, ...] = ()
    robustness: dict[str, float] = field(default_factory=dict)
    structure: dict[str, float] = field(default_factory=dict)


def judge_answer(ctx: Context, found: Search, degenerate_holdout: bool = False) -> Judgement:
    final = found.final
    if final is None or not found.groups:
        return Judgement()
    robust = robustness(ctx, final)
    resid = (ctx.d.y - final.y)[final.judged]
    structure = residual_structure(ctx.d.subset(final.judged), resid, ctx.noise(final.with_time))
    flags = bound_flags(ctx, final)
    conf = confidence(ctx, final, found.separation, robust, structure, flags, degenerate_holdout)
    return Judgement(conf, flags, robust, structure)


def _fitted(ctx: Context, found: Search) -> tuple[FittedEffect, ...]:
    f = found.final
    if f is None or not found.groups:
        return ()
    return tuple(
        FittedEffect(e.name, param_fits(ctx, e, th, sg)) for e, th, sg in zip(f.effects, f.theta, f.sigma, strict=True)
    )


def diagnose(
    d: GapData, p: DriveParams, holdout: str | None = None, candidates: dict[str, Effect] | None = None
) -> tuple[Diagnosis, Arrays]:
    """The diagnosis, and the arrays behind its plots (simulated output before and after)."""
    ctx = prepare(d, p, holdout, candidates)
    found = search(ctx)
    named = found.final is not None and bool(found.groups)
    judged = found.final.judged if found.final is not None and named else ctx.static_pts
    reach = holdout_reach(d, ctx.hold, judged, ctx.spec, ctx.scale)
    answer = judge_answer(ctx, found, reach is not None and reach.degenerate)
    y1 = found.final.y if found.final is not None and named else ctx.y0
    h = ctx.hold & judged
    b, a = _stats(ctx, ctx.y0, judged, h), _stats(ctx, y1, judged, h)
    diag = Diagnosis(
        source=d.source,
        quantity=d.quantity,
        unit=d.unit,
        data_kind=d.kind,
        points=len(d.y),
        noise_level=ctx.sigma,
        before=b,
        where=where(ctx),
        candidates=found.rounds[0].candidates if found.rounds else (),
        rounds=found.rounds,
        groups=found.groups,
        fitted=_fitted(ctx, found),
        confidence=answer.confidence,
        flags=answer.flags,
        verdict=_verdict(ctx, found, answer.confidence, answer.flags, reach),
        after=After(
            a.rmse,
            a.rmse_pct,
            a.heldout_rmse,
            1 - a.heldout_rmse / b.heldout_rmse if b.heldout_rmse > 0 else 0.0,
            regions(d, d.y - y1, h),
            a.all_rmse,
        ),
        holdout=Holdout(
            ctx.spec,
            int(ctx.hold.sum()),
            int(h.sum()),
            _judged_on(ctx, judged),
            regions(d, d.y - ctx.y0, h),
            reach.message if reach is not None else "",
            reach.reach if reach is not None else None,
            reach.needed if reach is not None else None,
        ),
        robustness=answer.robustness,
        residual_structure=answer.structure,
        refused_points=d.refused,
        refused_why=d.refused_why,
        judged=_coverage(ctx, judged),
        pair_search=found.pairs,
    )
    return diag, Arrays(ctx.y0, y1, ctx.hold, judged)


__all__ = ["REGION_VARS", "Context", "diagnose", "holdout_mask", "prepare"]
