"""Which operating points may be evaluated: the rules shared by training and the monitor.

An operating point is the mean of each input over a trailing window; it is evaluated only when every
input is fresh and plausible, the drive is steady (each input's spread within the window is small),
pump speed and displacement are high enough for the ratio to mean something, and the point lies in
the model's training envelope. Training applies the same rules (without the envelope, which it is
about to define), so transients never teach the model.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.windows import Affine, mean_std, window_sums
from cmcan.roles import GATED as GATED_ROLES


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
    samples with t - window_s < timestamp <= t (the monitor's window, :mod:`cmcan.monitor.windows`).
    Float values are centred on their median before the cumulative sums (less cancellation); integer
    raw values would be exact.
    """
    mean, std, count, age = {}, {}, {}, {}
    for role, (ts, vs) in series.items():
        ref = float(np.median(vs)) if len(vs) else 0.0
        s1, s2, n, newest = window_sums(ts, np.asarray(vs, dtype=np.float64) - ref, eval_t, window_s)
        mean[role], std[role] = mean_std(s1, s2, n, Affine(1.0, ref))
        count[role] = n
        age[role] = eval_t - newest
    return WindowStats(mean, std, count, age)


def gate_point(
    mean: dict[str, float],
    std: dict[str, float],
    count: dict[str, int],
    age_s: dict[str, float],
    limits: GateLimits,
    max_age_s: Mapping[str, float] | None = None,
    envelope: Mapping[str, tuple[float, float]] | None = None,
) -> Gate:
    """The gate of one operating point; the first failing rule in the order of :class:`Gate` wins.

    The monitor calls this per evaluation tick and training per window, so both apply the very same
    rules. All inputs silent (the machine is off, the bus idle) is ``NO_INPUT``, not a fault; some
    inputs silent while others arrive is ``STALE_INPUT``.
    """
    roles = [r for r in GATED_ROLES if r in mean]
    missing = 0
    for r in roles:
        a = age_s[r]
        if a == math.inf or (max_age_s is not None and a > max_age_s.get(r, math.inf)):
            missing += 1
    if missing == len(roles):
        return Gate.NO_INPUT
    if missing:
        return Gate.STALE_INPUT
    for r in roles:
        if count[r] < limits.min_samples:
            return Gate.WARMING_UP
    for r in roles:
        lo, hi = limits.plausible.get(r, (-math.inf, math.inf))
        m = mean[r]
        if not (lo <= m <= hi):  # also catches NaN
            return Gate.IMPLAUSIBLE_INPUT
    if (
        mean["pump_speed_rpm"] < limits.min_pump_speed_rpm
        or abs(mean["pump_disp_cc"]) < limits.min_pump_disp_cc
        or mean["motor_speed_rpm"] < limits.min_motor_speed_rpm
    ):
        return Gate.LOW_SPEED
    for r, lim in limits.max_std.items():
        if r in std and std[r] > lim:
            return Gate.TRANSIENT
    if envelope is not None:
        for r, (lo, hi) in envelope.items():
            if not (lo <= mean[r] <= hi):
                return Gate.OUTSIDE_ENVELOPE
    return Gate.EVALUATING


def gate_columns(
    mean: dict[str, NDArray[np.float64]],
    std: dict[str, NDArray[np.float64]],
    count: dict[str, NDArray[np.int64]],
    age_s: dict[str, NDArray[np.float64]],
    limits: GateLimits,
    max_age_s: Mapping[str, float] | None = None,
    envelope: Mapping[str, tuple[float, float]] | None = None,
) -> NDArray[np.int8]:
    """:func:`gate_point` over arrays of operating points, rule for rule (tests hold the two equal):
    training, evaluation and the columnar replay call this one, the streaming core the other."""
    roles = [r for r in GATED_ROLES if r in mean]
    n = len(mean[roles[0]]) if roles else 0
    out = np.full(n, Gate.EVALUATING, dtype=np.int8)
    open_ = np.ones(n, dtype=bool)  # no rule has decided yet

    def decide(mask: NDArray[np.bool_], g: Gate) -> None:
        nonlocal open_
        hit = open_ & mask
        out[hit] = g
        open_ = open_ & ~hit

    missing = np.zeros(n, dtype=np.int64)
    for r in roles:
        a = age_s[r]
        limit = max_age_s.get(r, math.inf) if max_age_s is not None else math.inf
        missing += (a == math.inf) | (a > limit)
    decide(missing == len(roles), Gate.NO_INPUT)
    decide(missing > 0, Gate.STALE_INPUT)
    for r in roles:
        decide(count[r] < limits.min_samples, Gate.WARMING_UP)
    for r in roles:
        lo, hi = limits.plausible.get(r, (-math.inf, math.inf))
        m = mean[r]
        with np.errstate(invalid="ignore"):
            decide(~((lo <= m) & (m <= hi)), Gate.IMPLAUSIBLE_INPUT)  # NaN too
    with np.errstate(invalid="ignore"):
        decide(
            (mean["pump_speed_rpm"] < limits.min_pump_speed_rpm)
            | (np.abs(mean["pump_disp_cc"]) < limits.min_pump_disp_cc)
            | (mean["motor_speed_rpm"] < limits.min_motor_speed_rpm),
            Gate.LOW_SPEED,
        )
        transient = np.zeros(n, dtype=bool)
        for r, lim in limits.max_std.items():
            if r in std:
                transient |= std[r] > lim
        decide(transient, Gate.TRANSIENT)
        if envelope is not None:
            outside = np.zeros(n, dtype=bool)
            for r, (lo, hi) in envelope.items():
                outside |= ~((lo <= mean[r]) & (mean[r] <= hi))
            decide(outside, Gate.OUTSIDE_ENVELOPE)
    return out


def gate(
    stats: WindowStats,
    limits: GateLimits,
    max_age_s: Mapping[str, float] | None = None,
    envelope: Mapping[str, tuple[float, float]] | None = None,
) -> NDArray[np.int64]:
    """:func:`gate_point` over many windows (training and evaluation)."""
    return gate_columns(stats.mean, stats.std, stats.count, stats.age_s, limits, max_age_s, envelope).astype(np.int64)


def eval_times(t_first: float, t_last: float, rate_hz: float) -> NDArray[np.float64]:
    """Evaluation instants: multiples of the period, as the monitor ticks on frame time."""
    period = 1.0 / rate_hz
    k0 = np.floor(t_first / period) + 1
    k1 = np.floor(t_last / period)
    return np.arange(k0, k1 + 1) * period
