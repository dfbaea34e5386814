"""The gap diagnosis's answer as typed, frozen values: what ``diagnose()`` returns, what the report
files and the command line read (by attribute), and what ``report.json`` is written from."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

HIGH, MEDIUM, LOW = "high", "medium", "low"
LEVELS = (HIGH, MEDIUM, LOW)


@dataclass(frozen=True)
class ParamFit:
    name: str
    unit: str
    value: float
    uncertainty: float  # one standard uncertainty, from the fit's Jacobian (widened for correlated residuals)
    plausible: tuple[float, float]  # the plausible range on this machine (the fit's bounds)
    at_bound: bool  # the fit ended on a bound of the plausible range


@dataclass(frozen=True)
class CandidateFit:
    """One candidate effect fitted (jointly with the effects found before it) and judged."""

    name: str
    kind: str  # "physical" or "sensor"
    params: tuple[ParamFit, ...]
    heldout_reduction: float  # share of the withheld part's remaining gap it removes
    judged_rmse: float  # residual RMSE over every judged point (fit and withheld part)
    significant: bool  # every parameter at least 5 uncertainties from zero
    eligible: bool  # significant and a real withheld reduction: may be named

    @property
    def at_bound(self) -> bool:
        return any(q.at_bound for q in self.params)


@dataclass(frozen=True)
class Round:
    """Candidates fitted on top of ``base`` (the effects found so far)."""

    base: tuple[str, ...]
    candidates: tuple[CandidateFit, ...]


@dataclass(frozen=True)
class PairFit:
    """Two effects fitted jointly by the pair search, each judged as if fitted last on top of the other."""

    names: tuple[str, str]
    members: tuple[CandidateFit, CandidateFit]
    heldout_reduction: float  # share of the withheld gap the two remove together
    eligible: bool  # both members may be named and neither sits on a bound


@dataclass(frozen=True)
class PairSearch:
    """The pair search, run where no single effect leaves little but noise: the pairs fitted jointly
    after the linearized screening, and whether one removed enough more than one effect alone."""

    best_single: str | None  # the best single effect that qualified (None: none did)
    single_reduction: float  # its share of the withheld gap (0 where none qualified)
    needed: float  # a pair must remove at least this share of the withheld gap to be named
    pairs: tuple[PairFit, ...]
    chosen: tuple[str, str] | None  # the pair named (None: the single effects stand)


@dataclass(frozen=True)
class GapStats:
    """The gap at the judged points (what the diagnosis judges), and for context at every point."""

    rmse: float  # at the judged points
    rmse_pct: float
    mean: float
    heldout_rmse: float  # at the judged points of the withheld part
    all_rmse: float  # at every point, judged or not (the unjudged ones at the relief valve, ...)


@dataclass(frozen=True)
class Coverage:
    """Which points the figures are over: the judged ones, and why the others are not judged."""

    judged: int
    total: int
    on: str  # "steady points", "every point the simulator can follow", "every operating point"
    near_relief: int  # not judged: the pressure within 10 % of the relief setting
    no_pressure: int  # not judged: the delta pressure at or below zero (the loop's other side high)
    transient: int  # not judged: followable but not steady, for an answer judged on steady points

    @property
    def unjudged(self) -> int:
        return self.total - self.judged

    def why(self) -> str:
        """The unjudged points by reason, e.g. ``412 near the relief valve, 230 at or below 0 bar``."""
        parts = [
            f"{n} {what}"
            for n, what in (
                (self.near_relief, "near the relief valve"),
                (self.no_pressure, "at or below 0 bar delta pressure"),
                (self.transient, "transient"),
            )
            if n
        ]
        return ", ".join(parts)


@dataclass(frozen=True)
class Bin:
    lo: float
    hi: float
    points: int
    mean_gap: float
    rmse: float
    share: float  # of the squared gap


@dataclass(frozen=True)
class PartStat:
    points: int
    rmse: float
    share: float


@dataclass(frozen=True)
class Regions:
    """The gap by quartile of each varying input, and steady against transient points."""

    bins: Mapping[str, tuple[Bin, ...]]
    steady: PartStat
    transient: PartStat


@dataclass(frozen=True)
class DominantRegion:
    variable: str
    lo: float
    hi: float
    share: float
    explained_by_variable: float


@dataclass(frozen=True)
class TimeLag:
    lag_s: float
    correlation: float


@dataclass(frozen=True)
class Where:
    regions: Regions
    dominant: DominantRegion | None  # None when no input varies
    time_lag: TimeLag | None  # None for operating-point tables (no time series)


@dataclass(frozen=True)
class Holdout:
    spec: str
    points: int
    judged_points: int
    judged_on: str
    regions_before: Regions
    # Where the withheld part hardly differs from the fit part along its variable (docs/gap.md, "The
    # withheld part"): why, in one sentence; empty where the hold-out asks for a real extrapolation.
    degenerate: str = ""
    reach: float | None = None  # how far the withheld part's median lies from the fit part's, along VAR
    reach_needed: float | None = None  # ... and the least reach that tests an extrapolation


@dataclass(frozen=True)
class After:
    rmse: float  # at the judged points, as GapStats
    rmse_pct: float
    heldout_rmse: float
    heldout_reduction: float
    regions_heldout: Regions
    all_rmse: float  # at every point, judged or not


@dataclass(frozen=True)
class FittedEffect:
    """An effect in the final simulator, with its parameters after the last joint fit."""

    name: str
    params: tuple[ParamFit, ...]


@dataclass(frozen=True)
class Flag:
    code: str  # "bound": a fitted value on its plausible bound
    message: str


@dataclass(frozen=True)
class Confidence:
    """How sure the answer is, with the figures the level was decided on (see docs/gap.md)."""

    level: str  # high, medium or low
    reasons: tuple[str, ...]  # why not higher (empty for high)
    checks: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Diagnosis:
    source: str
    quantity: str
    unit: str
    data_kind: str  # "series" or "points"
    points: int
    noise_level: float
    before: GapStats
    where: Where
    candidates: tuple[CandidateFit, ...]  # every candidate alone (the first round)
    rounds: tuple[Round, ...]
    groups: tuple[tuple[str, ...], ...]  # the answer: one group per effect found; >1 name = ambiguous
    fitted: tuple[FittedEffect, ...]
    confidence: Confidence | None  # None when no effect is named
    flags: tuple[Flag, ...]
    verdict: str
    after: After
    holdout: Holdout
    robustness: Mapping[str, float]  # withheld reduction with each region withheld in turn
    residual_structure: Mapping[str, float]  # RMS of residual decile means per input, in noise levels
    refused_points: int = 0  # points left out by the plausibility gate (not in ``points``)
    refused_why: str = ""  # ... which values, outside which plausible ranges
    judged: Coverage | None = None  # the points the figures are over, and why the others are not judged
    pair_search: PairSearch | None = None  # None: not run (one effect left little but noise)

    @property
    def selected(self) -> tuple[str, ...]:
        """Every effect named (members of an ambiguous group included)."""
        return tuple(n for g in self.groups for n in g)

    @property
    def ambiguous(self) -> tuple[tuple[str, ...], ...]:
        return tuple(g for g in self.groups if len(g) > 1)

    def to_dict(self) -> dict[str, Any]:
        out = _plain(asdict(self))
        out["selected"] = list(self.selected)
        out["ambiguous"] = [list(g) for g in self.ambiguous]
        return out


@dataclass(frozen=True)
class Arrays:
    """The arrays behind the report's plots."""

    y_before: NDArray[np.float64]
    y_after: NDArray[np.float64]
    holdout: NDArray[np.bool_]
    judged: NDArray[np.bool_]  # the points the answer is judged on (the headline's and the figures')


def _plain(v: Any) -> Any:
    """JSON-ready: tuples as lists, numpy scalars as Python numbers, non-finite floats as None."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v
