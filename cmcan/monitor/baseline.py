"""The machine's own healthy baseline, learned on board: learning, monitoring, baseline_suspect.

A gateway starts from its machine type's model. Every machine of a type differs a little from it
(displacements within their tolerance, healthy leakage, sensor calibration), and over the first hours
of steady operation the baseline learns by how much, as a correction of the type model's prediction in
l/min:

    c(x) = theta_0 + theta_1 * q_geo / 100 l/min + theta_2 * (dp / dp_ref) * (nu_ref / nu(T))

three physical terms: an offset (sensor zero errors), a share of the geometric flow
``q_geo = n_P V_P`` (displacement and speed-sensor tolerances, the motor's V_M), and a laminar leak at
the reference pressure and viscosity (the unit's own healthy leakage). Three numbers can learn what
differs between units of one type and cannot learn the shape of a wear curve; the ONNX graph stays the
type's model, untouched and checksummed, and the correction is added to its prediction outside it (the
gateway has no onnx package to build a graph with, and three numbers in the state file are easy to
inspect, reset and keep in a history).

Learning keeps, per bin of the envelope the configuration names (pump speed x dp x oil temperature),
the sufficient statistics of the residual ``r = (measured - type prediction) * lpm_per_unit`` against
the features: a few hundred numbers, whatever the hours. The fit is closed form (ridge-regularised
normal equations, each covered bin weighted equally, so hours of idling at one point do not outweigh
the rest of the envelope), float64, in microseconds: it runs at the tick that ends the learning, not
on the receive path. Only ticks the gate passed inside the envelope (``EVALUATING``) are learned.

Learning ends when ``coverage_pct`` of the bins hold ``min_points`` ticks each (the evidence) *and*
``min_hours`` of operation have passed while learning, never after a fixed time alone. The hours are
operating hours on the prognosis's clock (:mod:`cmcan.monitor.operating`): a logger that records
bursts some minutes apart, or a machine whose ticks mostly fall outside the envelope, still runs them.
Then the guard judges two parts of what was learned, each against the same ``suspect_lpm`` (what
units of the type differ by at a point of the envelope):

- the **mean**: a covered bin whose mean residual lies further than it from the type model (a
  machine that arrived with a leak, a wrong sensor; ``distance_lpm``);
- the **pressure part**: the learned correction less its flow part, ``theta_0 + theta_2 * laminar``
  (:func:`pressure_part`), at the covered bin where it is lowest, below minus it
  (``pressure_part_lpm``). A unit that delivers a few % more than its type (displacement and speed
  tolerances: the flow part, ``theta_1``) can carry a leak its mean hides; the leak does not grow
  with the flow, so the flow part does not carry it. The offset belongs to this part: an orifice
  leak (sqrt(dp)) over the covered pressures is learned as an offset and a slope, and the speed
  sensors, which read 0 at standstill, give no offset of their own. Only its low side is judged: a
  unit that leaks less than its type by more than units differ is no fault the type model misses.

Either beyond makes the baseline ``baseline_suspect`` (``suspect_by`` names the parts): the type model
stays the reference, the state says by how much (l/min). Otherwise the machine is ``monitoring``
against its own baseline.

One tick at a time (:meth:`Baseline.learn`), or a stretch of ticks (:meth:`Baseline.learn_columns`)
with the same additions in the same order: the same state bit for bit.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.operating import OperatingClock
from cmcan.monitor.warnings import Thresholds
from cmcan.oil import VG46, Oil
from cmcan.roles import DP, MODEL_INPUTS, PUMP_DISP, PUMP_SPEED, TEMP
from cmcan.schema import Num, Obj, Seq, setting

FORMAT = "cmcan-baseline/1"  # fields added since (pressure_part_lpm, suspect_by) have defaults: the same format
N_FEATURES = 3
FEATURES = ("offset_lpm", "geometric_per_100lpm", "laminar_leak_lpm")
BIN_ROLES = (PUMP_SPEED, DP, TEMP)  # the envelope the coverage is counted over
SUSPECT_PARTS = ("mean", "pressure")  # what the guard judges (suspect_by names those beyond the allowance)
HISTORY_MAX = 16
Q_SCALE_LPM = 100.0  # the geometric term per 100 l/min: its coefficient of the order of the others
_IX = {r: MODEL_INPUTS.index(r) for r in MODEL_INPUTS}
REF_DP_BAR, REF_TEMP_C = 300.0, 50.0  # where the laminar feature is 1 (its coefficient in l/min there)


class Mode(IntEnum):
    LEARNING = 1
    MONITORING = 2
    SUSPECT = 3


MODE_NAMES = {Mode.LEARNING: "learning", Mode.MONITORING: "monitoring", Mode.SUSPECT: "baseline_suspect"}
_MODE_OF = {v: k for k, v in MODE_NAMES.items()}


class BaselineStateError(ValueError):
    """A saved baseline that cannot be used; ``str()`` names the field."""


def _rising_edges(e: dict[str, Any]) -> tuple[str, str] | None:
    for role, edges in e.items():
        if edges is not None and any(b <= a for a, b in itertools.pairwise(edges)):
            return role, f"bin edges must rise, got {edges}"
    return None


@dataclass(frozen=True)
class BaselineSettings:
    """The configuration's ``baseline`` section, each setting declared once (:func:`cmcan.schema.setting`);
    the assembly makes :class:`BaselineParams` of them and the model."""

    edges: dict[str, Any] = setting(
        Obj({r: Seq(Num(-1e6, 1e6), min_len=2, max_len=21, default=None) for r in BIN_ROLES}, {}, _rising_edges),
        "per role (pump_speed_rpm, dp_bar, temp_c) the bin edges the coverage counts over; default: the "
        "model's envelope split in 3, 3 and 2 bins",
    )
    min_points: int = setting(
        Num(1, 10_000_000, "ticks", default=100, integer=True), "evaluated ticks a bin needs to count as covered"
    )
    coverage_pct: float = setting(Num(1, 100, "%", default=20.0), "share of the bins that must be covered")
    min_hours: float = setting(
        Num(0, 10000, "h", default=2.0),
        "and at least this many operating hours while learning (the operating clock the prognosis counts on)",
    )
    check_every_s: float = setting(
        Num(0.1, 3600, "s", default=60.0), "the learning's end is checked this often (tick time)"
    )
    suspect_lpm: float | None = setting(
        Num(0.01, 10000, "l/min", default=None),
        "a covered bin's mean residual further than this from the type model, or the learned correction's "
        "pressure part (offset and laminar leak) below minus this: suspect; default: "
        "suspect_sigmas x the type's unit-to-unit spread in the model's metadata, else 2 % of nominal flow",
    )
    suspect_sigmas: float = setting(Num(1, 20, default=4.0), "the allowance in the type's unit-to-unit spreads")
    learning_low_pct: float = setting(
        Num(50, 100, "%", default=95.0), "the low warning's ratio while the type model judges alone (learning)"
    )
    learning_high_pct: float = setting(
        Num(100, 200, "%", default=105.0), "the high warning's ratio while the type model judges alone"
    )


@dataclass(frozen=True)
class BaselineParams:
    """What the configuration's ``baseline`` section says (see :mod:`cmcan.config`)."""

    edges: tuple[tuple[float, ...], ...]  # bin edges along BIN_ROLES (ascending, >= 2 each)
    min_points: int  # ticks a bin needs to count as covered
    coverage_pct: float  # share of the bins that must be covered
    min_hours: float  # operating hours while learning at least (the operating clock)
    suspect_lpm: float  # a bin's mean residual, or the correction's pressure part, further than this: suspect
    lpm_per_unit: float  # the output quantity's unit in l/min (V_M / 1000 for motor speed)
    period_s: float  # one tick
    max_gap_s: float = 3600.0  # the operating clock's: a longer gap between ticks is the machine off
    oil: Oil = VG46
    ref_dp_bar: float = REF_DP_BAR
    ref_temp_c: float = REF_TEMP_C
    ridge: float = 1e-3  # relative to the mean diagonal: keeps an unexcited term near the type model
    block_ticks: int = 600  # the learning's end is checked once per block of this many ticks (a minute)
    # the warning thresholds while the type model judges alone (learning, suspect): wider
    learning_thresholds: Thresholds | None = None

    @property
    def n_bins(self) -> int:
        return math.prod(len(e) - 1 for e in self.edges)

    @property
    def bins_needed(self) -> int:
        return max(1, math.ceil(self.coverage_pct / 100.0 * self.n_bins - 1e-9))

    def describe(self) -> dict[str, Any]:
        """What must not change under saved statistics (a different envelope starts learning afresh)."""
        return {"edges": [list(e) for e in self.edges], "roles": list(BIN_ROLES)}


def features(p: BaselineParams, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """(n, 3) features of operating points ``x`` (n, 4) in the model's input order."""
    return unit_features(x, p.oil, p.ref_dp_bar, p.ref_temp_c)


def unit_features(
    x: NDArray[np.float64], oil: Oil = VG46, ref_dp_bar: float = REF_DP_BAR, ref_temp_c: float = REF_TEMP_C
) -> NDArray[np.float64]:
    """(n, 3) columns of what a unit differs from its type by (:data:`FEATURES`) at operating points
    ``x`` (n, 4) in the model's input order: the baseline learns them on board, ``fleet train``
    fits them per machine beside the type model."""
    x = np.asarray(x, dtype=np.float64)
    q_geo = x[:, _IX[PUMP_SPEED]] * x[:, _IX[PUMP_DISP]] / 1000.0
    nu_ref = oil.kinematic_viscosity_cst(np.array([ref_temp_c]))
    fluidity = nu_ref / oil.kinematic_viscosity_cst(x[:, _IX[TEMP]])
    out = np.empty((len(x), N_FEATURES))
    out[:, 0] = 1.0
    out[:, 1] = q_geo / Q_SCALE_LPM
    out[:, 2] = x[:, _IX[DP]] / ref_dp_bar * fluidity
    return out


def bin_index(p: BaselineParams, x: NDArray[np.float64]) -> NDArray[np.int64]:
    """Each point's envelope bin (row-major over BIN_ROLES), -1 outside the configured envelope."""
    x = np.asarray(x, dtype=np.float64)
    idx = np.zeros(len(x), dtype=np.int64)
    inside = np.ones(len(x), dtype=bool)
    for role, e in zip(BIN_ROLES, p.edges, strict=True):
        v = x[:, _IX[role]]
        k = np.searchsorted(np.asarray(e), v, side="right") - 1
        k = np.where(v == e[-1], len(e) - 2, k)  # the upper edge belongs to the last bin
        inside &= (k >= 0) & (k < len(e) - 1) & np.isfinite(v)
        idx = idx * (len(e) - 1) + np.clip(k, 0, len(e) - 2)
    return np.where(inside, idx, -1)


@dataclass(frozen=True)
class Fit:
    theta: tuple[float, float, float]  # l/min per feature (FEATURES)
    distance_lpm: float  # the covered bin's mean residual of largest magnitude (signed)
    bins_covered: int
    pressure_part_lpm: float = 0.0  # the correction less its flow part, at the covered bin where it is lowest


def pressure_part(
    p: BaselineParams, n: NDArray[np.int64], sxx: NDArray[np.float64], theta: tuple[float, float, float]
) -> float:
    """The learned correction less its flow part, ``theta_0 + theta_2 * laminar``, at the covered bin
    (its mean laminar feature) where it is lowest, in l/min: negative, the unit leaks more than its
    type. 0 with no bin covered."""
    cov = n >= p.min_points
    if not cov.any():
        return 0.0
    laminar = sxx[cov, 0, 2] / n[cov]  # sxx[b, 0, j] sums feature j (feature 0 is 1): the bin's mean
    return float(np.min(theta[0] + theta[2] * laminar))


def suspect_parts(f: Fit, allowance_lpm: float) -> tuple[str, ...]:
    """The parts of a fit beyond the guard's allowance (:data:`SUSPECT_PARTS`): the mean either way,
    the pressure part on its low side (a leak)."""
    beyond = (abs(f.distance_lpm) > allowance_lpm, f.pressure_part_lpm < -allowance_lpm)
    return tuple(name for name, b in zip(SUSPECT_PARTS, beyond, strict=True) if b)


def fit(
    p: BaselineParams, n: NDArray[np.int64], sxx: NDArray[np.float64], sxy: NDArray[np.float64], sy: NDArray[np.float64]
) -> Fit:
    """The closed-form fit over the covered bins, each weighted equally."""
    cov = n >= p.min_points
    if not cov.any():
        return Fit((0.0, 0.0, 0.0), 0.0, 0)
    w = 1.0 / n[cov]
    a = np.einsum("b,bij->ij", w, sxx[cov])
    b = np.einsum("b,bi->i", w, sxy[cov])
    lam = p.ridge * float(np.trace(a)) / N_FEATURES
    theta = np.linalg.solve(a + lam * np.eye(N_FEATURES), b)
    means = sy[cov] / n[cov]
    far = int(np.argmax(np.abs(means)))
    th = (float(theta[0]), float(theta[1]), float(theta[2]))
    return Fit(th, float(means[far]), int(cov.sum()), pressure_part(p, n, sxx, th))


class Baseline:
    """The learning stage's state (see the module)."""

    def __init__(self, p: BaselineParams) -> None:
        self.p = p
        self.mode = Mode.LEARNING
        b = p.n_bins
        self.n = np.zeros(b, dtype=np.int64)
        self.sxx = np.zeros((b, N_FEATURES, N_FEATURES))
        self.sxy = np.zeros((b, N_FEATURES))
        self.sy = np.zeros(b)
        self.covered = 0
        self.learned_ticks = 0
        # the operating hours while learning, counted as the prognosis counts its hours
        self.clock = OperatingClock(p.max_gap_s)
        self.theta = (0.0, 0.0, 0.0)
        self.distance_lpm = 0.0
        self.pressure_part_lpm = 0.0
        self.suspect_by: tuple[str, ...] = ()  # the parts the guard found beyond its allowance
        self.started_t_s: float | None = None  # frame time of the first learned tick
        self.finished_t_s: float | None = None
        self.history: list[dict[str, Any]] = []
        self.block: int | None = None  # the block of ticks the newest tick is in (tick index // block_ticks)
        self._rows: list[tuple[float, ...]] = []  # ticks of the open block learned one at a time, not yet folded
        self.shown = (0.0, 0)  # operating seconds learning and covered bins at the last check: the ticks' progress

    # -- what it tells ------------------------------------------------------------------------------

    @property
    def learned_h(self) -> float:
        return self.progress_of(self.clock.operating_s, self.covered)[0]

    @property
    def coverage_pct(self) -> float:
        return self.progress_of(self.clock.operating_s, self.covered)[1]

    @property
    def shown_progress(self) -> tuple[float, float]:
        """Hours learned and envelope covered (%) as of the last check: what the ticks carry."""
        return self.progress_of(*self.shown)

    def progress_of(self, learning_s: Any, covered: Any) -> tuple[Any, Any]:
        """Hours learned and share of the envelope covered (%) from the operating seconds while
        learning and the bins, as :attr:`learned_h` and :attr:`coverage_pct` compute them (the same
        operations for one value or an array)."""
        return learning_s / 3600.0, 100.0 * covered / self.p.n_bins

    @property
    def applies(self) -> bool:
        """The correction is the reference (monitoring); learning and suspect judge on the type model."""
        return self.mode == Mode.MONITORING

    def correction_lpm(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """The machine's correction of the type model at points ``x`` (l/min); zero unless monitoring."""
        if not self.applies:
            return np.zeros(len(x))
        phi = features(self.p, x)
        t0, t1, t2 = self.theta  # term by term, not a BLAS product: one row or many, the same sums
        return phi[:, 0] * t0 + phi[:, 1] * t1 + phi[:, 2] * t2

    def describe(self) -> dict[str, Any]:
        self.fold()
        return {
            "state": MODE_NAMES[self.mode],
            "learned_h": self.learned_h,
            "coverage_pct": self.coverage_pct,
            "bins_covered": self.covered,
            "bins": self.p.n_bins,
            "bins_needed": self.p.bins_needed,
            "min_hours": self.p.min_hours,
            "theta": dict(zip(FEATURES, self.theta, strict=True)),
            "distance_lpm": self.distance_lpm,
            "pressure_part_lpm": self.pressure_part_lpm,
            "suspect_by": list(self.suspect_by),
            "suspect_lpm": self.p.suspect_lpm,
            "started_t_s": self.started_t_s,
            "finished_t_s": self.finished_t_s,
            "history": list(self.history),
        }

    # -- learning -----------------------------------------------------------------------------------
    #
    # The learning's end is checked at the first tick of each block of ``block_ticks`` ticks (by tick
    # index), on the ticks before it: the same ticks in both forms, however the frames came in chunks.
    # One tick at a time the rows wait in a list and are folded in per block, as arrays: learning
    # costs the receive path an append per tick, not numpy calls on single rows.

    def tick(self, k: int, t_s: float, t_run_s: float, has_input: bool) -> bool:
        """The start of tick ``k`` (at ``t_s``; ``t_run_s`` on the run's continuous base, with input or
        not), before it is judged: the operating clock goes on, and at the first tick of a new block
        the rows so far are folded in and the learning's end checked. True when it ended here: from
        this tick on the machine is judged in its new state."""
        if self.mode != Mode.LEARNING:
            return False
        self.clock.hours(t_run_s, has_input)
        blk = k // self.p.block_ticks
        if self.block is None or blk == self.block:
            self.block = blk
            return False
        self.block = blk
        self.fold()
        return self._check(t_s, self.clock.operating_s)

    def add(self, t_s: float, x: tuple[float, float, float, float], measured: float, predicted: float) -> None:
        """One tick the gate passed inside the envelope, while learning (folded in at its block's end)."""
        if self.mode == Mode.LEARNING:
            self._rows.append((t_s, *x, measured, predicted))

    def fold(self) -> None:
        """The waiting rows into the statistics (the order of the additions is the ticks')."""
        if self._rows:
            a = np.array(self._rows, dtype=np.float64)
            self._rows = []
            self._accumulate(a[:, 0], a[:, 1:5], a[:, 5], a[:, 6])

    def _accumulate(
        self,
        t_s: NDArray[np.float64],
        x: NDArray[np.float64],
        measured: NDArray[np.float64],
        predicted: NDArray[np.float64],
    ) -> None:
        if not len(t_s):
            return
        b = bin_index(self.p, x)
        r = (measured - predicted) * self.p.lpm_per_unit
        phi = features(self.p, x)
        ok = (b >= 0) & np.isfinite(r) & np.isfinite(phi).all(axis=1)
        pos = np.flatnonzero(ok)
        if not len(pos):
            return
        b, r, phi = b[pos], r[pos], phi[pos]
        np.add.at(self.sxx, b, phi[:, :, None] * phi[:, None, :])
        np.add.at(self.sxy, b, phi * r[:, None])
        np.add.at(self.sy, b, r)
        np.add.at(self.n, b, 1)
        self.covered = int(np.count_nonzero(self.n >= self.p.min_points))
        self.learned_ticks += len(pos)
        if self.started_t_s is None:
            self.started_t_s = float(t_s[pos[0]])

    def _check(self, t_s: float, learning_s: float) -> bool:
        """The learning's end at a block's first tick (``learning_s``: the operating seconds while
        learning up to it): enough bins covered and enough hours."""
        self.shown = (learning_s, self.covered)
        if self.covered >= self.p.bins_needed and learning_s / 3600.0 >= self.p.min_hours - 1e-12:
            self._finish(t_s)
            return True
        return False

    def run_columns(
        self,
        ks: NDArray[np.int64],
        t_k: NDArray[np.float64],
        t_run_s: NDArray[np.float64],
        has_input: NDArray[np.bool_],
        cand: NDArray[np.int64],
        x: NDArray[np.float64],
        measured: NDArray[np.float64],
        predicted: NDArray[np.float64],
    ) -> tuple[int, NDArray[np.int64], NDArray[np.int64]]:
        """:meth:`tick` and :meth:`add` for a stretch of ticks ``ks`` (at ``t_k``, on the run's base
        ``t_run_s``, with input or not); ``cand``: the indexes of the ticks the gate passed, whose
        points are ``x``, ``measured``, ``predicted``. Returns the first tick judged in the new state
        (``len(ks)`` when the learning goes on) and each tick's shown progress (operating seconds
        while learning, covered bins)."""
        n = len(ks)
        split = n
        learning_shown, covered_shown = np.full(n, self.shown[0]), np.full(n, self.shown[1])
        if self.mode != Mode.LEARNING or not n:
            return split, learning_shown, covered_shown
        op_s = self.clock.seconds_columns(t_run_s, has_input, upto=0)  # the clock moves once the end is known
        blocks = ks // self.p.block_ticks
        prev = np.empty(n, dtype=np.int64)
        prev[0] = blocks[0] if self.block is None else self.block
        prev[1:] = blocks[:-1]
        done = 0  # candidates folded in so far
        for i in np.flatnonzero(blocks != prev).tolist():
            upto = int(np.searchsorted(cand, i))
            self.fold()
            self._accumulate(t_k[cand[done:upto]], x[done:upto], measured[done:upto], predicted[done:upto])
            done = upto
            ended = self._check(float(t_k[i]), float(op_s[i]))
            learning_shown[i:], covered_shown[i:] = self.shown
            if ended:
                split = i
                break
        self.block = int(blocks[split - 1]) if split == n else int(blocks[split])
        self.clock.seconds_columns(t_run_s, has_input, upto=n if split == n else split + 1)
        if split == n:  # the rest of the stretch's rows are learned; its end is checked at the next block
            self.fold()
            self._accumulate(t_k[cand[done:]], x[done:], measured[done:], predicted[done:])
        return split, learning_shown, covered_shown

    def _finish(self, t_s: float) -> None:
        f = fit(self.p, self.n, self.sxx, self.sxy, self.sy)
        self.theta, self.distance_lpm, self.pressure_part_lpm = f.theta, f.distance_lpm, f.pressure_part_lpm
        self.finished_t_s = t_s
        self.suspect_by = suspect_parts(f, self.p.suspect_lpm)
        self.mode = Mode.SUSPECT if self.suspect_by else Mode.MONITORING

    # -- reset, persistence -------------------------------------------------------------------------

    def reset(self, reason: str, at: str | None = None) -> None:
        """Learn afresh (after service): the baseline so far goes into the history with why and when."""
        self.history.append(
            {
                "state": MODE_NAMES[self.mode],
                "theta": dict(zip(FEATURES, self.theta, strict=True)),
                "distance_lpm": self.distance_lpm,
                "pressure_part_lpm": self.pressure_part_lpm,
                "suspect_by": list(self.suspect_by),
                "learned_h": self.learned_h,
                "coverage_pct": self.coverage_pct,
                "started_t_s": self.started_t_s,
                "finished_t_s": self.finished_t_s,
                "reset_reason": reason,
                "reset_at": at,
            }
        )
        del self.history[:-HISTORY_MAX]
        history = self.history
        self.__init__(self.p)  # type: ignore[misc]
        self.history = history

    def to_dict(self) -> dict[str, Any]:
        self.fold()  # the sums are the same whenever rows are folded in; the end is checked per block
        return {
            "format": FORMAT,
            "envelope": self.p.describe(),
            "state": MODE_NAMES[self.mode],
            "n": self.n.tolist(),
            "sxx": self.sxx.reshape(len(self.n), -1).tolist(),
            "sxy": self.sxy.tolist(),
            "sy": self.sy.tolist(),
            "learned_ticks": self.learned_ticks,
            "clock": self.clock.to_dict(),
            "block": self.block,
            "theta": list(self.theta),
            "distance_lpm": self.distance_lpm,
            "pressure_part_lpm": self.pressure_part_lpm,
            "suspect_by": list(self.suspect_by),
            "started_t_s": self.started_t_s,
            "finished_t_s": self.finished_t_s,
            "history": self.history,
        }

    @classmethod
    def from_dict(cls, d: Any, p: BaselineParams) -> tuple[Baseline, str | None]:
        """The saved baseline under ``p``; a document of another envelope (the configuration changed)
        starts learning afresh, its old baseline in the history: (baseline, why it restarted or None).
        A document that is not a saved baseline raises :class:`BaselineStateError`."""
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise BaselineStateError(f"baseline: not a {FORMAT} document")
        bl = cls(p)
        hist = d.get("history", [])
        if not isinstance(hist, list) or not all(isinstance(h, dict) for h in hist):
            raise BaselineStateError("baseline.history: expected a list of records")
        state = d.get("state")
        if state not in _MODE_OF:
            raise BaselineStateError(f"baseline.state: {state!r:.40} is not one of {', '.join(_MODE_OF)}")
        theta = _floats(d.get("theta"), "baseline.theta", N_FEATURES)
        distance = _floats([d.get("distance_lpm")], "baseline.distance_lpm", 1)[0]
        saved_pressure, suspect_by = _saved_guard(d, _MODE_OF[state])
        ticks = d.get("learned_ticks")
        if isinstance(ticks, bool) or not isinstance(ticks, int) or ticks < 0:
            raise BaselineStateError(f"baseline.learned_ticks: expected a count, got {ticks!r:.40}")
        started, finished = d.get("started_t_s"), d.get("finished_t_s")
        for name, v in (("started_t_s", started), ("finished_t_s", finished)):
            if v is not None and not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)):
                raise BaselineStateError(f"baseline.{name}: expected a time or null, got {v!r:.40}")
        learning_s, last_t_s = _saved_clock(d.get("clock"), ticks * p.period_s)
        if d.get("envelope") != p.describe():
            old = cls(p)
            old.clock.operating_s = learning_s
            old.mode, old.theta, old.distance_lpm = _MODE_OF[state], tuple(theta), distance  # type: ignore[assignment]
            old.pressure_part_lpm, old.suspect_by = saved_pressure or 0.0, suspect_by
            old.learned_ticks, old.started_t_s, old.finished_t_s = ticks, started, finished
            old.history = hist[-HISTORY_MAX:]
            old.covered = 0
            old.reset("the configured envelope changed")
            return old, "the configured envelope changed: learning afresh"
        nb = p.n_bins
        n = np.asarray(_ints(d.get("n"), "baseline.n", nb), dtype=np.int64)
        sxx = np.asarray(_floats_2d(d.get("sxx"), "baseline.sxx", nb, N_FEATURES * N_FEATURES)).reshape(
            nb, N_FEATURES, N_FEATURES
        )
        sxy = np.asarray(_floats_2d(d.get("sxy"), "baseline.sxy", nb, N_FEATURES))
        sy = np.asarray(_floats(d.get("sy"), "baseline.sy", nb))
        bl.n, bl.sxx, bl.sxy, bl.sy = n, sxx, sxy, sy
        bl.covered = int(np.count_nonzero(n >= p.min_points))
        bl.learned_ticks = ticks
        bl.clock.operating_s, bl.clock.last_t_s = learning_s, last_t_s
        bl.mode = _MODE_OF[state]
        bl.theta = (theta[0], theta[1], theta[2])
        bl.distance_lpm = distance
        # an older file's: what its learned correction says, from the same statistics (its state stays)
        bl.pressure_part_lpm = pressure_part(p, n, sxx, bl.theta) if saved_pressure is None else saved_pressure
        bl.suspect_by = suspect_by
        bl.started_t_s, bl.finished_t_s = started, finished
        bl.history = hist[-HISTORY_MAX:]
        block = d.get("block")
        if block is not None and (isinstance(block, bool) or not isinstance(block, int)):
            raise BaselineStateError(f"baseline.block: expected a block number or null, got {block!r:.40}")
        bl.block = block
        bl.shown = (learning_s, bl.covered)  # after a restart the ticks carry all that was saved
        return bl, None


def _saved_clock(clock: Any, ticks_s: float) -> tuple[float, float]:
    """The saved learning's operating clock; one saved before it: the time of its learned ticks."""
    if clock is None:
        return ticks_s, math.nan
    try:
        return OperatingClock.state_from(clock, "baseline.clock")
    except ValueError as exc:
        raise BaselineStateError(str(exc)) from None


def _saved_guard(d: dict[str, Any], mode: Mode) -> tuple[float | None, tuple[str, ...]]:
    """The guard's saved pressure part (None: saved before the guard judged it) and the parts beyond
    the allowance (a file saved before they were named: a suspect one was judged on its mean alone)."""
    pressure = d.get("pressure_part_lpm")
    if pressure is not None:
        pressure = _floats([pressure], "baseline.pressure_part_lpm", 1)[0]
    v = d.get("suspect_by")
    if v is None:
        return pressure, ("mean",) if mode == Mode.SUSPECT else ()
    if not isinstance(v, list) or not all(isinstance(a, str) and a in SUSPECT_PARTS for a in v):
        raise BaselineStateError(f"baseline.suspect_by: expected a list of {', '.join(SUSPECT_PARTS)}, got {v!r:.60}")
    return pressure, tuple(v)


def _floats(v: Any, name: str, n: int) -> list[float]:
    ok = isinstance(v, list) and len(v) == n
    ok = ok and all(isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) for a in v)
    if not ok:
        raise BaselineStateError(f"{name}: expected {n} finite numbers, got {v!r:.60}")
    return [float(a) for a in v]


def _ints(v: Any, name: str, n: int) -> list[int]:
    ok = isinstance(v, list) and len(v) == n
    ok = ok and all(isinstance(a, int) and not isinstance(a, bool) and a >= 0 for a in v)
    if not ok:
        raise BaselineStateError(f"{name}: expected {n} counts, got {v!r:.60}")
    return list(v)


def _floats_2d(v: Any, name: str, n: int, m: int) -> list[list[float]]:
    if not isinstance(v, list) or len(v) != n:
        raise BaselineStateError(f"{name}: expected {n} rows, got {v!r:.60}")
    return [_floats(row, f"{name}[{i}]", m) for i, row in enumerate(v)]
