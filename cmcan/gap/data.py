"""Measured data for the gap diagnosis: operating points with a steady flag each.

Two kinds of data become the same :class:`GapData`:
- a time series (run CSV or CAN log): 0.1 s block means (10 Hz), the pressure's rate over each block
  from the raw samples at its edges, the lowest and highest raw pressure in it, and the monitor's gate;
- an operating-point table (cycle means, rig logs): one point per row, all steady, no time structure.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
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
from cmcan.monitor.gating import Gate, GateLimits, eval_times, gate, window_stats
from cmcan.roles import DP, FLOW, MODEL_INPUTS, MOTOR_SPEED, PUMP_DISP, PUMP_SPEED, TEMP

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
        )


def _check_quantity(quantity: str, source: str) -> None:
    if quantity not in QUANTITIES:
        raise DataError(f"{source}: output quantity {quantity!r} is not one of {', '.join(QUANTITIES)}")


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
    limits: GateLimits,
    source: str,
) -> GapData:
    _check_quantity(quantity, source)
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
    gate_roles = {r: series[r] for r in roles}
    if MOTOR_SPEED not in gate_roles:
        gate_roles[MOTOR_SPEED] = series[quantity]
    steady = gate(window_stats(gate_roles, t, limits.window_s), limits) == Gate.EVALUATING
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
            f"({MIN_BLOCKS * BLOCK_S:.0f} s)"
        )
    constant = frozenset(r for r in INPUT_ROLES if np.ptp(getattr(x, r)) == 0.0)
    return GapData(x, y, steady, dp_lo[ok], dp_hi[ok], quantity, source, "series", constant)


def from_points(pts: Points, quantity: str) -> GapData:
    """An operating-point table: each row a steady point, its own segment (no time structure)."""
    _check_quantity(quantity, pts.source)
    n = len(pts)
    if n < MIN_POINTS:
        raise DataError(f"{pts.source}: only {n} operating points; need at least {MIN_POINTS}")
    v = pts.values
    x = Inputs(
        pts.rows.astype(float),
        v[PUMP_SPEED],
        v[PUMP_DISP],
        v[DP],
        v[TEMP],
        np.zeros(n),
        np.arange(n, dtype=np.int64),
    )
    constant = frozenset(r for r in INPUT_ROLES if r not in pts.measured or np.ptp(v[r]) == 0.0)
    return GapData(x, v[quantity], np.ones(n, dtype=bool), v[DP], v[DP], quantity, pts.source, "points", constant)


def load_points(path: str | Path, spec: PointSpec, quantity: str = MOTOR_SPEED) -> GapData:
    _check_quantity(quantity, str(path))
    return from_points(read_points(path, spec, (*INPUT_ROLES, quantity), min_rows=1), quantity)


def load(
    path: str | Path,
    quantity: str = MOTOR_SPEED,
    limits: GateLimits | None = None,
    db: Any = None,
    mapping: Any = None,
    match: Any = None,
) -> GapData:
    """REAL as a run CSV (columns as ``cmcan simulate`` writes them; extra columns ignored) or a CAN log."""
    p = Path(path)
    limits = limits or GateLimits()
    if not p.exists():
        raise DataError(f"{p}: file not found")
    _check_quantity(quantity, str(p))
    if is_log(p):
        if quantity == FLOW:
            raise DataError(f"{p}: flow_lpm needs a CSV with a measured flow_lpm column")
        if db is None:
            from cmcan.dbc import load_dbc

            db = load_dbc()
        series = series_from_log(p, db, mapping, match=match)
        return from_series(series, quantity, limits, str(p))
    from cmcan.io.runcsv import read_run_csv

    try:
        cols = read_run_csv(p, required=(*REQUIRED, quantity))
    except ValueError as exc:
        raise DataError(str(exc)) from None
    if MOTOR_SPEED not in cols:  # a flow machine: the output stands in for the gate's motor speed
        cols = {**cols, MOTOR_SPEED: cols[quantity]}
    series, _ = series_from_columns(cols, str(p))
    if quantity not in series:
        series[quantity] = (cols["time_s"], cols[quantity])
    return from_series(series, quantity, limits, str(p))
