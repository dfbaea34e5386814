"""Where the simulator departs from measured data, which unmodelled effect causes it, and how far
the gap shrinks once that effect is added, judged on data withheld from the fit.

Every candidate effect is fitted (scipy's least squares) on the fit part and scored by the share of
the gap it removes on the withheld part. A candidate earns its place only with a real held-out
improvement, a parameter well above its uncertainty and a physically plausible value; where none
does, the answer is "unexplained". Candidates whose contributions the data cannot tell apart are
named together. A second effect is sought on what the first leaves.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.data import GapData
from cmcan.gap.effects import LIBRARY, Effect, simulate
from cmcan.sim.physics import DriveParams

REGION_VARS = ("dp_bar", "temp_c", "pump_speed_rpm", "pump_disp_cc")
MIN_REDUCTION = 0.3  # share of the remaining held-out gap a candidate must remove to be considered
HIGH_CONFIDENCE = 0.6  # ... and this much, leaving little but noise, to be named with confidence
MIN_SIGMAS = 5.0  # fitted parameter / its standard uncertainty
GAP_OVER_NOISE = 1.5  # a held-out gap below this many noise levels is no gap
MIN_GAP_SHARE = 0.0025
STRUCTURE_MAX = 0.3  # residual trend along any variable, in noise levels, still compatible with "explained"
AMBIGUOUS_CORR = 0.995  # contributions this correlated cannot be told apart on the data
AMBIGUOUS_MARGIN = 0.03
MAX_EFFECTS = 2
MAX_FIT_POINTS = 40_000


@dataclass
class Fit:
    effect: Effect
    theta: NDArray[np.float64]
    sigma: NDArray[np.float64]
    reduction: float  # held-out, relative to the model before this effect
    plausible: bool
    significant: bool
    contribution: NDArray[np.float64] = field(repr=False)  # its change of the simulated output, all points

    @property
    def eligible(self) -> bool:
        return self.plausible and self.significant and self.reduction >= MIN_REDUCTION

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.effect.name,
            "parameters": {
                q.name: {
                    "value": float(v),
                    "uncertainty": float(s),
                    "unit": q.unit,
                    "plausible_range": list(q.plausible),
                }
                for q, v, s in zip(self.effect.params, self.theta, self.sigma, strict=True)
            },
            "heldout_gap_reduction": float(self.reduction),
            "plausible": bool(self.plausible),
            "significant": bool(self.significant),
        }


def _rmse(e: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


def holdout_mask(d: GapData, spec: str | None) -> tuple[NDArray[np.bool_], str]:
    """Withheld points by operating region (default: the hottest quarter, or the highest-pressure
    quarter where the oil temperature hardly varies) so an added effect must extrapolate."""
    x = d.x
    if spec is None:
        spec = "temp_c:top25" if np.ptp(x.temp_c) >= 15.0 else "dp_bar:top25"
    if spec == "random25":
        mask = np.random.default_rng(0).random(len(d.y)) < 0.25
        return mask, spec
    try:
        var, side = spec.split(":")
        share = float(side[-2:]) / 100.0
        end = side[:-2]
        values = x.t_s if var == "time" else getattr(x, var)
    except (ValueError, AttributeError):
        raise ValueError(
            f"holdout {spec!r}: expected VAR:topNN or VAR:bottomNN with VAR one of "
            f"{', '.join((*REGION_VARS, 'time'))}, or random25"
        ) from None
    if end not in ("top", "bottom", "last", "first") or not 0 < share < 1:
        raise ValueError(f"holdout {spec!r}: expected top/bottom/last/first and a share in 01..99")
    mask = values >= np.quantile(values, 1 - share) if end in ("top", "last") else values <= np.quantile(values, share)
    return mask, spec


def noise_level(g: NDArray[np.float64], steady: NDArray[np.bool_]) -> float:
    """Point-to-point noise of the gap from successive steady points (robust MAD estimate)."""
    both = steady[1:] & steady[:-1]
    d = np.diff(g)[both] if both.sum() > 20 else np.diff(g)
    return float(np.median(np.abs(d - np.median(d))) / 0.6745 / np.sqrt(2)) if len(d) else 0.0


def _fit(
    p: DriveParams,
    d: GapData,
    fitted: list[tuple[Effect, NDArray[np.float64]]],
    cand: Effect,
    fit_mask: NDArray[np.bool_],
    hold: NDArray[np.bool_],
    base_rmse_h: float,
    scale: float,
) -> tuple[Fit, list[tuple[Effect, NDArray[np.float64]]]]:
    from scipy.optimize import least_squares

    effects = [*(e for e, _ in fitted), cand]
    x0 = np.concatenate([*(th for _, th in fitted), [q.start for q in cand.params]])
    sizes = [len(e.params) for e in effects]
    lo = np.concatenate([[q.bound_lo for q in e.params] for e in effects])
    hi = np.full_like(lo, np.inf)
    idx = np.flatnonzero(fit_mask & judged_points(d, any(e.name == "motor_speed_lag" for e in effects)))
    if len(idx) > MAX_FIT_POINTS:  # an even thinning keeps every region and the time structure
        idx = idx[:: int(np.ceil(len(idx) / MAX_FIT_POINTS))]
        keep = np.zeros_like(fit_mask)
        keep[idx] = True
        fit_mask = keep
    lag_effects = any(e.name == "motor_speed_lag" for e in effects)
    # Static effects are judged where the quasi-static simulator holds (steady points); a lag shows
    # only in transients, so a candidate set with a lag is judged on every point.
    pts = judged_points(d, lag_effects)
    fit_mask, hold = fit_mask & pts, hold & pts
    y_before = simulate(p, d.x, fitted) * scale
    base_rmse_h = _rmse((d.y - y_before)[hold])
    xf = d.x if lag_effects else d.x.subset(fit_mask)  # a lag needs the whole time series
    yf = d.y[fit_mask]

    def split(theta: NDArray[np.float64]) -> list[tuple[Effect, NDArray[np.float64]]]:
        out, k = [], 0
        for e, n in zip(effects, sizes, strict=True):
            out.append((e, theta[k : k + n]))
            k += n
        return out

    def resid(theta: NDArray[np.float64]) -> NDArray[np.float64]:
        y = simulate(p, xf, split(theta)) * scale
        return (y[fit_mask] if lag_effects else y) - yf

    res = least_squares(resid, x0, bounds=(lo, hi), method="trf", x_scale="jac")
    theta = res.x
    dof = max(len(yf) - len(theta), 1)
    s2 = float(np.sum(res.fun**2)) / dof
    try:
        cov = np.linalg.pinv(res.jac.T @ res.jac) * s2
        sigma = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        sigma = np.full_like(theta, np.inf)
    all_fitted = split(theta)
    y_all = simulate(p, d.x, all_fitted) * scale
    th_c, sg_c = all_fitted[-1][1], sigma[-len(cand.params) :]
    reduction = 1.0 - _rmse((d.y - y_all)[hold]) / base_rmse_h if base_rmse_h > 0 else 0.0
    plausible = all(q.plausible[0] <= v <= q.plausible[1] for q, v in zip(cand.params, th_c, strict=True))
    significant = all(abs(v) >= MIN_SIGMAS * s for v, s in zip(th_c, sg_c, strict=True))
    return Fit(cand, th_c, sg_c, reduction, plausible, significant, y_all - y_before), all_fitted


def judged_points(d: GapData, with_lag: bool = False) -> NDArray[np.bool_]:
    if with_lag or d.steady.sum() < 200:
        return np.ones(len(d.y), dtype=bool)
    return d.steady


def regions(d: GapData, gap: NDArray[np.float64], mask: NDArray[np.bool_]) -> dict[str, Any]:
    """The gap by operating region: quartile bins of each variable, steady against transient."""
    out: dict[str, Any] = {}
    g, total = gap[mask], float(np.sum(gap[mask] ** 2)) or 1.0
    for var in REGION_VARS:
        v = getattr(d.x, var)[mask]
        edges = np.unique(np.quantile(v, [0, 0.25, 0.5, 0.75, 1.0]))
        bins = []
        for a, b in itertools.pairwise(edges):
            sel = (v >= a) & ((v <= b) if b == edges[-1] else (v < b))
            if sel.any():
                bins.append(
                    {
                        "range": [float(a), float(b)],
                        "points": int(sel.sum()),
                        "mean_gap": float(g[sel].mean()),
                        "rmse": _rmse(g[sel]),
                        "share": float(np.sum(g[sel] ** 2) / total),
                    }
                )
        out[var] = bins
    st = d.steady[mask]
    out["steady"] = {"points": int(st.sum()), "rmse": _rmse(g[st]), "share": float(np.sum(g[st] ** 2) / total)}
    out["transient"] = {"points": int((~st).sum()), "rmse": _rmse(g[~st]), "share": float(np.sum(g[~st] ** 2) / total)}
    return out


def _decile_means(v: NDArray[np.float64], g: NDArray[np.float64]) -> tuple[NDArray[np.float64], list]:
    edges = np.unique(np.quantile(v, np.linspace(0, 1, 11)))
    idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, len(edges) - 2)
    means = np.array([g[idx == k].mean() if np.any(idx == k) else 0.0 for k in range(len(edges) - 1)])
    counts = np.bincount(idx, minlength=len(edges) - 1)
    return means, [(float(edges[k]), float(edges[k + 1]), int(counts[k])) for k in range(len(edges) - 1)]


def dominant_region(d: GapData, gap: NDArray[np.float64]) -> dict[str, Any]:
    """The variable whose decile means explain most of the squared gap, and the stretch of its range
    that holds most of the gap: the fewest top deciles (by share) that together hold 80 % of it."""
    total = float(np.sum(gap**2)) or 1.0
    best = None
    for var in REGION_VARS:
        means, bins = _decile_means(getattr(d.x, var), gap)
        explained = float(sum(m * m * n for m, (_, _, n) in zip(means, bins, strict=True))) / total
        if best is None or explained > best[0]:
            best = (explained, var, means, bins)
    assert best is not None
    explained, var, means, bins = best
    shares = np.array([m * m * n for m, (_, _, n) in zip(means, bins, strict=True)]) / total
    order = np.argsort(shares)[::-1]
    keep, acc = [], 0.0
    for k in order:
        keep.append(int(k))
        acc += shares[k]
        if acc >= 0.8 * explained:
            break
    lo, hi = min(bins[k][0] for k in keep), max(bins[k][1] for k in keep)
    return {"variable": var, "range": [lo, hi], "share": float(acc), "explained_by_variable": explained}


def residual_structure(d: GapData, resid: NDArray[np.float64]) -> dict[str, float]:
    """RMS of the residual's decile means along each operating variable: what a right effect leaves
    is noise (near zero here), what a stand-in leaves is a trend."""
    return {var: float(np.sqrt(np.mean(_decile_means(getattr(d.x, var), resid)[0] ** 2))) for var in REGION_VARS}


def time_lag(d: GapData, y_sim: NDArray[np.float64]) -> dict[str, float]:
    """Delay of the measured behind the simulated output, from the cross-correlation of their rates."""
    dt = float(np.median(np.diff(d.x.t_s)))
    same = np.r_[False, d.x.segment[1:] == d.x.segment[:-1]]
    a = np.where(same, np.diff(d.y, prepend=d.y[0]), 0.0)
    b = np.where(same, np.diff(y_sim, prepend=y_sim[0]), 0.0)
    if not a.any() or not b.any():
        return {"lag_s": 0.0, "correlation": 0.0}
    best_k, best_c = 0, -np.inf
    for k in range(0, 11):  # up to 1 s at 10 Hz
        c = float(np.dot(a[k:], b[: len(b) - k]))
        if c > best_c:
            best_k, best_c = k, c
    norm = float(np.sqrt(np.dot(a, a) * np.dot(b, b))) or 1.0
    return {"lag_s": best_k * dt, "correlation": best_c / norm}


ROBUSTNESS_SPLITS = (
    "temp_c:top25",
    "dp_bar:top25",
    "pump_speed_rpm:top25",
    "pump_speed_rpm:bottom25",
    "pump_disp_cc:bottom25",
)


def _robustness(
    p: DriveParams, d: GapData, fitted: list[tuple[Effect, NDArray[np.float64]]], scale: float, sigma_n: float
) -> dict[str, float]:
    """Held-out gap reduction of the selected effects refitted with each operating region withheld in
    turn: an effect that really is there extrapolates in every direction, a stand-in does not."""
    out = {}
    effects = [e for e, _ in fitted]
    y0 = simulate(p, d.x, []) * scale
    for spec in ROBUSTNESS_SPLITS:
        hold, _ = holdout_mask(d, spec)
        if hold.all() or not hold.any():
            continue
        base_h = _rmse((d.y - y0)[hold])
        if base_h <= GAP_OVER_NOISE * sigma_n:
            continue  # no gap in that region to extrapolate to
        f, _j = _fit(p, d, [(e, th) for e, th in fitted[:-1]], effects[-1], ~hold, hold, base_h, scale)
        out[spec] = f.reduction
    return out


def _best_pair(
    p: DriveParams,
    d: GapData,
    candidates: dict[str, Effect],
    fit_mask: NDArray[np.bool_],
    hold: NDArray[np.bool_],
    base_h: float,
    scale: float,
    sigma_n: float,
) -> tuple[float, list[str], list[tuple[Effect, NDArray[np.float64]]]] | None:
    best = None
    names = list(candidates)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            ea, eb = candidates[a], candidates[b]
            start = [(ea, np.array([q.start for q in ea.params]))]
            f, joint = _fit(p, d, start, eb, fit_mask, hold, base_h, scale)
            th_a = joint[0][1]
            ok_a = all(q.plausible[0] <= v <= q.plausible[1] for q, v in zip(ea.params, th_a, strict=True))
            y = simulate(p, d.x, [joint[0]]) * scale - simulate(p, d.x, []) * scale
            sig_a = _rmse(y) >= MIN_SIGMAS * sigma_n / np.sqrt(max(len(y), 1)) and _rmse(y) > 0.5 * sigma_n
            if f.eligible and ok_a and sig_a and (best is None or f.reduction > best[0]):
                best = (f.reduction, [a, b], joint)
    return best


def diagnose(
    d: GapData, p: DriveParams, holdout: str | None = None, candidates: dict[str, Effect] | None = None
) -> tuple[dict[str, Any], dict[str, NDArray[np.float64]]]:
    """The report, and the arrays behind its plots (simulated output before and after)."""
    candidates = candidates or LIBRARY
    scale = p.motor_disp_cc / 1000.0 if d.quantity == "flow_lpm" else 1.0
    hold_all, spec = holdout_mask(d, holdout)
    fit_mask = ~hold_all
    hold = hold_all & judged_points(d)  # where the verdicts on static effects are judged
    y0 = simulate(p, d.x, []) * scale
    g0 = d.y - y0
    sigma_n = noise_level(g0, d.steady)
    mean_y = float(np.mean(np.abs(d.y))) or 1.0
    # Below this a gap is within sensor noise or too small to matter (0.25 % of the output).
    gap_floor = max(GAP_OVER_NOISE * sigma_n, MIN_GAP_SHARE * mean_y)

    def _judged_hold(effects: list[tuple[Effect, NDArray[np.float64]]]) -> NDArray[np.bool_]:
        return hold_all & judged_points(d, any(e.name == "motor_speed_lag" for e, _ in effects))

    fitted: list[tuple[Effect, NDArray[np.float64]]] = []
    rounds: list[dict[str, Any]] = []
    selected: list[str] = []
    ambiguous: list[list[str]] = []
    confidence: dict[str, str] = {}
    robustness: dict[str, float] = {}
    structure: dict[str, float] = {}
    all_fits: dict[str, Fit] = {}
    groups = 0
    while groups < MAX_EFFECTS:
        y_now = simulate(p, d.x, fitted) * scale
        base_h = _rmse((d.y - y_now)[hold])
        if base_h <= gap_floor and _rmse((d.y - y_now)[hold_all]) <= gap_floor:
            break  # no gap left, neither at steady points nor in transients
        fits, joint = {}, {}
        for name, cand in candidates.items():
            if name in selected:
                continue
            f, j = _fit(p, d, fitted, cand, fit_mask, hold, base_h, scale)
            fits[name], joint[name] = f, j
        if not fitted:
            all_fits = dict(fits)
        rounds.append({name: f.to_dict() for name, f in fits.items()})
        eligible = [f for f in fits.values() if f.eligible]
        best = max(eligible, key=lambda f: f.reduction) if eligible else None
        left = (
            _rmse((d.y - simulate(p, d.x, joint[best.effect.name]) * scale)[_judged_hold(joint[best.effect.name])])
            if best
            else base_h
        )
        if not fitted and (best is None or left > 2.5 * sigma_n):
            # Two effects can hide each other (one slows the motor, the other speeds it up): try pairs.
            pair = _best_pair(p, d, candidates, fit_mask, hold, base_h, scale, sigma_n)
            if pair is not None and pair[0] >= (best.reduction if best else 0.0) + 0.2:
                _red, names, pair_fit = pair
                fitted = pair_fit
                selected += names
                groups += 2
                break
        if best is None:
            break
        twins = [
            f.effect.name
            for f in eligible
            if f is not best
            and f.reduction >= best.reduction - AMBIGUOUS_MARGIN
            and abs(np.corrcoef(f.contribution, best.contribution)[0, 1]) >= AMBIGUOUS_CORR
        ]
        fitted = joint[best.effect.name]
        selected.append(best.effect.name)
        groups += 1
        if twins:  # the data cannot tell these apart: name them all, pick none
            ambiguous.append([best.effect.name, *twins])
            selected += twins
    if selected:
        robustness = _robustness(p, d, fitted, scale, sigma_n)
        resid_h = _rmse((d.y - simulate(p, d.x, fitted) * scale)[_judged_hold(fitted)])
        worst = min(robustness.values(), default=1.0)
        structure = residual_structure(d, d.y - simulate(p, d.x, fitted) * scale)
        high = (
            worst >= HIGH_CONFIDENCE
            and resid_h <= 2.5 * max(sigma_n, 1e-9)
            and max(structure.values()) <= STRUCTURE_MAX * sigma_n
        )
        confidence = dict.fromkeys(selected, "high" if high else "low")
    y1 = simulate(p, d.x, fitted) * scale
    g1 = d.y - y1
    if any(e.name == "motor_speed_lag" for e, _ in fitted):
        hold = hold_all  # a selected lag was judged on every point: report it so
    gap_h0, gap_h1 = _rmse(g0[hold]), _rmse(g1[hold])
    if selected:
        verdict = "explained" if all(v == "high" for v in confidence.values()) else "partly explained (low confidence)"
        for group in ambiguous:
            verdict += f"; {' and '.join(group)} cannot be told apart on these data"
    elif gap_h0 > gap_floor or _rmse(g0[hold_all]) > gap_floor:
        verdict = "unexplained"
    else:
        verdict = "no significant gap"
    reg_before = regions(d, g0, np.ones(len(g0), dtype=bool))
    unit = "rpm" if d.quantity == "motor_speed_rpm" else "l/min"
    report = {
        "source": d.source,
        "quantity": d.quantity,
        "unit": unit,
        "points": len(d.y),
        "noise_level": sigma_n,
        "gap_before": {
            "rmse": _rmse(g0),
            "rmse_pct": 100 * _rmse(g0) / mean_y,
            "mean": float(g0.mean()),
            "heldout_rmse": gap_h0,
        },
        "where": {
            "regions": reg_before,
            "dominant_region": dominant_region(d, g0),
            "time_lag": time_lag(d, y0),
            "dependence": {
                v: [{"range": b["range"], "mean_gap": b["mean_gap"]} for b in reg_before[v]] for v in REGION_VARS
            },
        },
        "effects": [f.to_dict() for f in all_fits.values()],
        "rounds": rounds,
        "selected": selected,
        "ambiguous": ambiguous,
        "confidence": confidence,
        "robustness": robustness,
        "residual_structure": structure,
        "verdict": verdict,
        "fitted": {e.name: {q.name: float(v) for q, v in zip(e.params, th, strict=True)} for e, th in fitted},
        "gap_after": {
            "rmse": _rmse(g1),
            "rmse_pct": 100 * _rmse(g1) / mean_y,
            "heldout_rmse": gap_h1,
            "heldout_reduction": 1 - gap_h1 / gap_h0 if gap_h0 > 0 else 0.0,
            "regions_heldout": regions(d, g1, hold),
        },
        "holdout": {
            "spec": spec,
            "points": int(hold_all.sum()),
            "judged_points": int(hold.sum()),
            "judged_on": "steady points" if not judged_points(d).all() else "all points",
            "regions_before": regions(d, g0, hold),
        },
    }
    return report, {"y_before": y0, "y_after": y1, "holdout": hold_all}
