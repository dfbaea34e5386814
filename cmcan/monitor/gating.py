"""Which operating points may be evaluated: the rules shared by training and the monitor.

An operating point is the mean of each input over a trailing window; it is evaluated only when every
input is fresh and plausible, the drive is steady (each input's spread within the window is small),
pump speed and displacement are high enough for the ratio to mean something, and the point lies in
the model's training envelope. Training applies the same rules (without the envelope, which it is
about to define), so transients never teach the model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

# Roles the gate looks at (in this order), with the model's inputs among them.
GATED_ROLES: tuple[str, ...] = ("pump_speed_rpm", "pump_disp_cc", "dp_bar", "temp_c", "motor_speed_rpm")


class Gate(IntEnum):
    """Why a point is or is not evaluated; values are the DBC's ``cm_gate`` table."""

    EVALUATING = 0
    NO_INPUT = 1
    STALE_INPUT = 2
    IMPLAUSIBLE_INPUT = 3
    LOW_SPEED = 4
    TRANSIENT = 5
    OUTSIDE_ENVELOPE = 6
    WARMING_UP = 7


@dataclass(frozen=True)
class GateLimits:
    window_s: float = 1.0
    min_samples: int = 5
    min_pump_speed_rpm: float = 700.0
    # Below this pump displacement a fixed leakage is a large share of a small flow and the ratio
    # exaggerates it; the extra-leakage estimate in l/min is still published.
    min_pump_disp_cc: float = 20.0
    min_motor_speed_rpm: float = 300.0
    # Largest standard deviation within the window for the drive to count as steady.
    max_std: dict[str, float] = field(
        default_factory=lambda: {
            "pump_speed_rpm": 8.0,
            "pump_disp_cc": 0.5,
            "dp_bar": 5.0,
            "temp_c": 0.5,
            "motor_speed_rpm": 8.0,
        }
    )
    # Physically plausible ranges; a value outside means a broken sensor or a bad frame.
    plausible: dict[str, tuple[float, float]] = field(
        default_factory=lambda: {
            "pump_speed_rpm": (0.0, 4500.0),
            "pump_disp_cc": (-1000.0, 1000.0),
            "dp_bar": (-100.0, 650.0),
            "temp_c": (-40.0, 130.0),
            "motor_speed_rpm": (0.0, 9000.0),
        }
    )


@dataclass(frozen=True)
class WindowStats:
    """Per role: window mean, standard deviation, sample count and age of the newest sample."""

    mean: dict[str, NDArray[np.float64]]
    std: dict[str, NDArray[np.float64]]
    count: dict[str, NDArray[np.int64]]
    age_s: dict[str, NDArray[np.float64]]


def window_stats(
    series: dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]],
    eval_t: NDArray[np.float64],
    window_s: float,
) -> WindowStats:
    """Trailing-window statistics at each evaluation time, for irregularly sampled series.

    ``series[role] = (timestamps, values)``, timestamps ascending. The window at time t holds the
    samples with t - window_s < timestamp <= t. Cumulative sums make it O(n) for any number of windows.
    """
    mean, std, count, age = {}, {}, {}, {}
    for role, (ts, vs) in series.items():
        hi = np.searchsorted(ts, eval_t, side="right")
        lo = np.searchsorted(ts, eval_t - window_s, side="right")
        n = hi - lo
        ref = float(np.median(vs)) if len(vs) else 0.0  # centre the sums: less cancellation
        c1 = np.concatenate([[0.0], np.cumsum(vs - ref)])
        c2 = np.concatenate([[0.0], np.cumsum((vs - ref) ** 2)])
        with np.errstate(invalid="ignore", divide="ignore"):
            m = (c1[hi] - c1[lo]) / n
            var = (c2[hi] - c2[lo]) / n - m**2
        mean[role] = m + ref
        std[role] = np.sqrt(np.maximum(var, 0.0))
        count[role] = n
        last = np.where(hi > 0, ts[np.maximum(hi - 1, 0)] if len(ts) else 0.0, -np.inf)
        age[role] = eval_t - last
    return WindowStats(mean, std, count, age)


def gate(
    stats: WindowStats,
    limits: GateLimits,
    max_age_s: dict[str, float] | None = None,
    envelope: dict[str, tuple[float, float]] | None = None,
) -> NDArray[np.int64]:
    """Gate code per evaluation time; the first failing rule in the order of :class:`Gate` wins."""
    n = len(next(iter(stats.mean.values())))
    code = np.full(n, int(Gate.EVALUATING))

    def mark(mask: NDArray[np.bool_], g: Gate) -> None:
        code[(code == Gate.EVALUATING) & mask] = int(g)

    roles = [r for r in GATED_ROLES if r in stats.mean]
    mark(np.any([~np.isfinite(stats.age_s[r]) for r in roles], axis=0), Gate.NO_INPUT)
    if max_age_s is not None:
        mark(np.any([stats.age_s[r] > max_age_s.get(r, np.inf) for r in roles], axis=0), Gate.STALE_INPUT)
    mark(np.any([stats.count[r] < limits.min_samples for r in roles], axis=0), Gate.WARMING_UP)
    implausible = np.zeros(n, dtype=bool)
    for r in roles:
        lo, hi = limits.plausible.get(r, (-np.inf, np.inf))
        m = stats.mean[r]
        implausible |= ~np.isfinite(m) | (m < lo) | (m > hi)
    mark(implausible, Gate.IMPLAUSIBLE_INPUT)
    low = (
        (stats.mean["pump_speed_rpm"] < limits.min_pump_speed_rpm)
        | (np.abs(stats.mean["pump_disp_cc"]) < limits.min_pump_disp_cc)
        | (stats.mean["motor_speed_rpm"] < limits.min_motor_speed_rpm)
    )
    mark(low, Gate.LOW_SPEED)
    transient = np.zeros(n, dtype=bool)
    for r, lim in limits.max_std.items():
        if r in stats.std:
            transient |= stats.std[r] > lim
    mark(transient, Gate.TRANSIENT)
    if envelope is not None:
        outside = np.zeros(n, dtype=bool)
        for r, (lo, hi) in envelope.items():
            outside |= (stats.mean[r] < lo) | (stats.mean[r] > hi)
        mark(outside, Gate.OUTSIDE_ENVELOPE)
    return code


def eval_times(t_first: float, t_last: float, rate_hz: float) -> NDArray[np.float64]:
    """Evaluation instants: multiples of the period, as the monitor ticks on frame time."""
    period = 1.0 / rate_hz
    k0 = np.floor(t_first / period) + 1
    k1 = np.floor(t_last / period)
    return np.arange(k0, k1 + 1) * period
