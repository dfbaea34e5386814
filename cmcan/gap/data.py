"""Measured data for the gap diagnosis: operating points with a steady flag each.

Two kinds of data become the same :class:`GapData`:
- a time series (run CSV or CAN log): 0.1 s block means (10 Hz), the pressure's rate over each block
  from the raw samples at its edges, the lowest and highest raw pressure in it, and the monitor's gate;
- an operating-point table (cycle means, rig logs): one point per row, all steady, no time structure.
  Its rows are put in a canonical order (by operating point), so nothing downstream depends on the
  order the file lists them in.

Both are checked with the monitor's plausibility gate, as training and scoring check theirs: a point
with an input or output outside its plausible range (a temperature in Kelvin, a pressure in psi) is
not an operating point of this machine and is left out; too few left is a data error.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.effects import Inputs
from cmcan.io.points import Points, PointSpec, read_points
from cmcan.model.features import (
    DataError,
    contiguous_spans,
    is_log,
    series_from_columns,
    series_from_log,
)
from cmcan.monitor.gating import (
    REFERENCE_PUMP_SPEED_RPM,
    Gate,
    GateLimits,
    eval_times,
    gate,
    outside_plausible,
    scaled,
    signed_roles,
    table_stats,
    window_stats,
)
from cmcan.roles import DP, FLOW, MODEL_INPUTS, MOTOR_SPEED, PUMP_DISP, PUMP_SPEED, TEMP, UNITS, gated_roles
from cmcan.sim.physics import DriveParams

BLOCK_S = 0.1
QUANTITIES = {MOTOR_SPEED: "rpm", FLOW: "l/min"}
INPUT_ROLES = MODEL_INPUTS
REQUIRED = ("time_s", *INPUT_ROLES)
MIN_BLOCKS = 100
MIN_POINTS = 20
_EPS_S = 5e-7
EDGE_HALF_S = 0.03  # half-width of the mean that estimates the pressure at a block edge


@dataclass(frozen=True)
class GapData:
    x: Inputs
    y: NDArray[np.float64]  # the measured output quantity
    steady: NDArray[np.bool_]
    dp_lo_bar: NDArray[np.float64]  # lowest and highest raw pressure within each point
    dp_hi_bar: NDArray[np.float64]
    quantity: str
    source: str
    kind: str = "series"  # "series": 0.1 s blocks of a time series; "points": one operating point per row
    constant: frozenset[str] = frozenset()  # input roles that do not vary (no sensor, or held constant)
    refused: int = 0  # points left out by the plausibility gate
    refused_why: str = ""  # ... which values, and the ranges they are outside

    @property
    def unit(self) -> str:
        return QUANTITIES[self.quantity]

    @property
    def has_time(self) -> bool:
        return self.kind == "series"

    def subset(self, mask: NDArray[np.bool_]) -> GapData:
        return GapData(
            self.x.subset(mask),
            self.y[mask],
            self.steady[mask],
            self.dp_lo_bar[mask],
            self.dp_hi_bar[mask],
            self.quantity,
            self.source,
            self.kind,
            self.constant,
            self.refused,
            self.refused_why,
        )


def _check_quantity(quantity: str, source: str) -> None:
    if quantity not in QUANTITIES:
        raise DataError(f"{source}: output quantity {quantity!r} is not one of {', '.join(QUANTITIES)}")


def gate_limits_for(quantity: str, limits: GateLimits | None = None, drive: DriveParams | None = None) -> GateLimits:
    """The monitor's gates for ``quantity``: ``limits`` where they are for that output (a configuration
    of this machine), else the reference drive's gates sized for ``drive`` (the reference drive by
    default) with the output role ``quantity`` (a flow machine's gates apply to its flow, in l/min)."""
    if limits is not None and limits.output_role == quantity:
        return limits
    p = drive or DriveParams()
    lpm_per_unit = p.motor_disp_cc / 1000.0 if quantity == MOTOR_SPEED else 1.0
    sized = scaled(quantity, lpm_per_unit, REFERENCE_PUMP_SPEED_RPM, p.pump_disp_max_cc)
    return sized if limits is None else replace(sized, window_s=limits.window_s, min_samples=limits.min_samples)


def implausible(means: Mapping[str, NDArray[np.float64]], limits: GateLimits) -> NDArray[np.bool_]:
    """Points the gap cannot compare: those the monitor's gate refuses as implausible (an input or the
    output missing or outside its plausible range) or as reverse travel (the drive and its model are
    judged forward), each point's values taken as already-averaged means (the gate's table rules)."""
    g = gate(table_stats(dict(means)), limits)
    return (g == Gate.IMPLAUSIBLE_INPUT) | (g == Gate.REVERSE)


def refusal(means: Mapping[str, NDArray[np.float64]], bad: NDArray[np.bool_], limits: GateLimits) -> str:
    """Which values the refused points hold and the plausible ranges they are outside, e.g.
    ``temp_c 308..331 degC outside the plausible range -40..130 degC (55 points)``."""
    parts = []
    outside = np.zeros(len(bad), dtype=bool)
    for r, v in means.items():
        lo, hi = limits.plausible.get(r, (-np.inf, np.inf))
        out = bad & outside_plausible(r, v, limits)  # a signed role by its magnitude, as the gate judges it
        outside |= out
        if not out.any():
            continue
        vals = v[out]
        fin = vals[np.isfinite(vals)]
        unit = UNITS.get(r, "")
        seen = f"{fin.min():.4g}..{fin.max():.4g} {unit}" if len(fin) else "missing"
        if len(fin) and len(fin) < len(vals):
            seen += " or missing"
        parts.append(f"{r} {seen} outside the plausible range {lo:.4g}..{hi:.4g} {unit} ({int(out.sum())} points)")
    reverse = bad & ~outside
    if reverse.any():
        parts.append(f"reverse travel: negative {' or '.join(signed_roles(limits))} ({int(reverse.sum())} points)")
    return "; ".join(parts)


def _at(t: NDArray[np.float64], v: NDArray[np.float64], te: NDArray[np.float64]) -> NDArray[np.float64]:
    """The latest sample at or before each time (sample and hold, as the monitor sees a signal)."""
    idx = np.clip(np.searchsorted(t, te + _EPS_S, side="right") - 1, 0, len(t) - 1)
    return v[idx]


def _local_mean(t: NDArray[np.float64], v: NDArray[np.float64], te: NDArray[np.float64]) -> NDArray[np.float64]:
    """The mean of the samples within EDGE_HALF_S of each time (the held value where there are none):
    a block edge's pressure with the noise of a few samples averaged out and no lag (symmetric)."""
    c = np.r_[0.0, np.cumsum(v)]
    lo = np.searchsorted(t, te - EDGE_HALF_S - _EPS_S, side="left")
    hi = np.searchsorted(t, te + EDGE_HALF_S + _EPS_S, side="right")
    n = hi - lo
    return np.where(n > 0, (c[hi] - c[lo]) / np.maximum(n, 1), _at(t, v, te))


def _block_extremes(
    t: NDArray[np.float64], v: NDArray[np.float64], te: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Lowest and highest sample in each block (te - BLOCK_S, te]; the held value where a block is empty."""
    lo = np.searchsorted(t, te - BLOCK_S + _EPS_S, side="right")
    hi = np.searchsorted(t, te + _EPS_S, side="right")
    held = _at(t, v, te)
    padded = np.append(v, v[-1])
    pairs = np.ravel(np.column_stack([lo, np.maximum(hi, lo + 1)]))
    vmin = np.minimum.reduceat(padded, pairs)[::2]
    vmax = np.maximum.reduceat(padded, pairs)[::2]
    empty = hi <= lo
    return np.where(empty, held, vmin), np.where(empty, held, vmax)


def from_series(
    series: Mapping[str, tuple[NDArray[np.float64], NDArray[np.float64]]],
    quantity: str,
    limits: GateLimits | None,
    source: str,
    drive: DriveParams | None = None,
) -> GapData:
    _check_quantity(quantity, source)
    limits = gate_limits_for(quantity, limits, drive)
    if quantity not in series:
        raise DataError(f"{source}: no {quantity} in the data")
    t_ref = series[quantity][0]
    spans = contiguous_spans(t_ref, max_gap_s=1.0)
    per_span = [eval_times(a, b, 1.0 / BLOCK_S) for a, b in spans]
    t = np.concatenate(per_span) if per_span else np.empty(0)
    seg = np.concatenate([np.full(len(e), i) for i, e in enumerate(per_span)]) if per_span else np.empty(0, np.int64)
    roles = [r for r in (*INPUT_ROLES, MOTOR_SPEED) if r in series]
    blocks = window_stats({r: series[r] for r in roles}, t, BLOCK_S)
    y_blocks = window_stats({quantity: series[quantity]}, t, BLOCK_S).mean[quantity]
    ok = np.all([blocks.count[r] > 0 for r in roles], axis=0) & (blocks.count.get(quantity, np.ones(len(t))) > 0)
    # A block at the start of a span has no edge sample before it for the pressure's rate.
    ok &= np.r_[False, seg[1:] == seg[:-1]] if len(seg) else np.zeros(0, dtype=bool)
    ok &= np.isfinite(y_blocks)
    gate_roles = {r: series[r] for r in gated_roles(quantity)}  # the output role is the quantity compared
    steady = gate(window_stats(gate_roles, t, limits.window_s), limits) == Gate.EVALUATING
    means = {**{r: blocks.mean[r] for r in INPUT_ROLES}, quantity: y_blocks}
    bad = ok & implausible(means, limits)
    why = refusal(means, bad, limits)
    ok &= ~bad
    t_dp, v_dp = series[DP]
    # The pressure's mean rate over each block from its value at the block's edges: the block's
    # line-compressibility flow (a gradient of block means smears the drive's ~1 Hz pressure swings).
    dp_rate = (_local_mean(t_dp, v_dp, t) - _local_mean(t_dp, v_dp, t - BLOCK_S)) / BLOCK_S
    dp_lo, dp_hi = _block_extremes(t_dp, v_dp, t)
    t, seg, y, steady = t[ok], seg[ok].astype(np.int64), y_blocks[ok], steady[ok]
    m = {r: blocks.mean[r][ok] for r in roles}
    x = Inputs(t, m[PUMP_SPEED], m[PUMP_DISP], m[DP], m[TEMP], dp_rate[ok], seg)
    if len(t) < MIN_BLOCKS:
        raise DataError(
            f"{source}: only {len(t)} usable 0.1 s blocks of data; need at least {MIN_BLOCKS} "
            f"({MIN_BLOCKS * BLOCK_S:.0f} s)" + (f"; left out as implausible: {why}" if why else "")
        )
    constant = frozenset(r for r in INPUT_ROLES if np.ptp(getattr(x, r)) == 0.0)
    return GapData(x, y, steady, dp_lo[ok], dp_hi[ok], quantity, source, "series", constant, int(bad.sum()), why)


# A table's canonical order: by oil temperature, then delta pressure, pump speed, displacement and the
# output (the last key of np.lexsort is the first). Any order of the same rows gives the same data.
CANONICAL = (TEMP, DP, PUMP_SPEED, PUMP_DISP)


def from_points(
    pts: Points, quantity: str, limits: GateLimits | None = None, drive: DriveParams | None = None
) -> GapData:
    """An operating-point table: each plausible row a steady point, its own segment (no time
    structure), in the canonical order of its operating points."""
    _check_quantity(quantity, pts.source)
    limits = gate_limits_for(quantity, limits, drive)
    v = {r: np.asarray(pts.values[r], dtype=np.float64) for r in gated_roles(quantity)}
    bad = implausible(v, limits)
    why = refusal(v, bad, limits)
    n = int((~bad).sum())
    if n < MIN_POINTS:
        of = f" of {len(pts)}" if bad.any() else ""
        raise DataError(
            f"{pts.source}: only {n}{of} operating points; need at least {MIN_POINTS}"
            + (f"; left out as implausible: {why}" if why else "")
        )
    keep = np.flatnonzero(~bad)
    order = keep[np.lexsort(tuple(v[r][keep] for r in (quantity, *reversed(CANONICAL))))]
    v = {r: a[order] for r, a in v.items()}
    x = Inputs(np.arange(n, dtype=float), v[PUMP_SPEED], v[PUMP_DISP], v[DP], v[TEMP], np.zeros(n), np.arange(n))
    constant = frozenset(r for r in INPUT_ROLES if r not in pts.measured or np.ptp(v[r]) == 0.0)
    return GapData(
        x,
        v[quantity],
        np.ones(n, dtype=bool),
        v[DP],
        v[DP],
        quantity,
        pts.source,
        "points",
        constant,
        int(bad.sum()),
        why,
    )


def load_points(
    path: str | Path,
    spec: PointSpec,
    quantity: str = MOTOR_SPEED,
    limits: GateLimits | None = None,
    drive: DriveParams | None = None,
) -> GapData:
    """A table read with ``spec``; a row with a missing value is judged on its own (the gate refuses it)."""
    _check_quantity(quantity, str(path))
    pts = read_points(path, spec, (*INPUT_ROLES, quantity), min_rows=1, missing_as_nan=True)
    return from_points(pts, quantity, limits, drive)


def load(
    path: str | Path,
    quantity: str = MOTOR_SPEED,
    limits: GateLimits | None = None,
    db: Any = None,
    mapping: Any = None,
    match: Any = None,
    drive: DriveParams | None = None,
) -> GapData:
    """REAL as a run CSV (columns as ``cmcan simulate`` writes them; extra columns ignored) or a CAN log.
    ``limits`` are the configuration's gates; where they are for another output quantity, the
    reference gates sized for ``drive`` are used (:func:`gate_limits_for`)."""
    p = Path(path)
    if not p.exists():
        raise DataError(f"{p}: file not found")
    _check_quantity(quantity, str(p))
    if is_log(p):
        if quantity == FLOW:
            raise DataError(f"{p}: flow_lpm needs a CSV with a measured flow_lpm column")
        if db is None:
            from cmcan.can.dbccache import load_compiled

            db = load_compiled()
        series = series_from_log(p, db, mapping, match=match)
        return from_series(series, quantity, limits, str(p), drive)
    from cmcan.io.runcsv import read_run_csv

    try:
        cols = read_run_csv(p, required=(*REQUIRED, quantity))
    except ValueError as exc:
        raise DataError(str(exc)) from None
    series, _ = series_from_columns(cols, str(p), quantity)
    return from_series(series, quantity, limits, str(p), drive)
