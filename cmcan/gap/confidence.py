"""How sure an answer is: robustness to the withheld region, bound flags, the confidence level."""

from __future__ import annotations

from cmcan.gap.context import GAP_OVER_NOISE, Context, holdout_mask, rmse
from cmcan.gap.fit import MIN_REDUCTION, SetFit, fit_set, param_fits
from cmcan.gap.result import (
    HIGH,
    LOW,
    MEDIUM,
    Confidence,
    Flag,
)
from cmcan.gap.where import varying
from cmcan.roles import DP, PUMP_DISP, PUMP_SPEED, TEMP

# Calibrated on `cmcan gap bench` (docs/gap.md, "Calibration"): "high" needs all of these.
HIGH_REDUCTION = 0.6  # withheld gap removed by the selection
HIGH_ROBUST = 0.5  # ... and in every region withheld in turn
HIGH_RESIDUAL = 2.5  # withheld residual, in noise levels
HIGH_STRUCTURE = 0.1  # trend left along any input, in noise levels (beyond what noise puts there)
HIGH_SEPARATION = 0.1  # the nearest rival outside the answer leaves this much more (noise variances)
MEDIUM_ROBUST = 0.3

ROBUSTNESS_SPLITS = (
    f"{TEMP}:top25",
    f"{DP}:top25",
    f"{PUMP_SPEED}:top25",
    f"{PUMP_SPEED}:bottom25",
    f"{PUMP_DISP}:bottom25",
)


def robustness(ctx: Context, final: SetFit) -> dict[str, float]:
    """Withheld gap reduction of the selection refitted with each operating region withheld in turn:
    an effect that really is there extrapolates in every direction, a stand-in does not."""
    out = {}
    moving = set(varying(ctx.d))
    for spec in ROBUSTNESS_SPLITS:
        if spec.split(":")[0] not in moving:
            continue
        hold, _ = holdout_mask(ctx.d, spec)
        h = hold & final.judged
        if h.all() or not h.any():
            continue
        base_h = rmse((ctx.d.y - ctx.y0)[h])
        if base_h <= GAP_OVER_NOISE * ctx.sigma:
            continue  # no gap in that region to extrapolate to
        s = fit_set(ctx, final.effects, final.theta, fit_mask=~hold)
        out[spec] = 1.0 - rmse((ctx.d.y - s.y)[h]) / base_h
    return out


def bound_flags(ctx: Context, final: SetFit) -> tuple[Flag, ...]:
    """Every fitted value of the final (joint) fit checked against its plausible range."""
    flags = []
    for e, th, sg in zip(final.effects, final.theta, final.sigma, strict=True):
        for q in param_fits(ctx, e, th, sg):
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
    degenerate_holdout: bool = False,
) -> Confidence:
    """The level and why it is not higher. A degenerate hold-out (the withheld part hardly differs
    from the fit part) tests no extrapolation, so its figures cannot make an answer high."""
    sigma = ctx.noise(final.with_time)
    h = ctx.hold & final.judged
    base_h = rmse((ctx.d.y - ctx.y0)[h])
    left = rmse((ctx.d.y - final.y)[h])
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
    if degenerate_holdout:
        reasons.append("the withheld part hardly differs from the fit part (a degenerate hold-out)")
    if not reasons:
        return Confidence(HIGH, (), checks)
    if flags or checks["robust_min"] < MEDIUM_ROBUST or checks["heldout_reduction"] < MIN_REDUCTION:
        return Confidence(LOW, tuple(reasons), checks)
    return Confidence(MEDIUM, tuple(reasons), checks)
