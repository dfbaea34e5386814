"""Duty cycles: set points of pump speed, pump displacement and load over operating time.

A duty cycle is a list of segments (hold a set point for a while, ramp to the next). Mixed cycles draw
segments from phase tables of typical wheel-loader and excavator travel work; the ranges are what
such machines show on their drive (engine 900-2300 rpm, displacement 0-100 %, 20-440 bar).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class SetPoints:
    pump_speed_rpm: NDArray[np.float64]
    pump_disp_pct: NDArray[np.float64]
    dp_bar: NDArray[np.float64]


@dataclass(frozen=True)
class Phase:
    name: str
    duration_s: tuple[float, float]
    pump_speed_rpm: tuple[float, float]
    pump_disp_pct: tuple[float, float]
    dp_bar: tuple[float, float]


# Forward travel magnitudes; the drive model is direction-agnostic.
WHEEL_LOADER = (
    Phase("approach_pile", (4, 8), (1800, 2200), (70, 100), (120, 220)),
    Phase("dig", (3, 6), (2000, 2300), (25, 50), (330, 440)),
    Phase("reverse_out", (3, 6), (1800, 2100), (60, 90), (100, 180)),
    Phase("travel_to_truck", (4, 10), (1800, 2200), (70, 100), (80, 200)),
    Phase("dump", (3, 6), (900, 1100), (0, 10), (20, 40)),
)
EXCAVATOR = (
    Phase("idle", (5, 20), (900, 1000), (0, 5), (20, 30)),
    Phase("travel", (10, 60), (1600, 2000), (80, 100), (80, 200)),
    Phase("travel_slope_turn", (5, 20), (1800, 2000), (50, 80), (250, 420)),
    Phase("dig_stationary", (10, 40), (1800, 2000), (0, 5), (20, 40)),
)
CYCLES = {"wheel_loader": WHEEL_LOADER, "excavator": EXCAVATOR}


def setpoints(duty: dict[str, Any], t_s: NDArray[np.float64], rng: np.random.Generator) -> SetPoints:
    """Set points at the operating times ``t_s`` (seconds, ascending, gaps allowed for bursts)."""
    kind = duty["kind"]
    if kind == "change":  # one duty until at_h, another after, on the same operating clock
        i = int(np.searchsorted(t_s, duty["at_h"] * 3600.0))
        a, b = setpoints(duty["before"], t_s[:i], rng), setpoints(duty["after"], t_s[i:], rng)
        return SetPoints(
            np.concatenate([a.pump_speed_rpm, b.pump_speed_rpm]),
            np.concatenate([a.pump_disp_pct, b.pump_disp_pct]),
            np.concatenate([a.dp_bar, b.dp_bar]),
        )
    if kind == "constant":
        n = len(t_s)
        return SetPoints(
            np.full(n, duty["pump_speed_rpm"]), np.full(n, duty["pump_disp_pct"]), np.full(n, duty["dp_bar"])
        )
    if kind in CYCLES:
        end = float(t_s[-1]) if len(t_s) else 0.0
        knots = _mixed_cycle_knots(
            CYCLES[kind], end + 1.0, duty["ramp_s"], duty["speed_scale"], duty["load_scale"], rng
        )
        return _interp(knots, t_s)
    if kind == "table":
        return _table(duty, t_s)
    if kind == "sweep":
        return _sweep(duty, t_s, rng)
    raise ValueError(f"unknown duty kind {kind!r}")


def _mixed_cycle_knots(
    phases: tuple[Phase, ...],
    end_s: float,
    ramp_s: float,
    speed_scale: float,
    load_scale: float,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    # Enough cycles even if every segment draws its shortest duration.
    min_cycle = sum(p.duration_s[0] for p in phases)
    n_cycles = int(end_s / min_cycle) + 2
    n_seg = n_cycles * len(phases)
    lo = np.array([[p.duration_s[0], p.pump_speed_rpm[0], p.pump_disp_pct[0], p.dp_bar[0]] for p in phases])
    hi = np.array([[p.duration_s[1], p.pump_speed_rpm[1], p.pump_disp_pct[1], p.dp_bar[1]] for p in phases])
    idx = np.tile(np.arange(len(phases)), n_cycles)
    draw = lo[idx] + rng.random((n_seg, 4)) * (hi[idx] - lo[idx])
    draw[:, 1] = np.clip(draw[:, 1] * speed_scale, 0, None)
    draw[:, 3] = np.clip(draw[:, 3] * load_scale, 0, None)
    starts = np.concatenate([[0.0], np.cumsum(draw[:-1, 0])])
    return _knots(starts, draw[:, 1:], ramp_s)


def _knots(starts: NDArray[np.float64], values: NDArray[np.float64], ramp_s: float) -> NDArray[np.float64]:
    """Breakpoints (t, speed, disp, dp): each segment ramps from the previous value over ``ramp_s``."""
    n = len(starts)
    rows = np.empty((2 * n, 4))
    rows[0::2, 0] = starts
    rows[1::2, 0] = starts + np.minimum(ramp_s, np.diff(np.append(starts, np.inf)) * 0.5)
    rows[0::2, 1:] = np.vstack([values[:1], values[:-1]])
    rows[1::2, 1:] = values
    return rows


def _interp(knots: NDArray[np.float64], t_s: NDArray[np.float64]) -> SetPoints:
    return SetPoints(
        np.interp(t_s, knots[:, 0], knots[:, 1]),
        np.interp(t_s, knots[:, 0], knots[:, 2]),
        np.interp(t_s, knots[:, 0], knots[:, 3]),
    )


def _table(duty: dict[str, Any], t_s: NDArray[np.float64]) -> SetPoints:
    pts = duty["points"]
    tk = np.array([p["t_s"] for p in pts], dtype=float)
    vals = np.array([[p["pump_speed_rpm"], p["pump_disp_pct"], p["dp_bar"]] for p in pts], dtype=float)
    t = np.asarray(t_s, dtype=float)
    if duty["repeat"]:
        period = tk[-1]
        t = np.mod(t - tk[0], period) + tk[0] if period > tk[0] else t
    if duty["interpolation"] == "step":
        i = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 1)
        return SetPoints(vals[i, 0], vals[i, 1], vals[i, 2])
    knots = np.column_stack([tk, vals])
    return _interp(knots, t)


def _sweep(duty: dict[str, Any], t_s: NDArray[np.float64], rng: np.random.Generator) -> SetPoints:
    """A test-rig program: hold random set points drawn uniformly from the given ranges."""
    end = float(t_s[-1]) + 1.0 if len(t_s) else 1.0
    lo_hold, hi_hold = duty["hold_s"]
    n = int(end / lo_hold) + 2
    ranges = np.array([duty["pump_speed_rpm"], duty["pump_disp_pct"], duty["dp_bar"]], dtype=float)
    values = ranges[:, 0] + rng.random((n, 3)) * (ranges[:, 1] - ranges[:, 0])
    # Machines spend much time at the ends of a range (full stroke, relief pressure, top engine speed):
    # a share of the set points sits exactly there so the model's envelope includes them.
    at_edge = rng.random((n, 3)) < duty["edge_share"]
    high_end = rng.random((n, 3)) < 0.5
    values = np.where(at_edge, np.where(high_end, ranges[:, 1], ranges[:, 0]), values)
    holds = lo_hold + rng.random(n) * (hi_hold - lo_hold)
    starts = np.concatenate([[0.0], np.cumsum(holds[:-1])])
    return _interp(_knots(starts, values, duty["ramp_s"]), t_s)
