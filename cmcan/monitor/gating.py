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
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from enum import IntEnum
from typing import Any, NamedTuple

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
_EVALUATED_CODES = np.array(sorted(int(g) for g in EVALUATED), dtype=np.int8)


def is_evaluated(gate: Any) -> Any:
    """Whether a gate gets a ratio (:data:`EVALUATED`): one gate, or per gate of an array."""
    return np.isin(gate, _EVALUATED_CODES) if isinstance(gate, np.ndarray) else gate in EVALUATED


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


def outside_plausible(role: str, values: Any, limits: GateLimits) -> Any:
    """Per value of ``role`` (a float or an array): outside its plausible range (NaN too), the
    magnitude judged for the roles of :func:`signed_roles`."""
    lo, hi = limits.plausible.get(role, (-math.inf, math.inf))
    v = abs(values) if role in signed_roles(limits) else values
    return (v < lo) | (v > hi) | (v != v)  # v != v: NaN


# -- the rules, once --------------------------------------------------------------------------------
#
# Each rule is a predicate over the window statistics, written with operators that mean the same on
# floats and on arrays (``&``, ``|``, comparisons, ``abs``), so one definition serves one point (the
# daemon's tick, evaluated in order, the first rule that holds wins) and arrays of points (training,
# scoring, the columnar replay: every rule over the whole arrays, the first that holds wins).


class _Subject(NamedTuple):  # (made at every tick: a frozen dataclass's init costs microseconds)
    """What the rules look at: the window statistics (per role a float, or an array over points) and
    the limits they are judged by."""

    mean: Mapping[str, Any]
    std: Mapping[str, Any]
    count: Mapping[str, Any]
    age_s: Mapping[str, Any]
    limits: GateLimits
    max_age_s: Mapping[str, float] | None
    envelope: Mapping[str, tuple[float, float]] | None
    roles: list[str]  # the gated roles present: the model's inputs and the measured output
    missing: Any  # how many roles have no fresh sample (two rules ask; worked out once)


def _subject(
    mean: Mapping[str, Any],
    std: Mapping[str, Any],
    count: Mapping[str, Any],
    age_s: Mapping[str, Any],
    limits: GateLimits,
    max_age_s: Mapping[str, float] | None,
    envelope: Mapping[str, tuple[float, float]] | None,
) -> _Subject:
    roles = [r for r in (*MODEL_INPUTS, limits.output_role) if r in mean]
    # no fresh sample: none at all, or the newest older than its maximum age
    missing: Any = 0
    ages = max_age_s or {}
    for r in roles:
        a = age_s[r]
        missing = missing + ((a == math.inf) | (a > ages.get(r, math.inf)))
    return _Subject(mean, std, count, age_s, limits, max_age_s, envelope, roles, missing)


def _any(parts: Iterable[Any]) -> Any:
    """Or over the parts (floats' bools or arrays' alike); False for none."""
    acc: Any = False
    for p in parts:
        acc = acc | p
    return acc


def _no_input(s: _Subject) -> Any:
    # all inputs silent: the machine is off, the bus idle; not a fault
    return s.missing == len(s.roles)


def _stale(s: _Subject) -> Any:
    return s.missing > 0


def _warming_up(s: _Subject) -> Any:
    return _any(s.count[r] < s.limits.min_samples_of(r) for r in s.roles)


def _implausible(s: _Subject) -> Any:
    return _any(outside_plausible(r, s.mean[r], s.limits) for r in s.roles)


def _reverse(s: _Subject) -> Any:
    lim = s.limits
    d, o = s.mean[PUMP_DISP], s.mean[lim.output_role]
    return ((d < 0.0) & (d <= -lim.min_pump_disp_cc)) | ((o < 0.0) & (o <= -lim.min_output))


def _low_speed(s: _Subject) -> Any:
    return s.mean[PUMP_SPEED] < s.limits.min_pump_speed_rpm


def _low_displacement(s: _Subject) -> Any:
    return abs(s.mean[PUMP_DISP]) < s.limits.min_pump_disp_cc


def _low_flow(s: _Subject) -> Any:
    return s.mean[s.limits.output_role] < s.limits.min_output


def _transient(s: _Subject) -> Any:
    return _any(s.std[r] > lim for r, lim in s.limits.max_std.items() if r in s.std)


def _extrapolated(s: _Subject) -> Any:
    env = s.envelope or {}
    return _any((s.mean[r] < lo) | (s.mean[r] > hi) | (s.mean[r] != s.mean[r]) for r, (lo, hi) in env.items())


# The order is the rules' priority: the first that holds names the gate; none holding is EVALUATING.
RULES: tuple[tuple[Gate, Callable[[_Subject], Any]], ...] = (
    (Gate.NO_INPUT, _no_input),
    (Gate.STALE_INPUT, _stale),
    (Gate.WARMING_UP, _warming_up),
    (Gate.IMPLAUSIBLE_INPUT, _implausible),
    (Gate.REVERSE, _reverse),
    (Gate.LOW_SPEED, _low_speed),
    (Gate.LOW_DISPLACEMENT, _low_displacement),
    (Gate.LOW_FLOW, _low_flow),
    (Gate.TRANSIENT, _transient),
    (Gate.EXTRAPOLATED, _extrapolated),
)


def gate_point(
    mean: Mapping[str, float],
    std: Mapping[str, float],
    count: Mapping[str, int],
    age_s: Mapping[str, float],
    limits: GateLimits,
    max_age_s: Mapping[str, float] | None = None,
    envelope: Mapping[str, tuple[float, float]] | None = None,
) -> Gate:
    """The gate of one operating point: the first of :data:`RULES` that holds, in this order: no
    input, stale input, warming up, implausible input (the pump displacement and the output by their
    magnitude), reverse, low pump speed, low displacement, low output, transient; a point that passes
    them all is ``EXTRAPOLATED`` when a model input lies outside ``envelope`` (input name -> [min,
    max], bounds included), else ``EVALUATING``.

    ``REVERSE`` takes a pump displacement or an output that is negative by at least its minimum
    (``min_pump_disp_cc``, ``min_output``): a window about a change of direction, or a machine at
    neutral whose signed sensors read a little below zero, has a mean near zero and stays
    ``LOW_DISPLACEMENT``, ``LOW_FLOW`` or ``TRANSIENT``.

    The monitor calls this per evaluation tick, :func:`gate_columns` (training, scoring, the columnar
    replay) the same rules over arrays. All inputs silent (the machine is off, the bus idle) is
    ``NO_INPUT``, not a fault; some inputs silent while others arrive is ``STALE_INPUT``.
    """
    s = _subject(mean, std, count, age_s, limits, max_age_s, envelope)
    for g, rule in RULES:
        if rule(s):
            return g
    return Gate.EVALUATING


def prediction_ok(predicted: Any, limits: GateLimits) -> Any:
    """A prediction the monitor may divide by (a float, or per value of an array): a positive finite
    number within the range the output quantity itself is plausible in (a prediction of 1e30 rpm
    would read as wear, not as a model gone wrong). False for NaN."""
    hi = limits.plausible.get(limits.output_role, (0.0, math.inf))[1]
    return (predicted > 0.0) & (predicted <= hi)


def gate_columns(
    mean: Mapping[str, NDArray[np.float64]],
    std: Mapping[str, NDArray[np.float64]],
    count: Mapping[str, NDArray[np.int64]],
    age_s: Mapping[str, NDArray[np.float64]],
    limits: GateLimits,
    max_age_s: Mapping[str, float] | None = None,
    envelope: Mapping[str, tuple[float, float]] | None = None,
) -> NDArray[np.int8]:
    """:func:`gate_point` over arrays of operating points: the same :data:`RULES`, each over all
    points, the first that holds per point wins."""
    s = _subject(mean, std, count, age_s, limits, max_age_s, envelope)
    roles = s.roles
    n = len(mean[roles[0]]) if roles else 0
    out = np.full(n, Gate.EVALUATING, dtype=np.int8)
    open_ = np.ones(n, dtype=bool)  # no rule has decided yet
    with np.errstate(invalid="ignore"):
        for g, rule in RULES:
            hit = open_ & rule(s)
            out[hit] = g
            open_ &= ~hit
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
