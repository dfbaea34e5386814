"""Which operating points may be evaluated: the rules shared by training, scoring and the monitor.

An operating point is the mean of each input over a trailing window (or a row of an operating-point
table, already a mean). It is evaluated only when every input is fresh and plausible, the drive is
steady (each input's spread within the window is small), and pump speed, pump displacement and the
measured output are high enough for the ratio to mean something. A point outside the model's
training envelope is still evaluated, and marked ``EXTRAPOLATED``: the model's physics carries it
(the learned correction fades out there), and a fault that moves the operating point out of the
envelope must not silence the monitor. What an extrapolated point may trigger is the warning
machine's business (:mod:`cmcan.monitor.warnings`). Training applies the same rules (without the
envelope, which it is about to define), so transients never teach the model.

The drive is judged in its forward direction, the one its model is trained in. A machine whose bus
sends a signed pump displacement (swash plate over centre) or a signed motor speed or flow reverses
in normal operation: such a point is ``REVERSE``, neither evaluated nor a fault, and the plausible
ranges of the pump displacement and the output judge their magnitudes (a motor turning at -3000 rpm
is plausible, one at -20000 rpm is not).

The default limits are the reference drive's (3000 rpm, 78 cm3/rev, 44 cm3/rev motor): :func:`scaled`
sizes them for another machine from its nominal pump speed, displacement and flow.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.windows import Affine, mean_std, window_sums
from cmcan.roles import MODEL_INPUTS, MOTOR_SPEED, PUMP_DISP, PUMP_SPEED


class Gate(IntEnum):
    """The verdict on an operating point; values are the DBC's ``cm_gate`` table.

    ``EVALUATING`` and ``EXTRAPOLATED`` points get a ratio (see :data:`EVALUATED`); the others say
    why a point got none."""

    EVALUATING = 0
    NO_INPUT = 1
    STALE_INPUT = 2
    IMPLAUSIBLE_INPUT = 3
    LOW_SPEED = 4  # pump speed below its minimum
    TRANSIENT = 5
    EXTRAPOLATED = 6  # evaluated, outside the model's training envelope
    WARMING_UP = 7
    LOW_DISPLACEMENT = 8  # pump displacement below its minimum
    LOW_FLOW = 9  # measured output (motor speed or flow) below its minimum
    MODEL_ERROR = 10  # the point was fit to evaluate, the model gave no plausible prediction
    REVERSE = 11  # travelling in reverse (negative pump displacement or output): not judged, not a fault


EVALUATED: frozenset[Gate] = frozenset({Gate.EVALUATING, Gate.EXTRAPOLATED})


# The reference drive the default limits are sized for: nominal pump speed and displacement, and the
# motor displacement that turns the minimum motor speed into a minimum flow.
REFERENCE_PUMP_SPEED_RPM = 3000.0
REFERENCE_PUMP_DISP_CC = 78.0
REFERENCE_MOTOR_DISP_CC = 44.0


@dataclass(frozen=True)
class GateLimits:
    window_s: float = 1.0
    min_samples: int = 5
    min_pump_speed_rpm: float = 700.0
    # Below this pump displacement a fixed leakage is a large share of a small flow and the ratio
    # exaggerates it; the extra-leakage estimate in l/min is still published.
    min_pump_disp_cc: float = 20.0
    # The measured output quantity: its role and its minimum, in its own unit.
    output_role: str = MOTOR_SPEED
    min_output: float = 300.0
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
    # A role whose message comes slowly (:func:`fit_to_cycles`): its own window and sample count.
    role_window_s: dict[str, float] = field(default_factory=dict)
    role_min_samples: dict[str, int] = field(default_factory=dict)

    def window_of(self, role: str) -> float:
        return self.role_window_s.get(role, self.window_s)

    def min_samples_of(self, role: str) -> int:
        return self.role_min_samples.get(role, self.min_samples)


def scaled(
    output_role: str,
    lpm_per_unit: float,
    pump_speed_nominal_rpm: float = REFERENCE_PUMP_SPEED_RPM,
    pump_disp_max_cc: float = REFERENCE_PUMP_DISP_CC,
    base: GateLimits | None = None,
) -> GateLimits:
    """The reference drive's limits sized for a machine: speed limits in proportion to its nominal
    pump speed, displacement limits to its largest displacement, output limits to its nominal flow
    (``pump_speed_nominal_rpm * pump_disp_max_cc``), in the output's unit (``lpm_per_unit`` l/min per
    unit: V_M / 1000 for motor speed, 1 for flow). The reference drive gets its limits unchanged."""
    b = base or GateLimits()
    ks = pump_speed_nominal_rpm / REFERENCE_PUMP_SPEED_RPM
    kd = pump_disp_max_cc / REFERENCE_PUMP_DISP_CC
    # The reference output is motor speed; as flow it is rpm * V_M,ref / 1000, then scaled by the
    # nominal flow and put in the machine's unit. Exactly 1.0 for the reference drive.
    ko = (pump_speed_nominal_rpm * pump_disp_max_cc) / (REFERENCE_PUMP_SPEED_RPM * REFERENCE_PUMP_DISP_CC)
    ko = ko * ((REFERENCE_MOTOR_DISP_CC / 1000.0) / lpm_per_unit)
    k = {PUMP_SPEED: ks, PUMP_DISP: kd}
    ref_out = b.output_role

    def std_of(role: str) -> float | None:
        if role == output_role:
            return b.max_std[ref_out] * ko if ref_out in b.max_std else None
        v = b.max_std.get(role)
        return None if v is None else v * k.get(role, 1.0)

    max_std = {r: v for r in (*MODEL_INPUTS, output_role) if (v := std_of(r)) is not None}
    plausible = {
        r: (lo * k.get(r, 1.0), hi * k.get(r, 1.0)) for r, (lo, hi) in b.plausible.items() if r in MODEL_INPUTS
    }
    lo, hi = b.plausible[ref_out]
    plausible[output_role] = (lo * ko, hi * ko)
    return replace(
        b,
        min_pump_speed_rpm=b.min_pump_speed_rpm * ks,
        min_pump_disp_cc=b.min_pump_disp_cc * kd,
        output_role=output_role,
        min_output=b.min_output * ko,
        max_std=max_std,
        plausible=plausible,
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
    window_s: float | Mapping[str, float],
) -> WindowStats:
    """Trailing-window statistics at each evaluation time, for irregularly sampled series.

    ``series[role] = (timestamps, values)``, timestamps ascending. The window at time t holds the
    samples with t - window_s < timestamp <= t (``window_s`` one for all roles, or each role's: the
    monitor's window, :mod:`cmcan.monitor.windows`). Float values are centred on their median before
    the cumulative sums (less cancellation); integer raw values would be exact.
    """
    mean, std, count, age = {}, {}, {}, {}
    for role, (ts, vs) in series.items():
        ref = float(np.median(vs)) if len(vs) else 0.0
        span = window_s[role] if isinstance(window_s, Mapping) else window_s
        s1, s2, n, newest = window_sums(ts, np.asarray(vs, dtype=np.float64) - ref, eval_t, span)
        mean[role], std[role] = mean_std(s1, s2, n, Affine(1.0, ref))
        count[role] = n
        age[role] = eval_t - newest
    return WindowStats(mean, std, count, age)


def signed_roles(limits: GateLimits) -> tuple[str, str]:
    """The roles a bus may send signed, with a negative value for reverse travel: their plausible
    ranges judge the magnitude, and a clearly negative one makes the point ``REVERSE``."""
    return (PUMP_DISP, limits.output_role)


def outside_plausible(role: str, values: NDArray[np.float64], limits: GateLimits) -> NDArray[np.bool_]:
    """Per value of ``role``: outside its plausible range (NaN too), the magnitude judged for the
    roles of :func:`signed_roles` (the rule :func:`gate_point` applies to one point)."""
    lo, hi = limits.plausible.get(role, (-math.inf, math.inf))
    v = np.abs(values) if role in signed_roles(limits) else np.asarray(values)
    with np.errstate(invalid="ignore"):
        return ~((lo <= v) & (v <= hi))


def gate_point(
    mean: dict[str, float],
    std: dict[str, float],
    count: dict[str, int],
    age_s: dict[str, float],
    limits: GateLimits,
    max_age_s: Mapping[str, float] | None = None,
    envelope: Mapping[str, tuple[float, float]] | None = None,
) -> Gate:
    """The gate of one operating point; the first failing rule in this order wins: no input, stale
    input, warming up, implausible input (the pump displacement and the output by their magnitude),
    reverse, low pump speed, low displacement, low output, transient; a point that passes them all
    is ``EXTRAPOLATED`` when a model input lies outside ``envelope`` (input name -> [min, max],
    bounds included), else ``EVALUATING``.

    ``REVERSE`` takes a pump displacement or an output that is negative by at least its minimum
    (``min_pump_disp_cc``, ``min_output``): a window about a change of direction, or a machine at
    neutral whose signed sensors read a little below zero, has a mean near zero and stays
    ``LOW_DISPLACEMENT``, ``LOW_FLOW`` or ``TRANSIENT``.

    The monitor calls this per evaluation tick and training per window, so both apply the very same
    rules. All inputs silent (the machine is off, the bus idle) is ``NO_INPUT``, not a fault; some
    inputs silent while others arrive is ``STALE_INPUT``.
    """
    out = limits.output_role
    roles = [r for r in (*MODEL_INPUTS, out) if r in mean]
    verdict = _inputs_gate(roles, mean, count, age_s, limits, max_age_s)
    if verdict is not None:
        return verdict
    d, o = mean[PUMP_DISP], mean[out]
    if (d < 0.0 and d <= -limits.min_pump_disp_cc) or (o < 0.0 and o <= -limits.min_output):
        return Gate.REVERSE
    if mean[PUMP_SPEED] < limits.min_pump_speed_rpm:
        return Gate.LOW_SPEED
    if abs(mean[PUMP_DISP]) < limits.min_pump_disp_cc:
        return Gate.LOW_DISPLACEMENT
    if mean[out] < limits.min_output:
        return Gate.LOW_FLOW
    for r, lim in limits.max_std.items():
        if r in std and std[r] > lim:
            return Gate.TRANSIENT
    if envelope is not None:
        for r, (lo, hi) in envelope.items():
            if not (lo <= mean[r] <= hi):
                return Gate.EXTRAPOLATED
    return Gate.EVALUATING


def _inputs_gate(
    roles: list[str],
    mean: dict[str, float],
    count: dict[str, int],
    age_s: dict[str, float],
    limits: GateLimits,
    max_age_s: Mapping[str, float] | None,
) -> Gate | None:
    """The first rules of :func:`gate_point`, on the inputs themselves: present, fresh, enough
    samples, plausible. None when they pass."""
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
        if count[r] < limits.min_samples_of(r):
            return Gate.WARMING_UP
    signed = signed_roles(limits)
    for r in roles:
        lo, hi = limits.plausible.get(r, (-math.inf, math.inf))
        m = abs(mean[r]) if r in signed else mean[r]
        if not (lo <= m <= hi):  # also catches NaN
            return Gate.IMPLAUSIBLE_INPUT
    return None


def prediction_ok(predicted: float, limits: GateLimits) -> bool:
    """A prediction the monitor may divide by: a positive finite number within the range the output
    quantity itself is plausible in (a prediction of 1e30 rpm would read as wear, not as a model
    gone wrong)."""
    hi = limits.plausible.get(limits.output_role, (0.0, math.inf))[1]
    return 0.0 < predicted <= hi  # False for NaN


def predictions_ok(predicted: NDArray[np.float64], limits: GateLimits) -> NDArray[np.bool_]:
    """:func:`prediction_ok` over an array."""
    hi = limits.plausible.get(limits.output_role, (0.0, math.inf))[1]
    with np.errstate(invalid="ignore"):
        return (predicted > 0.0) & (predicted <= hi)


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
    training, scoring and the columnar replay call this one, the streaming core the other."""
    out_role = limits.output_role
    roles = [r for r in (*MODEL_INPUTS, out_role) if r in mean]
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
        decide(count[r] < limits.min_samples_of(r), Gate.WARMING_UP)
    with np.errstate(invalid="ignore"):
        for r in roles:
            decide(outside_plausible(r, mean[r], limits), Gate.IMPLAUSIBLE_INPUT)  # NaN too
        d, o = mean[PUMP_DISP], mean[out_role]
        decide(((d < 0.0) & (d <= -limits.min_pump_disp_cc)) | ((o < 0.0) & (o <= -limits.min_output)), Gate.REVERSE)
        decide(mean[PUMP_SPEED] < limits.min_pump_speed_rpm, Gate.LOW_SPEED)
        decide(np.abs(mean[PUMP_DISP]) < limits.min_pump_disp_cc, Gate.LOW_DISPLACEMENT)
        decide(mean[out_role] < limits.min_output, Gate.LOW_FLOW)
        transient = np.zeros(n, dtype=bool)
        for r, lim in limits.max_std.items():
            if r in std:
                transient |= std[r] > lim
        decide(transient, Gate.TRANSIENT)
        if envelope is not None:
            outside = np.zeros(n, dtype=bool)
            for r, (lo, hi) in envelope.items():
                outside |= ~((lo <= mean[r]) & (mean[r] <= hi))
            decide(outside, Gate.EXTRAPOLATED)
    return out


def gate(
    stats: WindowStats,
    limits: GateLimits,
    max_age_s: Mapping[str, float] | None = None,
    envelope: Mapping[str, tuple[float, float]] | None = None,
) -> NDArray[np.int64]:
    """:func:`gate_point` over many windows (training and evaluation)."""
    return gate_columns(stats.mean, stats.std, stats.count, stats.age_s, limits, max_age_s, envelope).astype(np.int64)


def table_stats(means: dict[str, NDArray[np.float64]]) -> WindowStats:
    """Statistics of points that are already means (rows of an operating-point table): every input
    fresh, enough samples, no spread within the point. Gated with :func:`gate` like windows, so the
    rules on plausibility, minimum speed, displacement and output and the envelope are the same;
    staleness and steadiness do not apply to a cycle mean."""
    n = len(next(iter(means.values()))) if means else 0
    big = np.iinfo(np.int64).max
    return WindowStats(
        {r: np.asarray(v, dtype=np.float64) for r, v in means.items()},
        {r: np.zeros(n) for r in means},
        {r: np.full(n, big, dtype=np.int64) for r in means},
        {r: np.zeros(n) for r in means},
    )


def eval_times(t_first: float, t_last: float, rate_hz: float) -> NDArray[np.float64]:
    """Evaluation instants: multiples of the period, as the monitor ticks on frame time."""
    period = 1.0 / rate_hz
    k0 = np.floor(t_first / period) + 1
    k1 = np.floor(t_last / period)
    return np.arange(k0, k1 + 1) * period


# -- slow messages ----------------------------------------------------------------------------------

WINDOW_CYCLES = 2.0  # a role's window holds at least this many cycles of its message
AGE_CYCLES = 1.5  # and its newest sample may be this many cycles old before it is stale


@dataclass(frozen=True)
class RoleFit:
    """How one role's window, sample count and age fit its message's cycle time (:func:`fit_to_cycles`)."""

    cycle_s: float | None  # None: not known (no cycle time in the DBC or the configuration)
    window_s: float
    min_samples: int
    max_age_s: float

    @property
    def fitted(self) -> bool:
        return self.cycle_s is not None


def fit_to_cycles(
    limits: GateLimits, max_age_s: Mapping[str, float], cycles_s: Mapping[str, float | None]
) -> tuple[GateLimits, dict[str, float], dict[str, RoleFit]]:
    """The limits and maximum sample ages fitted to each role's message cycle time (``cycles_s``:
    seconds, None where not known), so that a role sent slowly is judged at all:

    - its window spans at least ``WINDOW_CYCLES`` cycles (a message sent once a second gets a 2 s
      window: the configured 1 s would hold one sample or none);
    - it needs half the samples its window holds at its cycle, at least 1, at most ``min_samples``
      (10 ms and 100 ms messages keep the configured 5);
    - its newest sample may be ``AGE_CYCLES`` cycles old (at least the configured age).

    A role whose cycle time is not known keeps the configured values (the configuration check says
    so). Pure: the same fit for the monitor, training and scoring."""
    role_window: dict[str, float] = {}
    role_min: dict[str, int] = {}
    ages = dict(max_age_s)
    fits: dict[str, RoleFit] = {}
    for role, cycle in cycles_s.items():
        age = max_age_s.get(role, math.inf)
        if cycle is None or not cycle > 0:
            fits[role] = RoleFit(None, limits.window_s, limits.min_samples, age)
            continue
        window = max(limits.window_s, WINDOW_CYCLES * cycle)
        need = min(limits.min_samples, max(1, math.floor(window / cycle / 2)))
        age = max(age, AGE_CYCLES * cycle) if math.isfinite(age) else age
        if window != limits.window_s:
            role_window[role] = window
        if need != limits.min_samples:
            role_min[role] = need
        ages[role] = age
        fits[role] = RoleFit(cycle, window, need, age)
    return replace(limits, role_window_s=role_window, role_min_samples=role_min), ages, fits
