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
from cmcan.gap.context import REGION_VARS, Context, holdout_mask, prepare, rmse
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
    Diagnosis,
    FittedEffect,
    Flag,
    GapStats,
    Holdout,
)
from cmcan.gap.search import Search, no_gap, search
from cmcan.gap.where import regions, residual_structure, where
from cmcan.sim.physics import DriveParams


def _stats(ctx: Context, y: NDArray[np.float64], h: NDArray[np.bool_]) -> tuple[float, float, float, float]:
    g = ctx.d.y - y
    return rmse(g), 100 * rmse(g) / ctx.mean_y, float(g.mean()), rmse(g[h])


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
    return "no significant gap" if no_gap(ctx, ctx.y0) else "unexplained"


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


def judge_answer(ctx: Context, found: Search) -> Judgement:
    final = found.final
    if final is None or not found.groups:
        return Judgement()
    robust = robustness(ctx, final)
    resid = (ctx.d.y - final.y)[final.judged]
    structure = residual_structure(ctx.d.subset(final.judged), resid, ctx.noise(final.with_time))
    flags = bound_flags(ctx, final)
    return Judgement(confidence(ctx, final, found.separation, robust, structure, flags), flags, robust, structure)


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
    answer = judge_answer(ctx, found)
    named = found.final is not None and bool(found.groups)
    y1 = found.final.y if found.final is not None and named else ctx.y0
    judged = found.final.judged if found.final is not None and named else ctx.static_pts
    h = ctx.hold & judged
    b, a = _stats(ctx, ctx.y0, h), _stats(ctx, y1, h)
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
        fitted=_fitted(ctx, found),
        confidence=answer.confidence,
        flags=answer.flags,
        verdict=_verdict(ctx, found, answer.confidence, answer.flags),
        after=After(a[0], a[1], a[3], 1 - a[3] / b[3] if b[3] > 0 else 0.0, regions(d, d.y - y1, h)),
        holdout=Holdout(
            ctx.spec, int(ctx.hold.sum()), int(h.sum()), _judged_on(ctx, judged), regions(d, d.y - ctx.y0, h)
        ),
        robustness=answer.robustness,
        residual_structure=answer.structure,
        refused_points=d.refused,
        refused_why=d.refused_why,
    )
    return diag, Arrays(ctx.y0, y1, ctx.hold)


__all__ = ["REGION_VARS", "Context", "diagnose", "holdout_mask", "prepare"]
