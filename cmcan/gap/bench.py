"""``cmcan gap bench``: the diagnosis checked on data whose effect it is not told.

Each trial draws a case (one effect from the library, none, two at once, an effect outside the
library, or a leak confined to high pressure), a realistic magnitude and a duty cycle; makes the
"real" data with the dynamic simulator (pressure build-up, motor inertia, relief valve, sensor noise,
the DBC's resolution and send periods) with the effect inside it (an extra loss term, a sensor error,
a mispositioned motor); and hands the diagnosis only the measured columns. Trials are independent and
seeded one by one, so a run gives the same figures however many processes share it.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.data import GapData, from_series
from cmcan.gap.diagnose import diagnose
from cmcan.gap.effects import LIBRARY, Inputs, Scale, simulate
from cmcan.gap.result import HIGH, LEVELS, Diagnosis
from cmcan.monitor.gating import GateLimits
from cmcan.roles import DP, GATED, HIGH_PRESSURE, LOW_PRESSURE, MOTOR_SPEED, PUMP_DISP, PUMP_SPEED, TEMP
from cmcan.sim import run as simrun
from cmcan.sim import scenario as scn
from cmcan.sim.physics import DriveParams, ExtraLosses, steady_motor_speed_rpm

RATE_HZ = 100.0
DUTIES = ("wheel_loader", "excavator", "sweep")
CASES = ("single", "none", "two", "outside", "region")
CASE_P = (0.6, 0.12, 0.12, 0.08, 0.08)
SIZE_RANGE_PCT = (0.5, 3.0)  # mean change of the output an effect makes, in % of the output
LAG_RANGE_S = (0.15, 0.6)
# Errors of the pressure and temperature sensors hardly move the output (they act through the losses,
# a few % of the flow): drawn in their own units, as a calibration sheet would state them.
NATURAL = {
    "temp_sensor_offset": (3.0, 10.0),  # C, either sign
    "temp_sensor_gain": (5.0, 15.0),  # %, either sign
    "pressure_sensor_offset": (0.015, 0.04),  # share of the highest pressure, either sign
    "pressure_sensor_gain": (3.0, 10.0),  # %, either sign
}
SIGNED = {"motor_disp_offset"} | {n for n, e in LIBRARY.items() if e.kind == "sensor"} - {"output_sensor_lag"}
OUTSIDE = ("centrifugal_loss", "high_pressure_leak")  # not in the library
HP_LEAK_FROM_BAR = 300.0
MEASURED = GATED  # what the diagnosis gets
# Effects that are (nearly) one constant factor on the output: two of them at once are one factor.
FACTOR = {"motor_disp_offset", "output_sensor_gain", "pump_speed_sensor_gain", "disp_sensor_gain"}


@dataclass(frozen=True)
class TrialSpec:
    """What one trial puts into the dynamic simulator."""

    seed: int
    case: str
    truth: tuple[str, ...]
    duty: str
    minutes: float
    temp_range_c: tuple[float, float]
    temp_phase: float
    size_pct: float
    signs: tuple[float, ...]
    values: tuple[float, ...] | None = None  # the effects' parameters as given (None: drawn)


@dataclass(frozen=True)
class Score:
    seed: int
    case: str
    truth: tuple[str, ...]
    duty: str
    values: tuple[float, ...]  # the parameters put in, in the library's units
    groups: tuple[tuple[str, ...], ...]
    level: str | None
    flags: int
    right: bool
    heldout_reduction: float
    located: bool  # the dominant region is high pressure (for the high-pressure leak)
    checks: dict[str, float]  # the figures the confidence level was decided on

    @property
    def named(self) -> set[str]:
        return {n for g in self.groups for n in g}


def draw(seed: int, minutes: float = 20.0, case: str | None = None) -> TrialSpec:
    rng = np.random.default_rng(seed)
    names = list(LIBRARY)
    if case is None:
        case = str(rng.choice(CASES, p=CASE_P))
    if case == "single":
        truth: tuple[str, ...] = (str(rng.choice(names)),)
    elif case == "two":
        pool = [n for n in names if not LIBRARY[n].needs_time]
        truth = tuple(str(n) for n in rng.choice(pool, size=2, replace=False))
        while set(truth) <= FACTOR:  # two constant factors on the output add up to one
            truth = tuple(str(n) for n in rng.choice(pool, size=2, replace=False))
    elif case == "outside":
        truth = ("centrifugal_loss",)
    elif case == "region":
        truth = ("high_pressure_leak",)
    else:
        truth = ()
    duty = str(rng.choice(DUTIES))
    temp = (float(rng.uniform(25, 45)), float(rng.uniform(65, 90)))
    phase = float(rng.uniform(0, 2 * np.pi))
    size = float(rng.uniform(*SIZE_RANGE_PCT))
    signs = tuple(float(rng.choice([-1.0, 1.0])) for _ in truth)
    return TrialSpec(seed, case, truth, duty, minutes, temp, phase, size, signs)


def _doc(spec: TrialSpec) -> dict[str, Any]:
    """The trial as a scenario: its duty, the oil warming and cooling, no effect yet."""
    duty: dict[str, Any] = {"kind": spec.duty}
    if spec.duty == "sweep":
        duty.update(
            pump_speed_rpm=[900, 3200], pump_disp_pct=[15, 100], dp_bar=[40, 450], hold_s=[4, 12], edge_share=0.1
        )
    t0, t1 = spec.temp_range_c
    th = np.linspace(0.0, spec.minutes / 60.0, 61)
    temp = t0 + (t1 - t0) * 0.5 * (1 + np.sin(2 * np.pi * th * 60.0 / spec.minutes + spec.temp_phase))
    return {
        "name": f"gap_bench_{spec.seed}",
        "seed": spec.seed % 2**32,
        "duration_h": spec.minutes / 60.0,
        "sample_rate_hz": RATE_HZ,
        "oil": {"model": "profile", "points": [[float(a), float(b)] for a, b in zip(th, temp, strict=True)]},
        "duty": duty,
    }


def _put(doc: dict[str, Any], name: str, value: float) -> None:
    """Put an effect into the scenario: an extra loss, a sensor error, a mispositioned motor."""
    extra = doc.setdefault("losses", {}).setdefault("extra", {})
    errors = doc.setdefault("sensors", {}).setdefault("errors", {})

    def err(ch: str, key: str) -> None:
        errors.setdefault(ch, {})[key] = errors.get(ch, {}).get(key, 0.0) + value

    leak = {"laminar_leakage": "laminar_lpm", "pressure_leakage": "pressure_lpm", "turbulent_leakage": "turbulent_lpm"}
    role = {"pump_speed": PUMP_SPEED, "disp": PUMP_DISP, "temp": TEMP, "output": MOTOR_SPEED}
    if name in leak:
        extra[leak[name]] = value
    elif name == "compressibility":
        extra["compress_factor"] = value
    elif name == "centrifugal_loss":
        extra["filling_lpm"] = value
    elif name == "high_pressure_leak":  # a relief valve weeping from 300 bar: value l/min per 100 bar above
        doc.setdefault("drive", {}).update(relief_dp_bar=HP_LEAK_FROM_BAR, relief_gain_lpm_per_bar=value / 100.0)
    elif name == "motor_disp_offset":
        doc.setdefault("events", []).append({"type": "misposition", "mode": "step", "start_h": 0.0, "pct": value})
    elif name == "output_sensor_lag":
        err(MOTOR_SPEED, "lag_s")
    elif name == "pressure_sensor_offset":
        err(HIGH_PRESSURE, "offset")
    elif name == "pressure_sensor_gain":  # both transducers: the delta pressure reads pct % high
        err(HIGH_PRESSURE, "gain_pct")
        err(LOW_PRESSURE, "gain_pct")
    else:
        prefix, kind = name.rsplit("_sensor_", 1)
        err(role[prefix], "offset" if kind == "offset" else "gain_pct")


def _quasi_static(p: DriveParams, x: Inputs, name: str, value: float) -> NDArray[np.float64]:
    """The output with an effect at ``value`` by the flow balance: only to size the effect."""
    if name in LIBRARY:
        return simulate(p, x, [(LIBRARY[name], np.array([value]))])
    if name == "centrifugal_loss":
        q = replace(p, extra=ExtraLosses(filling_lpm=value))
        return steady_motor_speed_rpm(q, x.pump_speed_rpm, x.pump_disp_cc, x.dp_bar, x.temp_c)
    leak = value * np.clip(x.dp_bar - HP_LEAK_FROM_BAR, 0.0, None) / 100.0
    return steady_motor_speed_rpm(p, x.pump_speed_rpm, x.pump_disp_cc, x.dp_bar, x.temp_c, extra_leak_lpm=leak)


def _value(p: DriveParams, x: Inputs, scale: Scale, spec: TrialSpec, k: int) -> float:
    """The parameter that gives effect ``k`` the drawn size (or its natural size), inside its plausible
    range on this machine."""
    name, sign = spec.truth[k], spec.signs[k]
    rng = np.random.default_rng([spec.seed, k])
    if name == "output_sensor_lag":
        return float(rng.uniform(*LAG_RANGE_S))
    if name in NATURAL:
        v = float(rng.uniform(*NATURAL[name]))
        return sign * (v * scale.dp_max_bar if name == "pressure_sensor_offset" else v)
    base = simulate(p, x, [])
    unit = 1.0
    change = float(np.mean(np.abs(_quasi_static(p, x, name, unit) - base)) / np.mean(np.abs(base)) * 100)
    v = unit * spec.size_pct / max(change, 1e-12) * (sign if name in SIGNED else 1.0)
    if name in LIBRARY:
        lo, hi = LIBRARY[name].params[0].plausible(scale)
        v = float(np.clip(v, 0.8 * lo, 0.8 * hi))
    return float(v)


def trial_data(spec: TrialSpec, p: DriveParams | None = None) -> tuple[GapData, tuple[float, ...]]:
    """The trial's measured data from the dynamic simulator with its effects inside, and their values."""
    r, values = trial_run(spec, p)
    series = {k: (r["time_s"], r[k]) for k in MEASURED}
    return from_series(series, MOTOR_SPEED, GateLimits(), f"trial {spec.seed}"), values


def trial_run(spec: TrialSpec, p: DriveParams | None = None) -> tuple[simrun.Run, tuple[float, ...]]:
    """The trial's run of the dynamic simulator with its effects inside, and their values."""
    p = p or DriveParams()
    doc = _doc(spec)
    values: tuple[float, ...] = ()
    if spec.truth:
        healthy = simrun.simulate(scn.from_dict(copy.deepcopy(doc), source=doc["name"]))
        t = healthy["time_s"]
        # Sized on what the sensors show (the pressure sensor sees one side of the loop only).
        x = Inputs(
            t,
            healthy[PUMP_SPEED],
            healthy[PUMP_DISP],
            healthy[DP],
            healthy[TEMP],
            np.zeros(len(t)),
            np.zeros(len(t), dtype=np.int64),
        )
        scale = Scale.of(p, x, simulate(p, x, []))
        values = spec.values or tuple(_value(p, x, scale, spec, k) for k in range(len(spec.truth)))
        for name, v in zip(spec.truth, values, strict=True):
            _put(doc, name, v)
    return simrun.simulate(scn.from_dict(doc, source=doc["name"])), values


def score(spec: TrialSpec, values: tuple[float, ...], diag: Diagnosis) -> Score:
    named = set(diag.selected)
    groups = diag.groups
    if spec.case == "single":
        right = len(groups) == 1 and spec.truth[0] in named
    elif spec.case == "two":
        right = set(spec.truth) <= named
    else:  # none, or an effect outside the library: any effect named is wrong
        right = not groups
    dom = diag.where.dominant
    located = dom is not None and dom.variable == DP and dom.lo >= 250.0
    return Score(
        spec.seed,
        spec.case,
        spec.truth,
        spec.duty,
        values,
        groups,
        diag.confidence.level if diag.confidence else None,
        len(diag.flags),
        bool(right),
        diag.after.heldout_reduction,
        bool(located),
        dict(diag.confidence.checks) if diag.confidence else {},
    )


def run_trial(seed: int, minutes: float = 20.0, case: str | None = None, p: DriveParams | None = None) -> Score:
    p = p or DriveParams()
    spec = draw(seed, minutes, case)
    data, values = trial_data(spec, p)
    diag, _ = diagnose(data, p)
    return score(spec, values, diag)


def trial_seeds(seed: int, trials: int) -> list[int]:
    return [seed * 100_003 + i for i in range(trials)]


def run(seed: int, trials: int, minutes: float = 20.0, jobs: int = 1) -> list[Score]:
    """The trials in seed order; ``jobs`` > 1 runs them in that many processes (same results)."""
    seeds = trial_seeds(seed, trials)
    if jobs <= 1:
        return [run_trial(s, minutes) for s in seeds]
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=jobs) as pool:
        return list(pool.map(run_trial, seeds, [minutes] * len(seeds)))


@dataclass(frozen=True)
class LevelRow:
    level: str
    answers: int  # answers naming an effect at this level
    right: int
    singles: int  # of them, on single-effect cases

    @property
    def rate(self) -> float | None:
        return self.right / self.answers if self.answers else None


@dataclass(frozen=True)
class Count:
    """k of n trials; the rate is None where there were none to count."""

    k: int
    n: int

    @property
    def rate(self) -> float | None:
        return self.k / self.n if self.n else None

    def __str__(self) -> str:
        return f"{self.k}/{self.n} ({100 * self.k / self.n:.1f} %)" if self.n else "0/0 (n/a)"


@dataclass(frozen=True)
class Summary:
    trials: int
    # Each rate below with the counts it is made of (k of n trials).
    single_right: Count
    single_high: Count
    none_right: Count
    two_found: Count
    outside_unnamed: Count
    region_located: Count
    single_right_rate: float | None
    single_high_share: float | None  # share of single-effect cases answered with high confidence
    none_right_rate: float | None
    two_found_rate: float | None
    outside_named_high: int  # effects outside the library named with high confidence (must be 0)
    outside_unnamed_rate: float | None
    region_located_rate: float | None
    median_heldout_reduction_single: float | None
    ambiguous_single: int
    by_level: tuple[LevelRow, ...]
    by_effect: dict[str, tuple[int, int]]  # single cases: effect -> (trials, right)
    per_trial: tuple[Score, ...]


def _count(xs: Iterable[bool]) -> Count:
    v = list(xs)
    return Count(int(sum(v)), len(v))


def summarize(scores: list[Score]) -> Summary:
    by_case = {c: [s for s in scores if s.case == c] for c in CASES}
    singles = by_case["single"]
    outside = by_case["outside"] + by_case["region"]
    rows = []
    for lv in LEVELS:
        at = [s for s in scores if s.level == lv and s.groups]
        rows.append(LevelRow(lv, len(at), sum(s.right for s in at), sum(s.case == "single" for s in at)))
    effects: dict[str, tuple[int, int]] = {}
    for s in singles:
        n, r = effects.get(s.truth[0], (0, 0))
        effects[s.truth[0]] = (n + 1, r + int(s.right))
    counts = {
        "single_right": _count(s.right for s in singles),
        "single_high": _count(s.level == HIGH for s in singles),
        "none_right": _count(s.right for s in by_case["none"]),
        "two_found": _count(s.right for s in by_case["two"]),
        "outside_unnamed": _count(not s.groups for s in outside),
        "region_located": _count(s.located for s in by_case["region"]),
    }
    return Summary(
        trials=len(scores),
        **counts,
        single_right_rate=counts["single_right"].rate,
        single_high_share=counts["single_high"].rate,
        none_right_rate=counts["none_right"].rate,
        two_found_rate=counts["two_found"].rate,
        outside_named_high=sum(s.level == HIGH for s in outside),
        outside_unnamed_rate=counts["outside_unnamed"].rate,
        region_located_rate=counts["region_located"].rate,
        median_heldout_reduction_single=float(np.median([s.heldout_reduction for s in singles])) if singles else None,
        ambiguous_single=sum(any(len(g) > 1 for g in s.groups) for s in singles),
        by_level=tuple(rows),
        by_effect=dict(sorted(effects.items())),
        per_trial=tuple(scores),
    )
