"""Measured data for the gap diagnosis: block means at 10 Hz with a steady flag per point."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.effects import Inputs
from cmcan.model.features import (
    DataError,
    contiguous_spans,
    is_log,
    series_from_columns,
    series_from_log,
)
from cmcan.monitor.gating import Gate, GateLimits, eval_times, gate, window_stats

BLOCK_S = 0.1
QUANTITIES = {"motor_speed_rpm": "rpm", "flow_lpm": "l/min"}
REQUIRED = ("time_s", "pump_speed_rpm", "pump_disp_cc", "dp_bar", "temp_c")


@dataclass(frozen=True)
class GapData:
    x: Inputs
    y: NDArray[np.float64]  # the measured output quantity
    steady: NDArray[np.bool_]
    quantity: str
    source: str

    def subset(self, mask: NDArray[np.bool_]) -> GapData:
        return GapData(self.x.subset(mask), self.y[mask], self.steady[mask], self.quantity, self.source)


def from_series(
    series: Mapping[str, tuple[NDArray[np.float64], NDArray[np.float64]]],
    quantity: str,
    limits: GateLimits,
    source: str,
) -> GapData:
    if quantity not in QUANTITIES:
        raise DataError(f"{source}: output quantity {quantity!r} is not one of {', '.join(QUANTITIES)}")
    if quantity not in series:
        raise DataError(f"{source}: no {quantity} in the data")
    t_ref = series[quantity][0]
    spans = contiguous_spans(t_ref, max_gap_s=1.0)
    t = np.concatenate([eval_times(a, b, 1.0 / BLOCK_S) for a, b in spans]) if spans else np.empty(0)
    seg = (
        np.concatenate([np.full(len(eval_times(a, b, 1.0 / BLOCK_S)), i) for i, (a, b) in enumerate(spans)])
        if spans
        else np.empty(0, np.int64)
    )
    roles = [r for r in ("pump_speed_rpm", "pump_disp_cc", "dp_bar", "temp_c", "motor_speed_rpm") if r in series]
    blocks = window_stats({r: series[r] for r in roles}, t, BLOCK_S)
    y_blocks = window_stats({quantity: series[quantity]}, t, BLOCK_S).mean[quantity]
    ok = np.all([blocks.count[r] > 0 for r in roles], axis=0) & (blocks.count.get(quantity, np.ones(len(t))) > 0)
    ok &= np.isfinite(y_blocks)
    gate_roles = {r: series[r] for r in roles}
    if "motor_speed_rpm" not in gate_roles:
        gate_roles["motor_speed_rpm"] = series[quantity]
    steady = gate(window_stats(gate_roles, t, limits.window_s), limits) == Gate.EVALUATING
    t, seg, y, steady = t[ok], seg[ok].astype(np.int64), y_blocks[ok], steady[ok]
    m = {r: blocks.mean[r][ok] for r in roles}
    dp_rate = np.zeros_like(t)
    for s in np.unique(seg):
        idx = np.flatnonzero(seg == s)
        if len(idx) > 2:
            dp_rate[idx] = np.gradient(m["dp_bar"][idx], t[idx])
    x = Inputs(t, m["pump_speed_rpm"], m["pump_disp_cc"], m["dp_bar"], m["temp_c"], dp_rate, seg)
    if len(t) < 100:
        raise DataError(f"{source}: only {len(t)} usable 0.1 s blocks of data; need at least 100 (10 s)")
    return GapData(x, y, steady, quantity, source)


def load(
    path: str | Path,
    quantity: str = "motor_speed_rpm",
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
    if is_log(p):
        if db is None:
            from cmcan.dbc import load_dbc

            db = load_dbc()
        series = series_from_log(p, db, mapping, match)
        if quantity == "flow_lpm":
            raise DataError(f"{p}: flow_lpm needs a CSV with a measured flow_lpm column")
        return from_series(series, quantity, limits, str(p))
    from cmcan.io.runcsv import read_run_csv

    try:
        cols = read_run_csv(p, required=(*REQUIRED, quantity))
    except ValueError as exc:
        raise DataError(str(exc)) from None
    series, _ = series_from_columns(cols, str(p))
    if quantity not in series:
        series[quantity] = (cols["time_s"], cols[quantity])
    return from_series(series, quantity, limits, str(p))
