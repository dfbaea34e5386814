"""A machine-type model from many machines' healthy operating points (``cmcan fleet train``): the pure core.

Arrays in, arrays and figures out; reading the data set on Dask is :mod:`cmcan.fleet.points`, the
command line :mod:`cmcan.cli.fleet_train`.

- :func:`healthy_rows` picks a machine's timeline rows a type model may learn from: every tick of the
  row evaluated inside the envelope, a finite operating point, warning level ok, before the machine's
  first ratio warning (a drive that warned once was wearing before it did) and before ``until_h``.
- :func:`fit_type` fits them with the same closed-form fit as ``cmcan train``
  (:func:`cmcan.model.train.fit`, float64), each machine's own unit terms beside it
  (:func:`fit_with_units`: what the on-board baseline learns, so that the model is the kept machines'
  average unit and not their differences at their duties), and measures the **unit-to-unit
  spread**: each machine's offset, the mean of its residual (measured - predicted) in l/min over its
  own points, and the spread of those offsets, recorded in the model's ``training["unit_spread"]``.
- A machine whose offset lies far from the others' is not a unit of the type the model may learn
  (:func:`outlying`): a machine that arrives leaking sits well below the type, one whose displacement
  control is set high above it. Its offset is judged against the median of the offsets and their
  median absolute deviation (MAD), which one or two such machines cannot move; it is named, left out
  of the fit and of the spread, and the type is fitted again on the rest until no machine is left
  out anew. The spread written is the standard deviation of the offsets of the machines kept.
- The median cannot judge a type where half the machines arrive leaking (two of four). Each machine
  is therefore also judged against the **reference**, the model its logs were replayed with (the
  type's shipped model, trained on a healthy unit): :func:`off_reference` names a machine whose mean
  residual against it lies further than the largest offset a healthy series unit can have
  (:data:`OUTLIER_Z` times :data:`SCALE_FLOOR_SHARE` of the type's median flow) in the part that grows
  with the pressure (a leak, :func:`reference_shape`), or in the mean and the part that grows with the
  flow (a displacement, a speed gain; a unit whose tolerances add up, each within its own, is off in
  the mean but in neither part); unless more than half of the type would be named
  (then the reference does not fit the type and only the median judges).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.errors import CmcanError, Kind
from cmcan.monitor.baseline import FEATURES, N_FEATURES, Mode, unit_features
from cmcan.roles import MODEL_INPUTS

MIN_MACHINES = 2  # a spread needs two units
MIN_MACHINES_JUDGED = 4  # fewer: the median and MAD of the offsets cannot tell which machine is the odd one
# A robust z-score |offset - median| / (1.4826 MAD) above it: an outlier (Iglewicz and Hoaglin's 3.5).
OUTLIER_Z = 3.5
MAD_TO_SD = 1.4826  # the MAD of a normal sample times this estimates its standard deviation
# The least scale the offsets are judged on, as a share of the type's median delivered flow: the
# datasheet tolerance of a series unit's displacement (+-1 %) and its healthy leakage make offsets of
# about 1 % of the flow between healthy units of a type, however alike the few in a data set happen
# to be; with ten or so machines the MAD alone is too uncertain to judge on (it would name healthy
# units). Above it, 3.5 robust SDs: a unit 3.5 % of its flow or more off its type.
SCALE_FLOOR_SHARE = 0.01
# A leak's share of the residual is stated as an orifice's flow at this delta pressure (as the
# simulator states arriving leaks; the paper's rig ran at it): the pressure these drives run up to.
LEAK_REF_DP_BAR = 480.0
# Points whose ideal flow and sqrt(dp) move together this closely cannot tell a leak from a
# displacement: the shape is not judged then (the mean decides alone).
SHAPE_MAX_CORRELATION = 0.95
MIN_POINTS_PER_MACHINE = 20  # fewer: a machine's offset is noise
# Why a row is left out, in the order the rules are applied (the counts say which rule took it).
REFUSALS = ("not_all_evaluated", "outside_envelope", "no_operating_point", "not_ok", "after_warning", "after_until_h")
WARNING_LEVELS = ("low", "high")  # ratio warnings: the drive itself (a fault is an input's, not the drive's)
TYPE_COLUMNS = ("machine", "type")


@dataclass(frozen=True)
class MachinePoints:
    """One machine's healthy points, rows sorted by operating hour."""

    machine: str
    x: NDArray[np.float64]  # (n, 4) in MODEL_INPUTS order
    measured: NDArray[np.float64]  # the output quantity (rpm or l/min)
    operating_h: NDArray[np.float64]
    rows: int  # timeline rows read
    refused: dict[str, int]  # rows left out, by rule (REFUSALS)
    # The replay model's prediction of each point (the quantity's unit) and that model's hash; None
    # when the data set has no such column, the machine's rows were replayed with several models, or
    # some with an on-board baseline monitoring (their prediction is then the machine's own).
    reference: NDArray[np.float64] | None = None
    reference_model: str | None = None

    def __len__(self) -> int:
        return len(self.measured)


@dataclass(frozen=True)
class DriveFacts:
    """What the type model's fit needs from the configuration the machines were replayed with."""

    quantity: str
    motor_disp_cc: float | None
    oil_nu40_cst: float
    oil_nu100_cst: float

    @property
    def lpm_per_unit(self) -> float:
        """l/min per unit of the quantity: V_M / 1000 for motor speed, 1 for flow."""
        return 1.0 if self.motor_disp_cc is None else self.motor_disp_cc / 1000.0


# -- which machines: the type mapping --------------------------------------------------------------------


def read_types(path: str | Path) -> dict[str, str]:
    """machine -> type from a CSV with a header naming ``machine`` and ``type`` (other columns are
    ignored: an inventory may have more); a machine listed twice with two types is refused."""
    p = Path(path)
    try:
        with open(p, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            header = [h.strip() for h in reader.fieldnames or ()]
            missing = [c for c in TYPE_COLUMNS if c not in header]
            if missing:
                raise CmcanError(
                    f"{p}: --types lacks column(s) {', '.join(missing)}; expected a header machine,type", Kind.DATA
                )
            out: dict[str, str] = {}
            for line, row in enumerate(reader, start=2):
                row = {(k or "").strip(): (v or "").strip() for k, v in row.items() if k is not None}
                m, t = row.get("machine", ""), row.get("type", "")
                if not m and not t:
                    continue
                if not m or not t:
                    raise CmcanError(f"{p} line {line}: expected a machine and its type, got {m!r}, {t!r}", Kind.DATA)
                if out.get(m, t) != t:
                    raise CmcanError(f"{p} line {line}: machine {m} has type {out[m]} on an earlier line", Kind.DATA)
                out[m] = t
    except OSError as exc:
        raise CmcanError(f"{p}: cannot read the types file: {exc.strerror or exc}", Kind.NO_INPUT) from None
    except (UnicodeError, csv.Error) as exc:
        raise CmcanError(f"{p}: not a CSV file: {exc}", Kind.DATA) from None
    return out


def machines_of_type(types: Mapping[str, str], machine_type: str, source: str) -> list[str]:
    """The machines of a type, sorted; an unknown type names the known ones."""
    chosen = sorted(m for m, t in types.items() if t == machine_type)
    if not chosen:
        known = ", ".join(sorted(set(types.values()))) or "none"
        raise CmcanError(f"{source}: no machine of type {machine_type!r}; its types are {known}", Kind.DATA)
    return chosen


def common_facts(facts: Mapping[str, DriveFacts], dataset: str) -> DriveFacts:
    """The one quantity, V_M and oil every machine was replayed with; a mix is refused, naming the field
    and the machines on each side."""
    if not facts:
        raise CmcanError(f"{dataset}: no machines to compare", Kind.DATA)
    for field in ("quantity", "motor_disp_cc", "oil_nu40_cst", "oil_nu100_cst"):
        by_value: dict[Any, list[str]] = {}
        for m in sorted(facts):
            by_value.setdefault(getattr(facts[m], field), []).append(m)
        if len(by_value) > 1:
            sides = "; ".join(f"{v} on {', '.join(ms)}" for v, ms in by_value.items())
            raise CmcanError(
                f"{dataset}: the machines were replayed with configurations of different {field} ({sides}); "
                "a type model needs one configuration's quantity, V_M and oil: name machines of one type",
                Kind.DATA,
            )
    return facts[min(facts)]


# -- which rows: healthy, evaluated, inside the envelope ----------------------------------------------------


def healthy_rows(
    cols: Mapping[str, NDArray[Any]], until_h: float = math.inf
) -> tuple[NDArray[np.bool_], dict[str, int]]:
    """Rows a type model may learn from, and how many each rule (:data:`REFUSALS`) left out.

    ``cols``: one machine's timeline columns (``ticks``, ``evaluated``, ``gate``, ``warning_level``,
    ``measured``, the operating point) with ``operating_h`` (its place on the machine's life)."""
    n = len(cols["ticks"])
    op_h = np.asarray(cols["operating_h"], dtype=np.float64)
    ticks = np.asarray(cols["ticks"], dtype=np.int64)
    level = np.asarray(cols["warning_level"], dtype=object)
    # the gate column is the row's last tick's: with every tick evaluated, that one inside the envelope
    rules = {
        "not_all_evaluated": (ticks > 0) & (np.asarray(cols["evaluated"], dtype=np.int64) == ticks),
        "outside_envelope": np.asarray(cols["gate"], dtype=object) == "evaluating",
        "no_operating_point": np.all(
            np.isfinite(np.column_stack([np.asarray(cols[c], dtype=np.float64) for c in (*MODEL_INPUTS, "measured")])),
            axis=1,
        )
        if n
        else np.ones(0, dtype=bool),
        "not_ok": level == "ok",
        "after_warning": op_h < _first_warning_h(op_h, level),
        "after_until_h": op_h < until_h,
    }
    keep = np.ones(n, dtype=bool)
    refused = {}
    for name in REFUSALS:
        refused[name] = int(np.count_nonzero(keep & ~rules[name]))
        keep &= rules[name]
    return keep, refused


def _first_warning_h(op_h: NDArray[np.float64], level: NDArray[Any]) -> float:
    warned = np.isin(level, WARNING_LEVELS)
    return float(op_h[warned].min()) if warned.any() else math.inf


def machine_points(machine: str, cols: Mapping[str, NDArray[Any]], until_h: float = math.inf) -> MachinePoints:
    """A machine's healthy points from its timeline columns, sorted by (operating hour, time)."""
    keep, refused = healthy_rows(cols, until_h)
    order = np.lexsort((np.asarray(cols["time_s"], dtype=np.float64)[keep], np.asarray(cols["operating_h"])[keep]))
    x = np.column_stack([np.asarray(cols[c], dtype=np.float64)[keep] for c in MODEL_INPUTS]).reshape(-1, 4)
    reference, reference_model = None, None
    if "predicted" in cols and "model_hash" in cols:
        models = set(np.asarray(cols["model_hash"], dtype=object)[keep].tolist())
        own = "baseline_state" in cols and bool(np.any(np.asarray(cols["baseline_state"])[keep] == Mode.MONITORING))
        if len(models) == 1 and not own:  # one replay model: one reference to judge the machine against
            reference = np.asarray(cols["predicted"], dtype=np.float64)[keep][order]
            reference_model = str(models.pop())
    return MachinePoints(
        machine,
        np.ascontiguousarray(x[order]),
        np.asarray(cols["measured"], dtype=np.float64)[keep][order],
        np.asarray(cols["operating_h"], dtype=np.float64)[keep][order],
        rows=len(cols["ticks"]),
        refused=refused,
        reference=reference,
        reference_model=reference_model,
    )


def check_points(points: Sequence[MachinePoints], min_points: int, dataset: str) -> None:
    """Enough machines, each with enough points; else an error naming the machine and the rules that
    took its rows."""
    for mp in points:
        if len(mp) < min_points:
            why = ", ".join(f"{k} {v}" for k, v in mp.refused.items() if v) or "none refused"
            raise CmcanError(
                f"{dataset}: machine {mp.machine}: {len(mp)} healthy points of {mp.rows} timeline rows, expected at "
                f"least {min_points} (--min-points); rows left out: {why}. Leave it out with --exclude {mp.machine}",
                Kind.DATA,
            )
    if len(points) < MIN_MACHINES:
        raise CmcanError(
            f"{dataset}: {len(points)} machine(s) with healthy points, expected at least {MIN_MACHINES}: "
            "a unit-to-unit spread needs two units (for one machine, use cmcan train)",
            Kind.DATA,
        )


# -- the spread ----------------------------------------------------------------------------------------------


def unit_spread(
    residual_lpm: Mapping[str, NDArray[np.float64]], outliers: Mapping[str, Mapping[str, Any]] | None = None
) -> dict[str, Any]:
    """``training["unit_spread"]``: each kept machine's offset (the mean of its residual in l/min, each
    of its points weighted equally), their sample standard deviation (n - 1) and the largest absolute
    one; the machines left out as outliers, with their offsets and why (:func:`outlying`)."""
    per = {m: {"offset_lpm": float(np.mean(r)), "points": len(r)} for m, r in sorted(residual_lpm.items())}
    offsets = np.array([v["offset_lpm"] for v in per.values()], dtype=np.float64)
    return {
        "machines": len(per),
        "offset_sd_lpm": float(np.std(offsets, ddof=1)) if len(offsets) > 1 else 0.0,
        "offset_max_abs_lpm": float(np.max(np.abs(offsets))) if len(offsets) else 0.0,
        "per_machine": per,
        "outliers": {m: dict(v) for m, v in sorted((outliers or {}).items())},
        "rule": f"offset more than {OUTLIER_Z:g} robust SDs (1.4826 MAD, at least {SCALE_FLOOR_SHARE:.1%} of the "
        "median flow) from the median offset: left out",
    }


def outlying(offsets_lpm: Mapping[str, float], floor_lpm: float) -> dict[str, dict[str, Any]]:
    """The machines whose offset is an outlier among ``offsets_lpm``: its modified z-score (distance to
    the median over 1.4826 MAD, the MAD floored at ``floor_lpm``) above :data:`OUTLIER_Z`, each with its
    offset, score and what it suggests. None judged among fewer than :data:`MIN_MACHINES_JUDGED`."""
    if len(offsets_lpm) < MIN_MACHINES_JUDGED:
        return {}
    v = np.array(list(offsets_lpm.values()), dtype=np.float64)
    center = float(np.median(v))
    scale = max(MAD_TO_SD * float(np.median(np.abs(v - center))), floor_lpm)
    out = {}
    for m, o in sorted(offsets_lpm.items()):
        z = (o - center) / scale
        if abs(z) > OUTLIER_Z:
            why = "arrives leaking: delivers less than the type" if z < 0 else "delivers more than the type"
            out[m] = {"offset_lpm": float(o), "robust_z": float(z), "why": f"{why} (does not fit the type)"}
    return out


def reference_shape(x: NDArray[np.float64], residual_lpm: NDArray[np.float64]) -> tuple[float, float]:
    """A machine's residual against the reference split by shape, least squares on its points:
    ``a * Q_geo + b * sqrt(dp / LEAK_REF_DP_BAR)``. Returns (the flow-shaped part at the machine's mean
    ideal flow, the pressure-shaped part at :data:`LEAK_REF_DP_BAR`), both l/min: a displacement or a
    speed sensor's gain moves the first (the same share of every flow), a leak the second (an orifice
    at the loop's pressure; a healthy unit's gap leakage differs from its type's by a share of a
    healthy leakage, a few % of the flow at full pressure). Points that cannot tell the two apart
    (the two columns correlated beyond :data:`SHAPE_MAX_CORRELATION`, or constant): the mean for both."""
    from cmcan.model.physics import ideal_flow_lpm

    mean = float(np.mean(residual_lpm))
    q = ideal_flow_lpm(x)
    s = np.sqrt(np.clip(x[:, 2], 0.0, None) / LEAK_REF_DP_BAR)
    if len(q) < 3 or np.ptp(q) <= 0 or np.ptp(s) <= 0 or abs(np.corrcoef(q, s)[0, 1]) > SHAPE_MAX_CORRELATION:
        return mean, mean
    (a, b), *_ = np.linalg.lstsq(np.column_stack([q, s]), residual_lpm, rcond=None)
    return float(a * np.mean(q)), float(b)


def off_reference(
    reference_offsets_lpm: Mapping[str, float],
    bound_lpm: float,
    shapes_lpm: Mapping[str, tuple[float, float]] | None = None,
) -> dict[str, Any]:
    """The judgment against the reference (the model the machines were replayed with): each machine's
    mean residual against it; named, the machines with a part of their residual's shape beyond
    ``bound_lpm`` (``shapes_lpm``, :func:`reference_shape`; none given: the mean stands for both): the
    pressure-shaped part below it (a leak, whatever the flow part makes of the mean: a unit that
    delivers 2 % more can carry a leak its mean does not show), or the flow-shaped part with the mean
    beyond it (delivers less, or more, in proportion to the flow). A unit off by its displacement, its
    sensors and its gaps together, each within its tolerance, is off in the mean but in neither part.
    And whether the rule was applied: not when more than half of the machines would be named (the
    reference then does not fit the type, a median of the type does; a leak is a minority's defect)."""
    out = {}
    for m, o in sorted(reference_offsets_lpm.items()):
        flow_part, leak_part = (shapes_lpm or {}).get(m, (o, o))
        if leak_part < -bound_lpm:
            why = "arrives leaking: delivers less than the type, more so the higher the pressure"
        elif o < -bound_lpm and flow_part < -bound_lpm:
            why = "delivers less than the type, in proportion to the flow"
        elif o > bound_lpm and flow_part > bound_lpm:
            why = "delivers more than the type, in proportion to the flow"
        else:  # no part beyond what a unit's own tolerances give: the median judges it
            continue
        out[m] = {"reference_offset_lpm": float(o), "why": f"{why} (off the reference model)"}
    applied = bool(reference_offsets_lpm) and 2 * len(out) <= len(reference_offsets_lpm)
    if not applied:
        out = {}
    return {
        "applied": applied,
        "bound_lpm": float(bound_lpm),
        "offset_lpm": {m: float(o) for m, o in sorted(reference_offsets_lpm.items())},
        "outliers": out,
    }


def selection_info(until_h: float | None, excluded: Sequence[str], min_points: int) -> dict[str, Any]:
    """How the points were chosen, for ``training["selection"]``."""
    return {
        "rule": "every tick evaluated inside the envelope, finite operating point, warning level ok, "
        "before the machine's first ratio warning",
        "until_h": until_h,
        "excluded": sorted(excluded),
        "min_points": min_points,
    }


def _judge_on_reference(
    points: Sequence[MachinePoints], lpm_per_unit: float, bound_lpm: float
) -> dict[str, Any] | None:
    """:func:`off_reference` on the machines' mean residuals against their replay model, when every
    machine has one and it is the same model; else None."""
    models = {mp.reference_model for mp in points}
    if len(models) != 1 or None in models or any(mp.reference is None for mp in points):
        return None
    residual = {mp.machine: (mp.measured - mp.reference) * lpm_per_unit for mp in points}  # type: ignore[operator]
    offsets = {m: float(np.mean(r)) for m, r in residual.items()}
    shapes = {mp.machine: reference_shape(mp.x, residual[mp.machine]) for mp in points}
    judged = off_reference(offsets, bound_lpm, shapes)
    judged["shape_lpm"] = {m: {"flow": round(a, 4), "leak_at_ref_dp": round(b, 4)} for m, (a, b) in shapes.items()}
    return {"model": models.pop(), **judged}


# Fitting the type model and its units' own terms in turn: until the terms move less than this at
# any point (l/min: a thousandth of a speed sensor's noise), at most this many rounds (each a
# closed-form fit; linear convergence, some 20 rounds a decade where machines work at distinct duty).
UNIT_TOL_LPM = 1e-4
UNIT_ROUNDS = 200
UNIT_RIDGE = 1e-3  # the baseline's: relative to the mean diagonal, keeps a term the points do not excite near 0


@dataclass(frozen=True)
class UnitTerms:
    """Each machine's own terms beside the type model (l/min per :data:`FEATURES`), and the fit's rounds."""

    theta: dict[str, tuple[float, float, float]]
    rounds: int
    moved_lpm: float

    def describe(self) -> dict[str, Any]:
        return {
            "per_machine": {m: [round(v, 6) for v in th] for m, th in sorted(self.theta.items())},
            "rounds": self.rounds,
            "converged": self.moved_lpm < UNIT_TOL_LPM,
        }


def _unit_theta(f: NDArray[np.float64], r: NDArray[np.float64]) -> NDArray[np.float64]:
    """The least-squares terms of residual ``r`` on features ``f``, ridge-regularised as the baseline."""
    a = f.T @ f / len(r)
    b = f.T @ r / len(r)
    lam = UNIT_RIDGE * float(np.trace(a)) / N_FEATURES
    return np.linalg.solve(a + lam * np.eye(N_FEATURES), b)


def fit_with_units(points: Sequence[MachinePoints], facts: DriveFacts, oil: Any) -> tuple[Any, UnitTerms]:
    """The type model fitted on the machines' points with each machine's own unit terms beside it (an
    offset, a share of the geometric flow, a laminar leak: what the on-board baseline learns,
    :func:`cmcan.monitor.baseline.unit_features`), in turn until the terms settle; the terms centred
    on the machines' mean, so that the model is their average unit.

    Pooled without them, a few units that differ (a displacement at its tolerance, a leakier unit)
    and work at different duty (one at high pressure, one at high speed) teach the model their
    differences as a dependence on the operating point; the baseline's three terms cannot undo that
    on another unit, and what is left swings with the operating point in the monitored leakage: the
    prognosis's noise, which hid the first litres of wear on fleets of wider spread."""
    from cmcan.model.train import fit

    per = facts.lpm_per_unit
    x = np.concatenate([mp.x for mp in points]).astype(np.float64)
    y = np.concatenate([mp.measured for mp in points]).astype(np.float64)
    feats = [unit_features(mp.x, oil) for mp in points]
    shifts = [np.zeros(len(mp)) for mp in points]
    thetas = np.zeros((len(points), N_FEATURES))
    moved, rounds = math.inf, 0
    while True:
        rounds += 1
        model = fit(x, y - np.concatenate(shifts) / per, facts.motor_disp_cc, facts.quantity, oil)
        if moved < UNIT_TOL_LPM or rounds > UNIT_ROUNDS:
            break
        for i, (mp, f) in enumerate(zip(points, feats, strict=True)):
            thetas[i] = _unit_theta(f, (mp.measured - model.predict(mp.x)) * per)
        thetas -= thetas.mean(axis=0)
        new = [f @ th for f, th in zip(feats, thetas, strict=True)]
        moved = max(float(np.max(np.abs(a - b))) for a, b in zip(new, shifts, strict=True))
        shifts = new
    theta = {mp.machine: (float(t[0]), float(t[1]), float(t[2])) for mp, t in zip(points, thetas, strict=True)}
    return model, UnitTerms(theta, rounds, moved)


@dataclass(frozen=True)
class TypeFit:
    blob: bytes  # the sealed ONNX model
    model: Any  # cmcan.model.train.TrainedModel
    residual_stats: dict[str, Any]
    training: dict[str, Any]


def fit_type(
    points: Sequence[MachinePoints],
    facts: DriveFacts,
    machine_type: str,
    source: str,
    selection: Mapping[str, Any] | None = None,
    keep: Sequence[str] = (),
) -> TypeFit:
    """The type model on the machines' points (machines in sorted order), outlying machines left out
    (:func:`outlying`; never those in ``keep``), its residual figures and the unit-to-unit spread,
    written as ``cmcan train`` writes a model (:func:`cmcan.model.train.to_onnx`)."""
    from cmcan.model.train import fingerprint, residual_figures, to_onnx
    from cmcan.oil import Oil

    kept = sorted(points, key=lambda mp: mp.machine)
    oil = Oil(facts.oil_nu40_cst, facts.oil_nu100_cst)
    flow = np.concatenate([mp.measured for mp in kept]) * facts.lpm_per_unit
    floor_lpm = SCALE_FLOOR_SHARE * float(np.median(np.abs(flow))) if len(flow) else 0.0
    reference = _judge_on_reference(kept, facts.lpm_per_unit, OUTLIER_Z * floor_lpm)
    left_out: dict[str, dict[str, Any]] = {}
    if reference is not None:  # an absolute judgment: once, before the fits
        first = {m: v for m, v in reference["outliers"].items() if m not in keep}
        if len(kept) - len(first) >= MIN_MACHINES:
            left_out.update({m: dict(v) for m, v in first.items()})
            kept = [mp for mp in kept if mp.machine not in first]
    while True:  # each round leaves machines out or ends: at most one round per machine
        x = np.concatenate([mp.x for mp in kept]).astype(np.float64)
        y = np.concatenate([mp.measured for mp in kept]).astype(np.float64)
        model, units = fit_with_units(kept, facts, oil)
        residual_lpm = {mp.machine: (mp.measured - model.predict(mp.x)) * facts.lpm_per_unit for mp in kept}
        offsets = {m: float(np.mean(r)) for m, r in residual_lpm.items()}
        new = {m: v for m, v in outlying(offsets, floor_lpm).items() if m not in keep}
        if not new or len(kept) - len(new) < MIN_MACHINES:
            break
        left_out.update(new)
        kept = [mp for mp in kept if mp.machine not in new]
    v_kept = np.array(list(offsets.values()), dtype=np.float64)
    center = float(np.median(v_kept))
    scale = max(MAD_TO_SD * float(np.median(np.abs(v_kept - center))), floor_lpm)
    for m, v in left_out.items():  # as the final model sees it
        mp = next(p for p in points if p.machine == m)
        v["offset_lpm"] = float(np.mean((mp.measured - model.predict(mp.x)) * facts.lpm_per_unit))
        v.setdefault("robust_z", (v["offset_lpm"] - center) / scale if scale > 0 else 0.0)
        if reference is not None:
            v.setdefault("reference_offset_lpm", reference["offset_lpm"][m])
    stats = residual_figures(model, x, y, "D_trn")
    spread = unit_spread(residual_lpm, left_out)
    spread["rule"] += (
        f"; or further than {OUTLIER_Z * SCALE_FLOOR_SHARE:.1%} of the median flow from the reference model "
        f"(the one the logs were replayed with) in its residual's part growing with sqrt(dp) (at {LEAK_REF_DP_BAR:g} "
        "bar), or in the mean and the part growing with the flow, unless more than half would be: left out"
    )
    spread["reference"] = (
        {"applied": False, "why": "the machines were not all replayed with one model"}
        if reference is None
        else {k: reference[k] for k in ("model", "applied", "bound_lpm", "offset_lpm", "shape_lpm")}
    )
    training = {
        "fingerprint": fingerprint(x, y),
        "source": source,
        "machine_type": machine_type,
        "t_start_h": 0.0,
        "t_trn_h": None,
        "points_trn": len(y),
        "points_tst": 0,
        "selection": {**dict(selection or {}), "outliers": sorted(left_out), "kept_by_hand": sorted(keep)},
        "unit_spread": spread,
        "unit_terms": {
            "features": list(FEATURES),
            "rule": "each kept machine's own terms (as the on-board baseline learns them) fitted beside the type "
            "model, centred on the kept machines' mean: the model is their average unit",
            **units.describe(),
        },
    }
    return TypeFit(to_onnx(model, stats, training), model, stats, training)
