"""The data as the diagnosis sees it: withheld part, judged points, noise level, gap floor."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cmcan.errors import CmcanError, Kind
from cmcan.gap.data import MIN_BLOCKS, MIN_POINTS, GapData
from cmcan.gap.effects import LIBRARY, Effect, Scale, simulate
from cmcan.roles import DP, PUMP_DISP, PUMP_SPEED, TEMP, UNITS
from cmcan.sim.physics import DriveParams

REGION_VARS = (DP, TEMP, PUMP_SPEED, PUMP_DISP)
GAP_OVER_NOISE = 1.5  # a gap below this many noise levels is no gap
MIN_GAP_SHARE = 0.0025  # ... nor is one below this share of the output
CHUNKS = 20  # stretches of the data over which a candidate's advantage over a rival must hold
RELIEF_MARGIN = 0.9  # points whose pressure reaches this share of the relief setting are not judged
MIN_STEADY = 200  # fewer steady points than this: judge static effects on every followable point
# A withheld region tests an extrapolation only where it lies this far from the fit part along its
# variable (median to median): 5 C of oil temperature (the oil's viscosity changes by 15-30 % over
# 5 C), or a tenth of the highest delta pressure or pump speed in the data or of the pump's size.
MIN_REACH_C = 5.0
MIN_REACH_SHARE = 0.1


def rmse(e: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


def default_holdout(d: GapData, judged: NDArray[np.bool_], scale: Scale) -> str:
    """The withheld part an added effect must extrapolate to: the hottest quarter, or where that lies
    too close to the rest (a degenerate hold-out, :func:`holdout_reach`) the highest-pressure quarter;
    where both are degenerate, the one reaching furthest for its variable. Where neither varies: a time
    series's last quarter; a table's top quarter of the first input that varies, else a random quarter
    (a table has no time order)."""
    x = d.x
    tried = []
    for var in (TEMP, DP):
        if np.ptp(getattr(x, var)) == 0.0:
            continue
        spec = f"{var}:top25"
        hold, _ = holdout_mask(d, spec)
        r = holdout_reach(d, hold, judged, spec, scale)
        if r is None:  # no judged point on one side of the cut: no use
            continue
        if not r.degenerate:
            return spec
        tried.append((r.reach / r.needed, spec))
    if tried:
        return max(tried)[1]
    moving = [v for v in REGION_VARS if np.ptp(getattr(x, v)) > 0.0]
    return "time:last25" if d.has_time else f"{moving[0]}:top25" if moving else "random25"


def holdout_mask(d: GapData, spec: str) -> tuple[NDArray[np.bool_], str]:
    """Withheld points by operating region, so an added effect must extrapolate (``VAR:topNN``,
    ``VAR:bottomNN``), by time (``time:lastNN``, a time series only) or a random quarter."""
    x = d.x
    if spec == "random25":  # a table is in its canonical order, so the same rows draw the same quarter
        return np.random.default_rng(0).random(len(d.y)) < 0.25, spec
    if spec.split(":")[0] == "time" and not d.has_time:
        raise ValueError(
            f"--holdout {spec!r}: an operating-point table has no time order; withhold by "
            f"{', '.join(REGION_VARS)} or random25"
        )
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


@dataclass(frozen=True)
class Reach:
    """How far the withheld part lies from the fit part along the variable it was cut by."""

    reach: float  # |median of the withheld part - median of the fit part|, in the variable's unit
    needed: float  # the least reach that tests an extrapolation (MIN_REACH_C, MIN_REACH_SHARE)
    message: str  # why the hold-out is degenerate; empty where it is not

    @property
    def degenerate(self) -> bool:
        return bool(self.message)


def holdout_reach(
    d: GapData, hold: NDArray[np.bool_], judged: NDArray[np.bool_], spec: str, scale: Scale
) -> Reach | None:
    """Whether a hold-out by an operating region asks the effects to extrapolate at all: its judged
    points' median along the variable against the fit part's. A variable that barely varies (oil at
    34-36 C) withholds a region that is the fit part's own, and a reduction of the gap there says
    nothing about extrapolation. None for withheld parts that are not a region of an input (time,
    random25)."""
    var = spec.split(":")[0]
    if var not in REGION_VARS:
        return None
    v = getattr(d.x, var)
    held, fit = v[hold & judged], v[~hold & judged]
    if not len(held) or not len(fit):
        return None
    reach = float(abs(np.median(held) - np.median(fit)))
    top = {DP: scale.dp_max_bar, PUMP_SPEED: scale.speed_max_rpm, PUMP_DISP: scale.pump_disp_max_cc}
    needed = MIN_REACH_C if var == TEMP else MIN_REACH_SHARE * top[var]
    if reach >= needed:
        return Reach(reach, needed, "")
    u = "C" if var == TEMP else UNITS.get(var, "")
    msg = (
        f"the withheld part ({spec}: {var} {held.min():.4g}..{held.max():.4g} {u}) lies only {reach:.3g} {u} "
        f"from the fit part ({fit.min():.4g}..{fit.max():.4g} {u}), median to median, less than the "
        f"{needed:.3g} {u} that tests an extrapolation: a degenerate hold-out; withhold by a variable that "
        f"varies more"
    )
    return Reach(reach, needed, msg)


def _mad_of_differences(d: NDArray[np.float64]) -> float:
    """The noise level behind differences of two noisy values each (robust: MAD, / sqrt 2)."""
    return float(np.median(np.abs(d - np.median(d))) / 0.6745 / np.sqrt(2)) if len(d) else 0.0


def noise_level(g: NDArray[np.float64], steady: NDArray[np.bool_], segment: NDArray[np.int64]) -> float:
    """Point-to-point noise of the gap from successive steady points of a time series (robust MAD)."""
    both = steady[1:] & steady[:-1] & (segment[1:] == segment[:-1])
    return _mad_of_differences(np.diff(g)[both] if both.sum() > 20 else np.diff(g))


def table_noise_level(g: NDArray[np.float64], mask: NDArray[np.bool_], d: GapData) -> float:
    """Noise of the gap in an operating-point table, which has no time order: each point against its
    nearest neighbour in operating-point space (the inputs that vary, each in units of its standard
    deviation; a replicate is a neighbour at distance 0), robust MAD of those differences. Where no
    input varies, every point is a replicate: the scatter about the median."""
    idx = np.flatnonzero(mask)
    if len(idx) < 2:
        return 0.0
    cols = [getattr(d.x, v)[idx] for v in REGION_VARS]
    z = [(c - c.mean()) / c.std() for c in cols if np.ptp(c) > 0.0]
    gi = g[idx]
    if not z:
        return float(np.median(np.abs(gi - np.median(gi))) / 0.6745)
    from scipy.spatial import cKDTree

    pts = np.column_stack(z)
    _, nn = cKDTree(pts).query(pts, k=2)
    # The nearest other point (a replicate at distance 0 may come before the point itself).
    other = np.where(nn[:, 0] == np.arange(len(idx)), nn[:, 1], nn[:, 0])
    return _mad_of_differences(gi - gi[other])


def followable(d: GapData, p: DriveParams) -> NDArray[np.bool_]:
    """Points where the simulator on measured inputs can follow the machine: not at the relief valve
    (its flow changes by tens of l/min per bar, more than a pressure reading resolves) and not with
    the loop's other side high (negative delta pressure, which a high-side sensor does not show)."""
    return (d.dp_lo_bar > 0.0) & (d.dp_hi_bar < RELIEF_MARGIN * p.relief_dp_bar)


def chunks(n: int, k: int = CHUNKS) -> NDArray[np.int64]:
    """Contiguous stretches of the points in data order, of (nearly) equal size: stretches of time in
    a time series, slabs of operating points (by oil temperature, then delta pressure, ...) in a table,
    whose rows are in their canonical order (:data:`cmcan.gap.data.CANONICAL`)."""
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
    lib = candidates or LIBRARY
    cands = {
        k: e
        for k, e in lib.items()
        if d.quantity in e.quantities and (d.has_time or not e.needs_time) and _varies_for(e, d)
    }
    fol = followable(d, p)
    steady = d.steady & fol
    static_pts = steady if steady.sum() >= MIN_STEADY or not d.has_time else fol
    scale = Scale.of(p, d.x, d.y)
    hold, spec = holdout_mask(d, holdout if holdout is not None else default_holdout(d, static_pts, scale))
    _enough_judged(d, p, fol, hold, spec)
    y0 = simulate(p, d.x, [], d.quantity)
    if d.has_time:
        sigma = noise_level(d.y - y0, static_pts, d.x.segment)
        sigma_dyn = max(noise_level(d.y - y0, fol, d.x.segment), sigma)
    else:
        sigma = sigma_dyn = table_noise_level(d.y - y0, static_pts, d)
    mean_y = float(np.mean(np.abs(d.y))) or 1.0
    # Below this a gap is within sensor noise or too small to matter.
    floor = max(GAP_OVER_NOISE * sigma, MIN_GAP_SHARE * mean_y)
    return Context(
        d,
        p,
        scale,
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


class NotJudgeable(CmcanError):
    """Too few points the simulator can follow to diagnose (a data error, exit 65; deliberately not a
    ValueError, which the command line reads as a bad --holdout)."""

    kind = Kind.DATA


def _enough_judged(d: GapData, p: DriveParams, fol: NDArray[np.bool_], hold: NDArray[np.bool_], spec: str) -> None:
    need = MIN_BLOCKS if d.has_time else MIN_POINTS
    n = int(fol.sum())
    if n < need:
        near = int(np.sum(d.dp_hi_bar >= RELIEF_MARGIN * p.relief_dp_bar))
        zero = int(np.sum(d.dp_lo_bar <= 0.0))
        why = []
        if near:
            why.append(
                f"{near} with {DP} up to {float(np.max(d.dp_hi_bar)):.4g} bar, within "
                f"{100 * (1 - RELIEF_MARGIN):.0f} % of the relief setting ({p.relief_dp_bar:.4g} bar)"
            )
        if zero:
            why.append(f"{zero} with {DP} at or below 0 bar")
        raise NotJudgeable(
            f"{d.source}: only {n} of {len(d.y)} points can be judged (need at least {need}): "
            + ("; ".join(why) or "the simulator cannot follow the rest")
        )
    if not (hold & fol).any():
        raise NotJudgeable(
            f"{d.source}: no point of the withheld part ({spec}) can be judged; choose another --holdout"
        )


def _varies_for(e: Effect, d: GapData) -> bool:
    """A gain on an input that is zero throughout cannot show; everything else may."""
    return not (e.name == "pressure_sensor_gain" and not np.any(d.x.dp_bar))
