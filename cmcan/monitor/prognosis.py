"""Prognosis: operating hours until the warning and until end of life, each as p10/p50/p90, for wear
(the low side: the extra leakage grows, the ratio falls) and for a drifting displacement control (the
high side: the ratio rises; see :func:`estimate`).

The time base is operating hours: :class:`Stage` keeps an operating clock (the time between ticks
with input, gaps over ``max_gap_h`` cut out); no estimate on less than ``min_history_h`` of history.

Evaluated ticks go into a decimated history: one point per
``bin_h`` of operating time, the mean hour and ratio of its ticks and the sums that refer its leakage
to the reference conditions (``dp_ref_bar``, ``temp_ref_c``). A leak is a mix of a laminar flow (a worn
gap, ``a = (dp / dp_ref) * (mu(T_ref) / mu(T))``) and an orifice flow (a crack, a torn seal,
``o = sqrt(dp / dp_ref)``): ``leak = W * ((1 - s) a + s o)``. Per bin the sums of ``leak * a``,
``a^2``, ``leak * o``, ``a * o`` and ``o^2`` give its least-squares ``W`` for every orifice share ``s``
(ticks at low pressure, whose leakage says little, count little; below ``min_dp_bar`` not at all);
the estimate fits the share from the history's own spread of pressure and oil temperature
(:func:`_mix`: the wear law's fit of each share's referral), refers by the best one and divides an
end of life in l/min by how much higher the shares the data allow read the recent leakage. When the
history holds more than
``max_points``, adjacent points of its older half are merged in pairs down to three quarters of
that: the recent stretch keeps its resolution, the state stays bounded. One tick at a time
(:meth:`Prognosis.add`) or a stretch of ticks as arrays (:meth:`Prognosis.add_columns`): the same
bins with the same float additions in the same order, so both leave an identical state.
:meth:`Prognosis.restart` begins a new history (a replaced unit, a reset baseline);
:meth:`Prognosis.to_dict` / :meth:`Prognosis.from_dict` carry it across restarts. The estimate also
takes the open bin as its newest point once it holds ``min_ticks`` ticks.

The estimate (:func:`estimate`) fits the extra leakage ``y`` (l/min) over the history with a
baseline and a power law from an onset: ``y = b + c * ((h - t0) / (T - t0))^k`` for ``h > t0``
(``T`` the last point, so ``c`` is the rise from the onset until now). Wear grows slowly, then
faster; onset ``t0`` and shape ``k`` come from a grid, ``b`` and ``c`` (``c >= 0``) by least squares.

- No trend unless the best cell's rise is significant (``c`` over its standard error, inflated for
  the residuals' lag-1 autocorrelation, at least ``t_min``: the grid search and correlated points
  make 2 far too lax), and relevant: at least ``min_rise_lpm`` and, on the low side, the measured
  ratio's fall over the same onset and shape at least ``min_fall_pct`` (a share of the flow, so it
  scales with the machine). No gate in units of the points' own spread: that depends on the logger's
  sampling and the duty's pressure, not on the wear.
- The interval: the points weighed by their noise (a floor plus a share of the wear leakage, the
  share estimated from the worn stretch's residuals, at most ``level_rel``), curves are drawn from
  the fit's posterior (a cell by its likelihood, so every onset and shape the data do not rule out is
  drawn; its level and rise from their normal distributions; flat priors) and followed to each
  threshold, each time spread by ``model_rel`` (the law is an assumption). With ``pool_h`` (default
  0: off) the draws of the estimates of the last ``pool_h`` hours (at most a quarter of the hours
  left), less the hours since, are pooled with the current one's; referred to reference conditions,
  the oil's cycle that made this worth its lag is gone. Reported: p10, p50, p90.
- The law's own error (the hindcast): the fits of the history as it stood some hours ago (an
  eighth, a quarter and half of the worn stretch back, at least ``hindcast_min_h``) are asked how
  long they take to today's level; the one furthest from the hours it really took gives the factor
  ``q``. Every drawn curve's hours are spread by a lognormal of ``|ln q|`` and, where ``q > 1`` (the
  law ran slow: a crack's orifice law, a step of damage, heavier work), divided by ``q``; a law that
  ran fast moves nothing. Late is what a workshop booking cannot take: the interval carries the
  error of the law's form, and its lower end is set to hold the truth from below.
- Wear does not heal (the low side): the hours are also read through the corners of the levels the
  history held (:func:`_first_reached_hours`: staged damage, whose flat stretches pull the fit of the
  hours as they are towards a law standing still), each quantile booked at the earlier reading.
- State: ``none`` without a trend, ``imminent`` when p10 to end of life is within ``imminent_h``,
  ``trend`` otherwise.

Ratio thresholds (the low warning, an end of life given as a ratio) are mapped to an extra leakage by
the least-squares line of the ratio's deficit (100 - ratio) on the leakage over the history: on one
machine both move together, the ratio also through the flow it is a share of. The ratio is the one
measured, at the machine's own mix of oil temperatures and pressures, the leakage the referred one:
the line holds on average, and the warning, judged on the measured ratio, comes first on a warm or
high-pressure stretch, up to a part of the oil's cycle sooner than the hours to it say.

Nothing here reads a clock; float64 throughout; the same history gives the same estimate.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.operating import OperatingClock
from cmcan.oil import VG46, Oil
from cmcan.schema import Num, Str, finite_number, integer, setting

FORMAT = "cmcan-prognosis/3"
_FORMAT_V2 = "cmcan-prognosis/2"  # laminar sums only: read on, its points tell nothing of the orifice share
_FORMAT_V1 = "cmcan-prognosis/1"  # leakage as measured, not referred to reference conditions
NONE, TREND, IMMINENT = "none", "trend", "imminent"
LOW, HIGH = "low", "high"  # a trend's direction: the ratio to the low warning (wear) or the high one
EOL_KINDS = ("leak_lpm", "ratio_pct")
_NEVER_H = 1e6  # a drawn curve that never reaches a threshold; reported as inf
# Power-law exponents tried: 2^(i/8) from 1 to 8 (9 % apart; given as literals so every platform has
# the same grid). A coarser grid misfits the newest points, where the extrapolation starts, by more
# than their noise once the leakage is referred to reference conditions.
_SHAPES = (
    1.0, 1.091, 1.189, 1.297, 1.414, 1.542, 1.682, 1.834, 2.0, 2.181, 2.378, 2.594, 2.828,
    3.084, 3.364, 3.668, 4.0, 4.362, 4.757, 5.187, 5.657, 6.169, 6.727, 7.336, 8.0,
)  # fmt: skip
_SHAPE_ARRAY = np.array(_SHAPES, dtype=np.float64)


@dataclass(frozen=True)
class PrognosisParams:
    bin_h: float = 0.5  # one history point per half operating hour
    max_points: int = 256  # history bound (at least 64 h at full resolution; older merged in pairs)
    min_ticks: int = 10  # a bin with fewer valid ticks is too short to average and is dropped
    low_pct: float = 98.0  # the low warning's ratio (Thresholds.low_pct)
    high_pct: float = 102.0  # the high warning's ratio (Thresholds.high_pct)
    # End of life. Default: the ratio at 90 %, 10 % of the delivered flow lost to extra leakage beyond
    # a new unit's, a volumetric-efficiency loss at which hydrostatic units are commonly replaced (a
    # rule of thumb, short of loss of function: the simulated rig loses function at some 17 %). A
    # machine whose end of life is known configures it (l/min, or a ratio).
    eol_kind: str = setting(
        Str(default="ratio_pct", choices=EOL_KINDS),
        "what end of life is given in: the CM ratio (%) or the extra leakage (l/min at the reference conditions)",
        "end_of_life.kind",
    )
    eol_value: float = setting(
        Num(0.01, 10000, "(% or l/min at the reference conditions)", default=90.0),
        "the low side's end of life (a ratio in [50, 100) %, or a leakage)",
        "end_of_life.value",
    )
    # End of life on the high side: a ratio rising (the displacement control drifting, a misposition)
    # grows no leak; by default the mirror of the low side, the motor 10 % off its commanded speed, at
    # which a drive's speed control no longer holds the machine's travel or implement speed.
    eol_high_pct: float = setting(
        Num(100.5, 200, "%", default=110.0),
        "the high side's end of life: a ratio above the high warning (a drifting displacement control)",
        "end_of_life.high_pct",
    )
    imminent_h: float = setting(
        Num(0, 100000, "h", default=24.0), "p10 to end of life within this: imminent (service within a few shifts)"
    )
    min_points: int = 12  # the rising stretch must hold at least this many points (6 h)
    # No estimate on a shorter history: it need not hold one whole cycle of the oil and the duty (a
    # shift, a day), whose rising half a short history cannot tell from a trend
    min_history_h: float = 24.0
    # Onset candidates on the grid: ``onsets`` evenly over the history (some 3 h apart on 300 h) and
    # rises from min_points long each ``onset_ratio`` times longer: an onset's rounding errs the
    # extrapolation by its share of the rise's length, and a recent ramp of 10 h needs a finer grid
    # than one of 100 h
    onsets: int = 48
    onset_ratio: float = 1.07
    t_min: float = 6.0  # significance of the rise (grid search and autocorrelation make 2 too lax)
    # Significant is not yet relevant: a rise must also be wear worth a plan entry. On the low side
    # in both units a machine has: the referred leakage (at least the referral's own error against the
    # truth, 0.14-0.41 l/min on the benchmark) and the measured ratio, which scales with the machine's
    # flow (a tenth of the low warning's 2 % margin; healthy machines wander +-0.15 % after learning)
    min_rise_lpm: float = 0.5
    min_fall_pct: float = 0.2  # the measured ratio's fall over the same onset and shape, % of the flow
    min_rise_pct: float = 1.0  # the high side's: of the share of displacement the motor lacks, %
    draws: int = 400  # curves drawn for the interval
    sigma_floor_lpm: float = 0.05  # the noise assumed at least (a history smoother than the filter's)
    sigma_floor_pct: float = 0.01  # ... of that share
    # The wear law is an assumption: a field curve is no exact power law, and onset and shape are
    # picked from a grid. Hours to a threshold carry this relative error (lognormal) on top of the fit's.
    # 0.1 until the grid's finer onsets: the fit's own posterior then carried more of the onset's
    # uncertainty, and the 10-90 % band held the truth 94-97 % of the time (86-92 % at 0.06)
    model_rel: float = 0.06
    # The referred wear leakage may still scatter by a share of itself (a gap not quite laminar, the
    # sensors' lag behind the oil): the fit weighs its points by the share its residuals show, at most this.
    level_rel: float = 0.1
    # The law's own error, read off the history (the hindcast): the fit of the history as it stood
    # hindcast_share of the worn stretch ago (at least hindcast_min_h) is asked how long it would take
    # to reach today's level. Slower than it took (the law too slow: a crack, a step of damage, heavier
    # work) moves every curve's hours earlier by that factor; either way the factor's log widens the
    # spread. Late is what a workshop booking cannot take: a hindcast that was too fast moves nothing.
    # 0: off.
    hindcast_share: float = 0.25
    hindcast_min_h: float = 4.0
    # ... asking only fits whose rise was at least this: a fit from the first l/min of a rise has not
    # yet seen its bend and reads its own unresolved shape as the law's error (a cubic wear fitted at a
    # quarter of its rise as a near-straight line ran 2-3x slow, and the p50 was booked at a quarter of
    # the truth). The detection's smallest rise until a trend could be reported from 0.5 l/min
    hindcast_min_rise_lpm: float = 1.5
    # Wear does not heal: the low side's hours are also read by the law through the hours each level
    # was first reached (staged damage: through the steps' corners), each quantile booked at the
    # earlier of the two readings. 0: off
    first_reached: float = 1.0
    # Pool the estimates of the last pool_h hours (at most a quarter of the hours left), taken every
    # pool_every_h: off, as its lag costs more near the end than the referred leakage's scatter
    pool_h: float = 0.0
    pool_every_h: float = 2.0
    seed: int = 20260  # fixed: the same history gives the same interval
    # Reference conditions the leakage is referred to (a laminar gap flow: Q ~ dp / mu). Defaults: the
    # reference drive's rated 480 bar and 60 C oil, at which the simulator and a test rig state a wear
    # leakage; an end of life in l/min is meant at these conditions.
    dp_ref_bar: float = setting(
        Num(10, 1000, "bar", default=480.0), "the pressure the extra leakage is referred to", "ref_dp_bar"
    )
    temp_ref_c: float = setting(
        Num(-20, 150, "C", default=60.0), "the oil temperature the extra leakage is referred to", "ref_temp_c"
    )
    oil: Oil = VG46  # the configured oil's viscosity law (Config.oil)
    # The orifice share of the leak is fitted by the wear law's own fit of each share's referral
    # (:func:`_mix`); a share whose fit leaves more than this many times the best one's residual
    # variance (autocorrelation-inflated) more is ruled out. The end of life in l/min is booked at the
    # highest recent level of the shares left, over the best's (a factor on it)
    mix_chi2: float = 9.0
    # Below this pressure a tick's leakage is model error more than wear (a gap flow vanishes with dp)
    min_dp_bar: float = 20.0
    # The stage (:class:`Stage`) estimates once per this many operating hours (an estimate is a grid
    # fit of some tens of milliseconds: not on every tick)
    estimate_every_h: float = setting(Num(0.01, 100, "h", default=0.5), "one estimate per this much operating time")
    # Operating hours, not calendar hours: a gap between ticks longer than this is the machine switched
    # off (or the gateway with it) and adds nothing; a shorter one (a daemon restart, a time-lapse's
    # bursts some minutes apart, each standing for the time to the next) adds itself
    max_gap_h: float = setting(
        Num(0.001, 1000, "h", default=1.0), "a longer gap between ticks is the machine off: no operating hours"
    )

    def __post_init__(self) -> None:
        if self.eol_kind not in EOL_KINDS:
            raise ValueError(f"eol_kind {self.eol_kind!r} is not one of {', '.join(EOL_KINDS)}")
        if not self.low_pct < 100.0 < self.high_pct < self.eol_high_pct:
            raise ValueError("the ratios must lie low_pct < 100 < high_pct < eol_high_pct")
        if not self.onset_ratio > 1.0:
            raise ValueError("onset_ratio must be above 1")
        if not (self.max_gap_h > 0 and self.min_history_h >= 0):
            raise ValueError("max_gap_h must be positive and min_history_h not negative")
        if not self.bin_h > 0 or self.max_points < 2 * self.min_points:
            raise ValueError("bin_h must be positive and max_points at least twice min_points")
        if not (self.dp_ref_bar > 0 and self.min_dp_bar >= 0 and _TEMP_LO_C <= self.temp_ref_c <= _TEMP_HI_C):
            raise ValueError(
                f"dp_ref_bar must be positive, min_dp_bar not negative, temp_ref_c in "
                f"[{_TEMP_LO_C:g}, {_TEMP_HI_C:g}] C"
            )

    @property
    def end_of_life_text(self) -> str:
        """What end of life means for a machine with these settings, in one line for a planner."""
        if self.eol_kind == "leak_lpm":
            low = f"{self.eol_value:g} l/min of extra leakage (at {self.dp_ref_bar:g} bar, {self.temp_ref_c:g} C)"
        else:
            low = f"the CM ratio at {self.eol_value:g} % ({100.0 - self.eol_value:g} % of the flow lost to leakage)"
        return f"wear: {low}; a drifting displacement control: the ratio at {self.eol_high_pct:g} %"


Triple = tuple[float, float, float]
# A history point: mean hour, leakage referred to the reference conditions by the laminar law (l/min),
# ratio (%), ticks, and the bin's sums over its ticks of a^2, y * o, a * o and o^2 (y the leakage, a the
# laminar gain, o the orifice gain): with sum(y * a) = leak * sum(a^2) they refer the bin by any mix of
# the two laws (:func:`_refer`), and two bins merge by adding them
Point = tuple[float, float, float, int, float, float, float, float]
_NAN3: Triple = (math.nan, math.nan, math.nan)


@dataclass(frozen=True)
class Estimate:
    """State (none / trend / imminent), the trend's direction (low: the ratio falls with a growing
    leak, wear; high: it rises, a displacement control drifting; "" without a trend), hours until that
    side's warning and until its end of life as (p10, p50, p90) (NaN without a trend, inf where the
    curve never gets there), and the fits."""

    state: str = NONE
    at_h: float = math.nan  # the last history point's operating hour
    to_warning_h: Triple = _NAN3
    to_eol_h: Triple = _NAN3
    direction: str = ""
    rise_lpm: float = 0.0  # the leakage's fitted rise from the onset until now (at the reference conditions)
    t_stat: float = 0.0
    onset_h: float = math.nan
    shape_k: float = math.nan
    noise_lpm: float = 0.0  # the residuals' spread
    # rise_lpm, t_stat and noise_lpm are the low side's; onset_h and shape_k the reported side's
    fall_pct: float = 0.0  # the low side's: the measured ratio's fall over its onset and shape (%)
    rise_pct: float = 0.0  # the high side's fitted rise (of the share of displacement the motor lacks, %)
    t_stat_high: float = 0.0


@dataclass
class Prognosis:
    """The history and its open bin. ``points``: (hour, leak at reference l/min, ratio %, ticks,
    sum of squared gains) per bin. ``restarted``: why :meth:`from_dict` began a new history instead
    of loading the saved one ("" when it did not)."""

    params: PrognosisParams = field(default_factory=PrognosisParams)
    points: list[Point] = field(default_factory=list)
    open_bin: int | None = None  # index floor(hour / bin_h) of the bin being filled
    open_n: int = 0
    open_sum_h: float = 0.0
    open_sum_lg: float = 0.0  # sum of leak * gain (the laminar gain a)
    open_sum_gg: float = 0.0  # sum of gain^2
    open_sum_ratio: float = 0.0
    open_sum_lo: float = 0.0  # sum of leak * o (the orifice gain)
    open_sum_go: float = 0.0  # sum of a * o
    open_sum_oo: float = 0.0  # sum of o^2
    restarted: str = ""

    # -- one tick ------------------------------------------------------------------------------------

    def add(self, hour: float, leak_lpm: float, ratio_pct: float, dp_bar: float, temp_c: float, valid: bool) -> None:
        """One evaluated tick: its operating hour, raw extra leakage ((predicted - measured) *
        lpm_per_unit, l/min), raw ratio (%), operating point (window means of dp and oil temperature)
        and whether it was evaluated. Ticks not evaluated, below ``min_dp_bar`` or with a non-finite
        value are skipped."""
        ok = valid and all(math.isfinite(x) for x in (hour, leak_lpm, ratio_pct, dp_bar, temp_c))
        if not (ok and dp_bar >= self.params.min_dp_bar):
            return
        ga, go = _gains(self.params, np.array([dp_bar]), np.array([temp_c]))
        g, o = float(ga[0]), float(go[0])
        b = math.floor(hour / self.params.bin_h)
        if self.open_bin is None or b > self.open_bin:  # an earlier hour (clock back) stays in the open bin
            self._close()
            self.open_bin = b
        self.open_n += 1
        self.open_sum_h += hour
        self.open_sum_lg += leak_lpm * g
        self.open_sum_gg += g * g
        self.open_sum_ratio += ratio_pct
        self.open_sum_lo += leak_lpm * o
        self.open_sum_go += g * o
        self.open_sum_oo += o * o

    # -- a stretch of ticks --------------------------------------------------------------------------

    def add_columns(
        self,
        hours: NDArray[np.float64],
        leak_lpm: NDArray[np.float64],
        ratio_pct: NDArray[np.float64],
        dp_bar: NDArray[np.float64],
        temp_c: NDArray[np.float64],
        valid: NDArray[np.bool_],
    ) -> None:
        """:meth:`add` for every tick of a stretch: the same bins, the same additions in order."""
        cols = [np.asarray(x, dtype=np.float64) for x in (hours, leak_lpm, ratio_pct, dp_bar, temp_c)]
        keep = np.asarray(valid, dtype=bool) & np.logical_and.reduce([np.isfinite(x) for x in cols])
        keep &= cols[3] >= self.params.min_dp_bar
        h, lk, r, dp, tc = (x[keep] for x in cols)
        if not len(h):
            return
        g, o = _gains(self.params, dp, tc)
        lg, gg, lo, go, oo = lk * g, g * g, lk * o, g * o, o * o
        bins = np.floor(h / self.params.bin_h)
        start = -np.inf if self.open_bin is None else float(self.open_bin)
        eff = np.maximum.accumulate(np.maximum(bins, start))  # as add: never back to an earlier bin
        cuts = np.flatnonzero(np.diff(eff)) + 1
        edges = [0, *cuts.tolist(), len(h)]
        for a, z in itertools.pairwise(edges):
            b = int(eff[a])
            if self.open_bin is None or b > self.open_bin:
                self._close()
                self.open_bin = b
            self.open_n += z - a
            self.open_sum_h = _add_in_order(self.open_sum_h, h[a:z])
            self.open_sum_lg = _add_in_order(self.open_sum_lg, lg[a:z])
            self.open_sum_gg = _add_in_order(self.open_sum_gg, gg[a:z])
            self.open_sum_ratio = _add_in_order(self.open_sum_ratio, r[a:z])
            self.open_sum_lo = _add_in_order(self.open_sum_lo, lo[a:z])
            self.open_sum_go = _add_in_order(self.open_sum_go, go[a:z])
            self.open_sum_oo = _add_in_order(self.open_sum_oo, oo[a:z])

    # -- history -------------------------------------------------------------------------------------

    def _close(self) -> None:
        """The open bin becomes a point (when it holds enough ticks); the history thinned if full.
        Its leakage at the reference conditions is the least-squares L of leak_i = L * g_i."""
        q = self._open_point()
        if q is not None:
            self.points.append(q)
            if len(self.points) > self.params.max_points:
                self.points = _thin(self.points, self.params.max_points - self.params.max_points // 4)
        self._clear_open()

    def _clear_open(self) -> None:
        self.open_bin = None
        self.open_n = 0
        self.open_sum_h = self.open_sum_lg = self.open_sum_gg = self.open_sum_ratio = 0.0
        self.open_sum_lo = self.open_sum_go = self.open_sum_oo = 0.0

    def restart(self) -> None:
        """A replaced unit or a reset baseline: the wear history so far no longer applies."""
        self.points = []
        self._clear_open()

    def arrays(self, with_open: bool = False) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The closed points' hours, leakage at the reference conditions by the laminar law and ratio;
        ``with_open``: and the open bin's as the newest point, when it holds ``min_ticks`` ticks already."""
        p = self.table(with_open)
        return p[:, 0].copy(), p[:, 1].copy(), p[:, 2].copy()

    def table(self, with_open: bool = False) -> NDArray[np.float64]:
        """The points as rows (the fields of :data:`Point`), the open bin's last as in :meth:`arrays`."""
        pts = self.points + ([q] if with_open and (q := self._open_point()) is not None else [])
        return np.array(pts, dtype=np.float64).reshape(len(pts), 8)

    def _open_point(self) -> Point | None:
        n = self.open_n
        if n < self.params.min_ticks or not self.open_sum_gg > 0:
            return None
        return (
            self.open_sum_h / n,
            self.open_sum_lg / self.open_sum_gg,
            self.open_sum_ratio / n,
            n,
            self.open_sum_gg,
            self.open_sum_lo,
            self.open_sum_go,
            self.open_sum_oo,
        )

    def newest_h(self) -> float:
        """The newest operating hour the history holds: its last point's, or its open bin's (0: none)."""
        last = self.points[-1][0] if self.points else 0.0
        if self.open_bin is None:
            return last
        return max(last, self.open_sum_h / self.open_n if self.open_n else self.open_bin * self.params.bin_h)

    def estimate(self) -> Estimate:
        """The estimate from the history and the open bin: the newest ticks count as soon as they
        make a point, not only when a later bin begins (half an hour and more sooner near the end)."""
        p = self.table(with_open=True)
        return estimate(self.params, p[:, 0], p[:, 1], p[:, 2], sums=p[:, 3:])

    # -- state file ----------------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        p = self.params
        return {
            "format": FORMAT,
            "bin_h": p.bin_h,
            "reference": _reference(p),
            "points": [list(q) for q in self.points],
            "open": None
            if self.open_bin is None
            else [
                self.open_bin,
                self.open_n,
                self.open_sum_h,
                self.open_sum_lg,
                self.open_sum_gg,
                self.open_sum_ratio,
                self.open_sum_lo,
                self.open_sum_go,
                self.open_sum_oo,
            ],
        }

    @classmethod
    def from_dict(cls, d: Any, params: PrognosisParams | None = None) -> Prognosis:
        """A saved history, checked. A damaged document or one binned by another width raises
        ValueError. One this history cannot continue, though sound, gives a new empty history with
        :attr:`restarted` saying why: saved by the first version (leakage not referred to reference
        conditions) or referred to other reference conditions or another oil. A ``cmcan-prognosis/2``
        history (laminar sums only) goes on: its points are given orifice sums equal to their laminar
        ones, which refer them alike by any mix of the laws (they tell nothing of the mix; the
        points after the upgrade do)."""
        params = params or PrognosisParams()
        fmt = d.get("format") if isinstance(d, dict) else None
        if fmt == _FORMAT_V1:
            out = cls(params)
            out.restarted = (
                f"a {_FORMAT_V1} history holds leakage not referred to reference conditions: a new history begins"
            )
            return out
        if fmt not in (FORMAT, _FORMAT_V2):
            raise ValueError(f"not a {FORMAT} document")
        width, open_width = (8, 9) if fmt == FORMAT else (5, 6)
        if d.get("bin_h") != params.bin_h:
            raise ValueError(f"history binned by {d.get('bin_h')!r} h, not {params.bin_h} h")
        if d.get("reference") != _reference(params):
            out = cls(params)
            out.restarted = (
                f"history referred to {d.get('reference')!r:.120}, not {_reference(params)}: a new history begins"
            )
            return out
        pts = d.get("points")
        if not isinstance(pts, list):
            raise ValueError("field 'points': expected a list")
        out = cls(params)
        for i, q in enumerate(pts):
            ok = isinstance(q, list) and len(q) == width and count(q[3])
            if not (ok and all(finite_number(x) for x in q[:3] + q[4:]) and q[4] > 0):
                raise ValueError(f"field 'points[{i}]': expected [{', '.join(_POINT_FIELDS[:width])}], got {q!r:.60}")
            x = [float(v) for v in q[:3] + q[4:]]
            lam = (x[3], x[1] * x[3], x[3], x[3])  # a /2 point: orifice sums as its laminar ones
            s_aa, s_lo, s_ao, s_oo = lam if width == 5 else x[3:]
            if not _mix_sums_ok(s_aa, s_ao, s_oo):
                raise ValueError(f"field 'points[{i}]': its gain sums cannot come from one set of ticks, got {q!r:.60}")
            out.points.append((x[0], x[1], x[2], int(q[3]), s_aa, s_lo, s_ao, s_oo))
        hours = [q[0] for q in out.points]
        if any(b <= a for a, b in itertools.pairwise(hours)):
            raise ValueError("field 'points': the hours must increase")
        out.points = out.points[-params.max_points :]
        op = d.get("open")
        if op is not None:
            ok = isinstance(op, list) and len(op) == open_width and integer(op[0]) and count(op[1])
            if not (ok and all(finite_number(x) for x in op[2:]) and op[4] >= 0):
                raise ValueError(f"field 'open': expected [{', '.join(_OPEN_FIELDS[:open_width])}], got {op!r:.60}")
            if out.points and int(op[0]) < math.floor(out.points[-1][0] / params.bin_h):
                raise ValueError("field 'open': its bin lies before the last point")
            x = [float(v) for v in op[2:]]
            mix = x[4:] if open_width == 9 else [x[1], x[2], x[2]]  # a /2 bin: orifice sums as its laminar ones
            if not (op[1] == 0 or _mix_sums_ok(x[2], mix[1], mix[2])):
                raise ValueError(f"field 'open': its gain sums cannot come from one set of ticks, got {op!r:.60}")
            out.open_bin, out.open_n = int(op[0]), int(op[1])
            out.open_sum_h, out.open_sum_lg, out.open_sum_gg, out.open_sum_ratio = x[:4]
            out.open_sum_lo, out.open_sum_go, out.open_sum_oo = mix
        return out


_POINT_FIELDS = ("hour", "leak", "ratio", "ticks", "weight", "sum_lo", "sum_ao", "sum_oo")
_OPEN_FIELDS = ("bin", "ticks", "sum_h", "sum_lg", "sum_gg", "sum_ratio", "sum_lo", "sum_ao", "sum_oo")


def _mix_sums_ok(s_aa: float, s_ao: float, s_oo: float) -> bool:
    """Sums of a^2, a * o and o^2 over one set of ticks (gains never negative): not negative, and
    Cauchy-Schwarz (s_ao^2 <= s_aa * s_oo, to rounding), so every mix of the gains has a weight >= 0."""
    return s_aa >= 0 and s_ao >= 0 and s_oo >= 0 and s_ao * s_ao <= s_aa * s_oo * (1.0 + 1e-9)


def _reference(p: PrognosisParams) -> list[float]:
    """What a saved leakage is referred to: dp (bar), oil temperature (C), the oil's nu40 and nu100 (cSt)."""
    return [p.dp_ref_bar, p.temp_ref_c, p.oil.nu40_cst, p.oil.nu100_cst]


# The viscosity ratio is tabulated (every 0.25 K) and interpolated with + - * / only: the per-tick and
# array forms then give bit-identical gains on any platform (a transcendental ufunc need not round a
# lone value and an array's alike); the table's error is below 4e-5 relative above 10 C (2e-4 at -30 C).
_TEMP_LO_C, _TEMP_HI_C, _TEMP_STEP_C = -30.0, 150.0, 0.25


@functools.lru_cache(maxsize=8)
def _visc_table(oil: Oil, temp_ref_c: float) -> NDArray[np.float64]:
    t = _TEMP_LO_C + _TEMP_STEP_C * np.arange(round((_TEMP_HI_C - _TEMP_LO_C) / _TEMP_STEP_C) + 1)
    tab = float(oil.dynamic_viscosity_pa_s(temp_ref_c)) / oil.dynamic_viscosity_pa_s(t)
    tab.flags.writeable = False
    return tab


def _gains(
    p: PrognosisParams, dp_bar: NDArray[np.float64], temp_c: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A leak's flow at this point over its flow at the reference conditions, for the two laws of a
    leak: laminar, ``a = (dp / dp_ref) * (mu_ref / mu(T))`` (a worn gap; the simulator's wear law),
    and orifice, ``o = sqrt(dp / dp_ref)`` (a crack, a torn seal: turbulent, hardly viscous). A real
    leak is a mix of both. Temperatures outside -30 ... 150 C are taken at the nearer end; sqrt is
    correctly rounded, so a lone value and an array's agree."""
    tab = _visc_table(p.oil, p.temp_ref_c)
    x = (np.clip(temp_c, _TEMP_LO_C, _TEMP_HI_C) - _TEMP_LO_C) / _TEMP_STEP_C
    i = np.minimum(np.floor(x), len(tab) - 2).astype(np.int64)
    f = x - i
    visc = tab[i] + f * (tab[i + 1] - tab[i])
    rel = dp_bar / p.dp_ref_bar
    return rel * visc, np.sqrt(rel)


def count(x: Any) -> bool:
    """A non-negative int (not a bool)."""
    return integer(x) and x >= 0


def _add_in_order(start: float, xs: NDArray[np.float64]) -> float:
    """``start + xs[0] + xs[1] + ...`` one addition after the other (cumsum adds in order, sum pairwise)."""
    return float(np.cumsum(np.concatenate(([start], xs)))[-1])


def _thin(points: list[Point], keep: int) -> list[Point]:
    """Down to ``keep`` points by merging, in the older half, the adjacent pair of fewest ticks (the
    oldest of equals) into one (hour and ratio tick-weighted, the leakage by its least-squares weight,
    as one bin would have given it), again and again: the older stretch evens out at a coarser
    resolution, the recent one keeps its own."""
    pts = list(points)
    half = len(pts) // 2
    while len(pts) > keep and half >= 2:
        w = [pts[i][3] + pts[i + 1][3] for i in range(half - 1)]
        i = w.index(min(w))
        (h1, l1, r1, n1, g1, *m1), (h2, l2, r2, n2, g2, *m2) = pts[i], pts[i + 1]
        n, g = n1 + n2, g1 + g2
        lo, ao, oo = (x1 + x2 for x1, x2 in zip(m1, m2, strict=True))
        pts[i : i + 2] = [((h1 * n1 + h2 * n2) / n, (l1 * g1 + l2 * g2) / g, (r1 * n1 + r2 * n2) / n, n, g, lo, ao, oo)]
        half -= 1
    return pts


# -- the leak's law: laminar and orifice shares ----------------------------------------------------

_SHARES = tuple(i / 20 for i in range(21))  # the orifice share of the leak at reference conditions tried


@dataclass(frozen=True)
class _Mix:
    """The leak's law fitted on the history: the orifice share of ``y = W * ((1 - s) a + s o)`` (``W``
    the leakage at the reference conditions) whose referral the wear law fits best, the history
    referred by it, and ``factor`` (>= 1): how much higher than by the best share any share the data
    do not rule out reads the recent leakage. The end of life in l/min is divided by it: the level is
    uncertain by as much, and the early end of that is the one booked."""

    best: float
    factor: float
    leak: NDArray[np.float64]


def _refer_all(leak: NDArray[np.float64], sums: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Every point referred by every share of :data:`_SHARES` (rows), and its weight there (the
    least-squares ``W = sum(y g) / sum(g^2)`` of ``g = (1 - s) a + s o``, and ``sum(g^2)``)."""
    s = np.array(_SHARES)[:, None]
    s_aa, s_lo, s_ao, s_oo = (sums[:, j] for j in range(1, 5))
    s_la = leak * s_aa
    num = s_la + s * (s_lo - s_la)
    den = s_aa + 2.0 * s * (s_ao - s_aa) + s * s * (s_oo - 2.0 * s_ao + s_aa)
    den = np.maximum(den, 1e-300)  # Cauchy-Schwarz keeps it >= 0; rounding may reach 0 for a = o
    return num / den, den


def _mix(p: PrognosisParams, h: NDArray[np.float64], leak: NDArray[np.float64], sums: NDArray[np.float64]) -> _Mix:
    """The share of the leak that flows by the orifice law, from the history's own spread of pressure
    and oil temperature: referred by the right share, the leakage follows the wear law's curve in
    time; by a wrong one it swings with the operating point on top of it (a laminar leak referred as
    an orifice one follows the oil's viscosity, over the oil's whole cycle). Each share's referral is
    fitted by the wear law itself (the grid of :func:`_detect`), scaled to the laminar referral's
    recent level so that the squares compare, and the share whose fit leaves the least is the best.

    The squares are not judged about a local line in time: that is blind to a swing slower than its
    window (an oil cycle of a day) and sees a temperature sensor's steps instead (J1939's 1 C: the
    laminar referral jumps 3 % at each, the leak does not), and it ruled the laminar law out on the
    J1939 demo's laminar wear (best share 0.7-0.8; booked 1.0, its p50 read 14 h for 10 h left).

    A share is ruled out when its fit's excess over the best's exceeds ``mix_chi2`` times the best
    fit's residual variance (inflated for the residuals' lag-1 autocorrelation). ``factor``: the
    highest recent level (the last ``min_history_h``) of a share not ruled out over the best's."""
    W, _ = _refer_all(leak, sums)
    recent = h >= h[-1] - p.min_history_h
    wt = sums[recent, 0]
    level = W[:, recent] @ wt / float(wt.sum())
    rms = np.sqrt((W[:, recent] ** 2) @ wt / float(wt.sum()))
    Y = W * (rms[0] / np.where(rms > 0, rms, 1.0))[:, None]
    grid = _grid(p, h)
    n = len(h)
    Yc = Y - Y.mean(axis=1, keepdims=True)
    suy = Yc @ grid.basis.T - Yc.sum(axis=1, keepdims=True) * grid.u_mean
    gain = np.where(suy > 0, suy * suy / np.where(grid.suu > 0, grid.suu, np.inf), 0.0)
    cell = np.argmax(gain, axis=1)
    sse = np.maximum(np.einsum("ij,ij->i", Yc, Yc) - gain[np.arange(len(_SHARES)), cell], 0.0)
    best = int(np.argmin(sse))
    g = int(cell[best])
    c = float(suy[best, g] / grid.suu[g]) if gain[best, g] > 0 else 0.0
    resid = Yc[best] - c * (grid.basis[g] - grid.u_mean[g])
    s2 = max(float(sse[best]) / max(n - 4, 1), 1e-12) * _inflation(resid)
    ok = sse - sse[best] <= p.mix_chi2 * s2
    factor = float(np.max(np.where(ok, level, -np.inf)) / level[best]) if level[best] > 0 else 1.0
    return _Mix(_SHARES[best], max(factor, 1.0), W[best])


# -- the estimate -----------------------------------------------------------------------------------


def estimate(
    p: PrognosisParams,
    h: NDArray[np.float64],
    leak: NDArray[np.float64],
    ratio: NDArray[np.float64],
    sums: NDArray[np.float64] | None = None,
) -> Estimate:
    """The prognosis from a history (hours increasing): see the module's description. Two sides are
    tracked: the leakage growing (wear; the ratio falls to the low warning) and the ratio rising (a
    drifting displacement control; to the high warning). Where both trend, the one ending sooner.
    ``leak`` is referred by the laminar law; with ``sums`` (the points' ticks and gain sums, the
    fields of :data:`Point` from the fourth on) the law's orifice share is fitted first (:func:`_mix`)
    and the leakage referred by it."""
    n = len(h)
    if n < p.min_points + 2 or not h[-1] - h[0] >= p.min_history_h:
        return Estimate(at_h=float(h[-1]) if n else math.nan)
    T = float(h[-1])
    mix = _mix(p, h, leak, sums) if sums is not None else None
    if mix is not None:
        leak = mix.leak
    # the low side's relevance is also judged on the measured ratio's fall (100 - ratio, %)
    fall = 100.0 - np.asarray(ratio, dtype=np.float64)
    # relevant if a share of the leak's law the data do not rule out reads the rise at the floor: the
    # level is uncertain by as much (the end of life is booked on that side too)
    d_low = _detect(p, h, leak, _LEAK, fall, 1.0 if mix is None else mix.factor)
    # The high side follows the ratio above 100 %: flow a healthy drive cannot deliver, which a leak,
    # however it swings with the oil and the pressure, never gives (it only lowers the ratio). As the
    # share of displacement the motor lacks (100 - 10^4 / ratio, %), linear in a drifting control
    excess = _short_pct(ratio)
    d_high = _detect(p, h, excess, _RATIO)
    base = Estimate(
        at_h=T,
        rise_lpm=d_low.c,
        fall_pct=d_low.fall,
        t_stat=d_low.t_stat,
        onset_h=d_low.onset_h,
        shape_k=d_low.shape_k,
        noise_lpm=d_low.sigma,
        rise_pct=d_high.c,
        t_stat_high=d_high.t_stat,
    )
    sides = []
    if d_low.trend:
        warn, eol = _leak_thresholds(p, leak, ratio)
        if mix is not None and p.eol_kind == "leak_lpm":  # a ratio's leakage moves with the referral
            eol /= mix.factor
        sides.append((LOW, d_low, _track_hours(p, h, leak, d_low, (warn, eol), _LEAK, fall)))
    if d_high.trend:
        ys = (float(_short_pct(np.array(p.high_pct))), float(_short_pct(np.array(p.eol_high_pct))))
        sides.append((HIGH, d_high, _track_hours(p, h, excess, d_high, ys, _RATIO)))
    if not sides:
        return base
    side, d, (q_warn, q_eol) = min(sides, key=lambda s: _sooner(s[2][1]))
    state = IMMINENT if q_eol[0] <= p.imminent_h else TREND
    onset = {"onset_h": d.onset_h, "shape_k": d.shape_k}
    return replace(base, state=state, to_warning_h=q_warn, to_eol_h=q_eol, direction=side, **onset)


def _short_pct(ratio_pct: NDArray[np.float64]) -> NDArray[np.float64]:
    """The share of its displacement (%) a motor turning at ``ratio_pct`` of the predicted speed lacks;
    0 at or below 100 %."""
    return 100.0 - 1e4 / np.maximum(ratio_pct, 100.0)


def _sooner(q: Triple) -> float:
    return math.inf if math.isnan(q[1]) else q[1]


def _track_hours(
    p: PrognosisParams,
    h: NDArray[np.float64],
    y: NDArray[np.float64],
    d: _Detected,
    ys: tuple[float, float],
    track: _Track,
    fall: NDArray[np.float64] | None = None,
) -> tuple[Triple, Triple]:
    """Hours (p10, p50, p90) until a trending side reaches its warning and its end of life, ``ys``.
    Pooled with the estimates of the last few hours (each less the hours since): one taken on a warm
    or a cold stretch of the oil's cycle no longer decides alone. Near the end the pool shrinks (to a
    quarter of the hours left): older estimates lag an accelerating wear."""
    T = float(h[-1])
    tw, te = _draw_hours(p, d, h, y, ys, track, p.seed)
    tw, te = _book_hindcast(p, _hindcast(p, h, y, d, track, fall), tw, te)
    warns, eols = [tw], [te]
    pool_h = min(p.pool_h, 0.25 * float(np.median(te)))
    for i, lag in enumerate(np.arange(p.pool_every_h, pool_h + 1e-9, p.pool_every_h).tolist(), start=1):
        m = int(np.searchsorted(h, T - lag, side="right"))
        if m < p.min_points + 2:
            break
        di = _detect(p, h[:m], y[:m], track, None if fall is None else fall[:m])
        if not di.trend:
            continue
        tw, te = _draw_hours(p, di, h[:m], y[:m], ys, track, p.seed + i)
        since = T - float(h[m - 1])
        warns.append(np.where(tw < _NEVER_H, np.maximum(tw - since, 0.0), tw))
        eols.append(np.where(te < _NEVER_H, np.maximum(te - since, 0.0), te))
    q_warn, q_eol = _quantiles(np.concatenate(warns)), _quantiles(np.concatenate(eols))
    if track.monotone and p.first_reached:
        env = _first_reached_hours(p, h, y, ys, track)
        if env is not None:  # each quantile the earlier of the two readings: late is the costly side
            q_warn, q_eol = _earlier(q_warn, env[0]), _earlier(q_eol, env[1])
    return q_warn, q_eol


def _book_hindcast(
    p: PrognosisParams, late: float, tw: NDArray[np.float64], te: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The drawn hours spread by the hindcast's factor (a lognormal of ``|ln late|``) and, where the
    law ran slow (``late > 1``), divided by it."""
    if late == 1.0:
        return tw, te
    rng = np.random.default_rng(p.seed - 1)
    scale = np.exp(rng.normal(0.0, abs(math.log(late)), len(tw))) / max(late, 1.0)
    return np.where(tw < _NEVER_H, tw * scale, tw), np.where(te < _NEVER_H, te * scale, te)


def _earlier(a: Triple, b: Triple) -> Triple:
    """Quantile by quantile the earlier of two estimates (NaN, no threshold, in either: ``a``)."""
    if any(math.isnan(x) for x in a + b):
        return a
    return (min(a[0], b[0]), min(a[1], b[1]), min(a[2], b[2]))


_HELD_POINTS = 4  # a level held for this many points (2 h at the default bin) is a corner
_CORNERS_MIN = 2  # ... and the curve is read through the corners once there are this many above the first level


def _first_reached_hours(
    p: PrognosisParams,
    h: NDArray[np.float64],
    y: NDArray[np.float64],
    ys: tuple[float, float],
    track: _Track,
) -> tuple[Triple, Triple] | None:
    """The hours to ``ys`` read the other way wear can be read: the law through the corners of the
    levels the history held (a level first reached at an hour, :func:`_first_reached`, and held for
    :data:`_HELD_POINTS` points or more), counted from the newest corner. Staged damage: the law
    passes through the steps' corners, and its hours count down while a level is held, where the law
    through the hours as they are sees a law standing still and promises more hours the longer the
    level is held. Points on the way between two levels (a bin that straddles a step) are left out:
    the curve passes above them. None where the history holds fewer than :data:`_CORNERS_MIN`
    corners above its first level (a smooth rise: none; one step: any onset and shape pass through
    it), or no rise."""
    T = float(h[-1])
    he = _first_reached(h, y, getattr(p, track.sigma_floor))
    corner, first, held = np.unique(he, return_index=True, return_counts=True)
    level = np.add.reduceat(y, first) / held
    # a corner is a level held, a relevant rise (the track's smallest) above the corner before it (a
    # slow rise's noise holds levels too, a few tenths apart), reached by a step: at least half of
    # that rise within the last two points before it (one may straddle the step). A smooth wear seen
    # through an oil cycle holds levels too, on the cycle's falling half, and rises between them over
    # its rising half: hours, not a bin
    keep_corner = np.zeros(len(corner), dtype=bool)
    keep_corner[0] = True
    last = float(level[0])
    for i in range(1, len(corner)):
        rise = float(level[i]) - last
        jump = float(level[i]) - float(y[max(int(first[i]) - 2, 0)])
        if held[i] >= _HELD_POINTS and rise >= getattr(p, track.min_rise) and jump >= 0.5 * rise:
            keep_corner[i] = True
            last = float(level[i])
    if np.count_nonzero(keep_corner[1:]) < _CORNERS_MIN:
        return None
    keep = np.isin(he, corner[keep_corner])
    # a step came between a corner's first point and the one before it: half way, not a bin late
    j = np.searchsorted(h, corner)
    mid = np.where(j > 0, 0.5 * (h[np.maximum(j - 1, 0)] + h[j]), corner)
    hk, yk = mid[np.searchsorted(corner, he[keep])], y[keep]
    de = _detect(p, hk, yk, track, onset_h=h)
    if not de.c > 0:
        return None
    tw, te = _draw_hours(p, de, hk, yk, ys, track, p.seed, True)
    shift = T - float(hk[-1])  # the curve's hours count from its newest corner
    tw = np.where(tw < _NEVER_H, np.maximum(tw - shift, 0.0), tw)
    te = np.where(te < _NEVER_H, np.maximum(te - shift, 0.0), te)
    return _quantiles(tw), _quantiles(te)


def _level_now(d: _Detected, y: NDArray[np.float64]) -> tuple[float, float]:
    """The best cell's level before the onset and its value at the history's last point."""
    b = float(np.mean(y - d.c * d.basis[d.g] - d.resid))
    return b, b + d.c


def _hindcast(
    p: PrognosisParams,
    h: NDArray[np.float64],
    y: NDArray[np.float64],
    d: _Detected,
    track: _Track,
    fall: NDArray[np.float64] | None = None,
) -> float:
    """How much slower than the truth the law ran over the last stretch: the hours the fit of the
    history as it stood then takes to today's level, over the hours it took (1: no hindcast, no
    earlier fit with a trend, or none that reaches today's level)."""
    out = [q for q in _hindcast_factors(p, h, y, d, track, fall) if q is not None]
    return float(max(out, key=lambda q: abs(math.log(q)))) if out else 1.0  # the one most wrong


def _hindcast_factors(
    p: PrognosisParams,
    h: NDArray[np.float64],
    y: NDArray[np.float64],
    d: _Detected,
    track: _Track,
    fall: NDArray[np.float64] | None = None,
) -> list[float | None]:
    """The hindcast's factors, newest fit first (an eighth, a quarter and half of the worn stretch
    back, at least ``hindcast_min_h``; None where there is none)."""
    if p.hindcast_share <= 0:
        return []
    T = float(h[-1])
    _, y_now = _level_now(d, y)
    out: list[float | None] = []
    for share in (0.5 * p.hindcast_share, p.hindcast_share, 2.0 * p.hindcast_share):
        out.append(None)
        lag = max(p.hindcast_min_h, share * (T - d.onset_h))
        m = int(np.searchsorted(h, T - lag, side="right"))
        if m < p.min_points + 2 or not h[m - 1] - h[0] >= p.min_history_h:
            continue
        old = _detect(p, h[:m], y[:m], track, None if fall is None else fall[:m])
        if not (old.trend and old.c >= getattr(p, track.hindcast_min_rise)):
            continue
        b_old, _ = _level_now(old, y[:m])
        took = T - float(h[m - 1])
        t = _hours_to(y_now, np.array([b_old]), np.array([old.c]), np.array([old.onset_h]), np.array([old.shape_k]),
                      float(h[m - 1]))[0]  # fmt: skip
        if 0.0 < t < _NEVER_H and took > 0:
            out[-1] = min(max(t / took, 0.1), 10.0)
    return out


@dataclass(frozen=True)
class _Track:
    """What a side's values are: the smallest rise reported, the noise assumed at least."""

    min_rise: str  # the PrognosisParams field
    sigma_floor: str
    hindcast_min_rise: str  # ... the smallest rise of a fit the hindcast asks
    monotone: bool = False  # the value never falls back (wear does not heal): hours by the first-reached hours


_LEAK = _Track("min_rise_lpm", "sigma_floor_lpm", "hindcast_min_rise_lpm", True)  # the leakage at reference, l/min
_RATIO = _Track("min_rise_pct", "sigma_floor_pct", "min_rise_pct")  # the ratio, %


def _first_reached(h: NDArray[np.float64], y: NDArray[np.float64], floor: float) -> NDArray[np.float64]:
    """Each point's hour moved back to the first hour at which the history's non-decreasing
    least-squares fit (isotonic regression, pool-adjacent-violators) came within two noise spreads
    of that point's level: wear does not heal, and a level held is a level reached. Staged damage (a
    flat stretch after each step) puts a flat stretch's points at its step: the curve through the
    steps' corners, which the law follows, where the flat points pull a fit of the hours as they are
    towards a law standing still (its hours grow while the next step nears). On a smooth rise the
    hours move earlier by the time the rise takes for two spreads (a fraction of an hour near the
    end): the curve as if two spreads higher, the early side. The spread: successive differences'
    median (a step or the law's rise hardly moves it), at least ``floor``."""
    starts: list[int] = []
    sums: list[float] = []
    counts: list[int] = []
    for i, v in enumerate(y.tolist()):
        starts.append(i)
        sums.append(v)
        counts.append(1)
        # pool while the block before is not below this one (means compared by cross products)
        while len(sums) > 1 and sums[-2] * counts[-1] >= sums[-1] * counts[-2]:
            s, c = sums.pop(), counts.pop()
            starts.pop()
            sums[-1] += s
            counts[-1] += c
    iso = np.repeat(np.array(sums) / np.array(counts, dtype=np.float64), np.array(counts, dtype=np.int64))
    # median |difference| of two points of spread sigma: 0.954 sigma
    sigma = max(float(np.median(np.abs(np.diff(y)))) / 0.954 if len(y) > 1 else 0.0, floor)
    first = np.searchsorted(iso, iso - 2.0 * sigma, side="left")
    return np.ascontiguousarray(h[first], dtype=np.float64)


@dataclass(frozen=True)
class _Detected:
    """The least-squares fit of the grid's best cell and whether its rise is a trend."""

    trend: bool
    c: float
    t_stat: float
    onset_h: float
    shape_k: float
    sigma: float
    g: int
    t0s: tuple[float, ...]
    ks: tuple[float, ...]
    basis: NDArray[np.float64]
    resid: NDArray[np.float64]
    fall: float = math.nan  # the measured ratio's fall over the same cell (%; NaN: not judged)


def _detect(
    p: PrognosisParams,
    h: NDArray[np.float64],
    y: NDArray[np.float64],
    track: _Track,
    fall: NDArray[np.float64] | None = None,
    rise_scale: float = 1.0,
    onset_h: NDArray[np.float64] | None = None,
) -> _Detected:
    """The grid's best cell for ``y`` and whether it is a trend: significant (``t_min``), at least
    ``min_points`` long, and relevant (its rise times ``rise_scale`` at least the track's smallest
    rise; with ``fall``, the ratio's deficit, also the measured ratio's fall fitted over the same
    onset and shape at least ``min_fall_pct``). No gate in units of the points' own spread: that
    spread depends on how densely the logger samples (ticks per bin) and on the referral's gain at
    the machine's duty, not on the wear, and the significance already weighs the rise against it."""
    n = len(h)
    grid = _grid(p, h, onset_h)
    t0s, ks, basis = grid.t0s, grid.ks, grid.basis
    f = _fit_unweighted(grid, y)
    g = int(np.argmin(f.sse))
    c = float(f.c[g])
    resid = y - (f.b[g] + c * basis[g])
    sigma = float(np.sqrt(f.sse[g] / max(n - 4, 1)))
    se = sigma * math.sqrt(_inflation(resid) / f.suu[g]) if f.suu[g] > 0 else math.inf
    t_stat = c / se if se > 0 else (math.inf if c > 0 else 0.0)
    # a rise shorter than min_points fits a fresh ramp as it is (the grid reaches closer: an older
    # onset forced on it would bend the curve and cut the hours short), but is not reported yet
    long_enough = t0s[g] <= float(h[n - p.min_points])
    trend = c > 0 and long_enough and t_stat >= p.t_min and c * rise_scale >= getattr(p, track.min_rise)
    fell = math.nan
    if fall is not None:
        # the same cell's least-squares rise of the ratio's deficit (its suu, the basis' moments, are
        # the grid's: one product)
        fc = fall - float(fall @ np.ones(n)) / n
        fell = float(basis[g] @ fc - grid.u_mean[g] * float(fc.sum())) / f.suu[g] if f.suu[g] > 0 else 0.0
        trend = trend and fell >= p.min_fall_pct
    return _Detected(trend, c, t_stat, t0s[g], ks[g], sigma, g, t0s, ks, basis, resid, fell)


def _draw_hours(
    p: PrognosisParams,
    d: _Detected,
    h: NDArray[np.float64],
    y: NDArray[np.float64],
    ys: tuple[float, float],
    track: _Track,
    seed: int,
    corners: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Hours from the last point until each drawn curve reaches each of ``ys`` (with the model's
    relative error). The fit weighs each point by its noise: a floor (as before the onset) plus a
    share of the wear leakage, which swings with the oil's viscosity and the duty's pressure.
    ``corners``: the hours are corners of levels held (:func:`_first_reached_hours`), each known to a
    bin, and the onset is drawn by :func:`_onset_prior`."""
    n, T = len(h), float(h[-1])
    before = d.basis[d.g] == 0.0
    floor = float(np.sqrt(np.mean(d.resid[before] ** 2))) if np.count_nonzero(before) >= 4 else 0.0
    floor = max(floor, getattr(p, track.sigma_floor))
    # The share of the wear leakage the points scatter by on top of the floor, from the worn stretch's
    # residuals (referred to reference conditions little is left of the oil's swing), at most
    # level_rel. From successive differences: a smooth misfit of the law is no scatter, and taken
    # for one it would let the newest points, which decide the extrapolation, count little.
    u = d.c * d.basis[d.g]
    worn = np.flatnonzero(u > 0.25 * d.c)
    rel2 = 0.0
    if len(worn) >= 4:
        scatter2 = 0.5 * float(np.mean(np.diff(d.resid[worn]) ** 2))
        rel2 = max(scatter2 - floor**2, 0.0) / float(np.mean(u[worn] ** 2))
    w = 1.0 / (floor**2 + min(rel2, p.level_rel**2) * u**2)
    f = _fit(d.basis, y, w)
    gw = int(np.argmin(f.sse))
    resid_w = (y - (f.b[gw] + f.c[gw] * d.basis[gw])) * np.sqrt(w)
    # a history the law fits exactly (no scatter at all) would make every weight 0 / 0: a thousandth
    # of the assumed noise floor at least
    s2 = max(float(f.sse[gw]) / max(n - 4, 1) * _inflation(resid_w), _S2_MIN)
    if corners:
        # first-reached hours are a step's to within a bin (the bin that straddles it, the one after):
        # a corner's level is uncertain by the curve's rise over that much time, however flat the
        # steps are (else the fit's least misfit by a hair picks one onset and shape of those that
        # pass through the corners alike)
        slope = float(f.c[gw]) * float(d.ks[gw]) / max(T - float(d.t0s[gw]), p.bin_h)
        s2 = max(s2, (slope * p.bin_h) ** 2 / 12.0 * float(np.mean(w)))
    rng = np.random.default_rng(seed)
    cell, bs, cs = _draws(p, f, s2, rng, _onset_prior(d.t0s, T) if corners else None)
    t0a, ka = np.array(d.t0s)[cell], np.array(d.ks)[cell]
    spread = np.exp(rng.normal(0.0, p.model_rel, len(cell)))
    out = []
    for target in ys:
        t = _hours_to(target, bs, cs, t0a, ka, T)
        out.append(np.where(t < _NEVER_H, t * spread, t))
    return out[0], out[1]


@dataclass(frozen=True)
class _Fits:
    """Least squares of ``y = b + c * basis[g]`` in every cell ``g`` of the grid (``c >= 0``)."""

    b: NDArray[np.float64]
    c: NDArray[np.float64]
    sse: NDArray[np.float64]  # residual sum of squares
    suu: NDArray[np.float64]  # the basis' sum of squares about its mean: var(c) = sigma^2 / suu
    u_mean: NDArray[np.float64]
    y_mean: float
    w_sum: float  # var(level at the basis' mean) = sigma^2 / w_sum


_NEWEST_ONSET_POINTS = 4  # the shortest rise on the grid (2 h at the default bin)


@dataclass(frozen=True)
class _Grid:
    """Onsets x shapes: each cell's basis row, and the parts of its unweighted fit that depend on the
    basis alone (read-only, cached: every estimate fits the same grid at least twice)."""

    t0s: tuple[float, ...]
    ks: tuple[float, ...]
    basis: NDArray[np.float64]
    u_mean: NDArray[np.float64]  # each row's mean
    suu: NDArray[np.float64]  # each row's sum of squares about its mean


def _grid(p: PrognosisParams, h: NDArray[np.float64], onset_h: NDArray[np.float64] | None = None) -> _Grid:
    """Onsets x shapes, and each cell's basis ((h - t0) / (T - t0))^k, 0 before the onset (read-only:
    an estimate fits both sides over the same hours, and the grid is their larger share of the work).
    ``onset_h``: the onsets are chosen on these hours (the history's own, where ``h`` are the hours
    each level was first reached, :func:`_first_reached`: hours held by many points would crowd the
    onsets onto a few), those not before ``h``'s last left out."""
    h = np.ascontiguousarray(h, dtype=np.float64)
    on = None if onset_h is None else np.ascontiguousarray(onset_h, dtype=np.float64).tobytes()
    return _grid_of(h.tobytes(), p.min_points, p.onsets, p.onset_ratio, on)


@functools.lru_cache(maxsize=4)
def _grid_of(h_bytes: bytes, min_points: int, onsets: int, onset_ratio: float, onset_bytes: bytes | None) -> _Grid:
    h = np.frombuffer(h_bytes, dtype=np.float64)
    n, T = len(h), float(h[-1])
    if onset_bytes is None:
        idx = _onsets(h, min_points, onsets, onset_ratio)
        t0_h = [float(h[i]) for i in idx]
    else:
        oh = np.frombuffer(onset_bytes, dtype=np.float64)
        t0_h = [x for x in dict.fromkeys(oh[_onsets(oh, min_points, onsets, onset_ratio)].tolist()) if x < T]
    m = len(_SHAPES)
    t0s = tuple(np.repeat(np.array(t0_h), m).tolist())
    ks = _SHAPES * len(t0_h)
    basis = np.zeros((len(t0_h) * m, n))
    u_mean, suu = np.empty(len(t0_h) * m), np.empty(len(t0_h) * m)
    for j, t0 in enumerate(t0_h):
        s = np.clip((h - t0) / max(T - t0, 1e-9), 0.0, 1.0)
        # only from the first point past the onset (0 ** k is 0 before it, and most onsets are recent);
        # s ** k as exp(k ln s): one logarithm per point for all shapes (a power costs 3-4 times an
        # exponential), within an ulp or two of the power
        lo = int(np.argmax(s > 0.0))
        rows = slice(j * m, (j + 1) * m)
        part = np.exp(np.multiply.outer(_SHAPE_ARRAY, np.log(s[lo:])))
        basis[rows, lo:] = part
        # each row's mean and sum of squares about it, the zeros before the onset counted at once
        mean = part.sum(axis=1) / n
        d = part - mean[:, None]
        u_mean[rows] = mean
        suu[rows] = np.einsum("ij,ij->i", d, d) + lo * mean * mean
    for a in (basis, u_mean, suu):
        a.flags.writeable = False
    return _Grid(t0s, ks, basis, u_mean, suu)


def _onsets(h: NDArray[np.float64], min_points: int, even: int, ratio: float) -> list[int]:
    """Indices of the onset candidates: ``even`` evenly spaced from the first point to ``min_points``
    before the last, and rises from :data:`_NEWEST_ONSET_POINTS` points long to the whole history,
    each ``ratio`` times the one before in hours, at the point nearest. Products and comparisons
    only: the same indices on every platform."""
    n, T = len(h), float(h[-1])
    newest, oldest = T - float(h[n - min(_NEWEST_ONSET_POINTS, min_points)]), T - float(h[0])
    out = set(np.round(np.linspace(0, n - min_points, even)).astype(np.int64).tolist())
    out.add(n - min(_NEWEST_ONSET_POINTS, min_points))
    d = newest * ratio
    while 0.0 < d < oldest:  # (hours that do not increase give no more onsets)
        i = int(np.searchsorted(h, T - d))  # the first point at or after T - d, or the one before it
        out.add(i - 1 if i > 0 and (T - d) - float(h[i - 1]) < float(h[i]) - (T - d) else i)
        d *= ratio
    return sorted(out)


def _fit(basis: NDArray[np.float64], y: NDArray[np.float64], w: NDArray[np.float64]) -> _Fits:
    """Every cell's weighted fit; a falling one is the flat one (``c = 0``): wear does not heal."""
    wsum = float(w.sum())
    u_mean = basis @ w / wsum
    uc = basis - u_mean[:, None]
    suu = (uc * uc) @ w
    y_mean = float(y @ w) / wsum
    yc = y - y_mean
    return _fitted(u_mean, suu, uc @ (w * yc), y_mean, float(yc @ (w * yc)), wsum)


def _fit_unweighted(grid: _Grid, y: NDArray[np.float64]) -> _Fits:
    """:func:`_fit` with every weight 1, the basis' own moments taken from the grid: one product with
    the basis instead of four passes over it (``suy``: the rows' sums about their means, as
    ``sum(u * yc) - u_mean * sum(yc)``)."""
    n = len(y)
    y_mean = float(y @ np.ones(n)) / n
    yc = y - y_mean
    suy = grid.basis @ yc - grid.u_mean * float(yc.sum())
    return _fitted(grid.u_mean, grid.suu, suy, y_mean, float(yc @ yc), float(n))


def _fitted(
    u_mean: NDArray[np.float64],
    suu: NDArray[np.float64],
    suy: NDArray[np.float64],
    y_mean: float,
    syy: float,
    wsum: float,
) -> _Fits:
    c = np.where(suy > 0, suy / np.where(suu > 0, suu, np.inf), 0.0)
    sse = syy - c * suy
    return _Fits(y_mean - c * u_mean, c, np.maximum(sse, 0.0), suu, u_mean, y_mean, wsum)


def _inflation(r: NDArray[np.float64]) -> float:
    """(1 + rho) / (1 - rho) for the residuals' lag-1 autocorrelation rho (in [0, 0.9]): how much
    less a correlated point tells than an independent one."""
    d = r - r.mean()
    den = float(d @ d)
    rho = float(d[1:] @ d[:-1]) / den if den > 0 else 0.0
    rho = min(max(rho, 0.0), 0.9)
    return (1 + rho) / (1 - rho)


_S2_MIN = 1e-6  # the weighted residual variance at least (weights are 1 / noise^2: 1 is the floor's)


def _onset_prior(t0s: tuple[float, ...], T: float) -> NDArray[np.float64]:
    """Per cell, a prior weight for its onset where the data cannot place it (a fit through a few
    corners of staged damage: every onset passes them with a shape of its own, the earlier the
    steeper): the hours the onset stands for (half the way to the onsets either side; the grid's
    onsets crowd towards the newest hours, and counting cells would favour a recent onset, a low
    shape, long hours), times the rise's length ``T - t0``: asymmetric on purpose, the earlier
    onsets, whose steeper curves end sooner, weigh more."""
    t0 = np.array(t0s)
    u = np.unique(t0)
    if len(u) < 2:
        return np.ones(len(t0))
    edges = np.concatenate(([u[0]], 0.5 * (u[1:] + u[:-1]), [u[-1]]))
    return np.diff(edges)[np.searchsorted(u, t0)] * np.maximum(T - t0, 0.0)


def _draws(
    p: PrognosisParams, f: _Fits, s2: float, rng: np.random.Generator, prior: NDArray[np.float64] | None = None
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Curves drawn from the fit's posterior: a cell (onset and shape) by its likelihood
    exp(-(SSE - SSE_min) / 2 s2), then its level and rise from their normal distributions (flat
    priors; level at the basis' mean and rise are independent). The onset and shape the data do not
    tell apart are all drawn: that is most of the uncertainty of an extrapolation."""
    logw = -(f.sse - f.sse.min()) / (2.0 * s2)
    w = np.exp(logw - logw.max())
    if prior is not None:
        w = w * prior
    w[f.c <= 0] = 0.0
    cell = rng.choice(len(w), size=p.draws, p=w / w.sum())
    level = f.y_mean + rng.normal(0.0, math.sqrt(s2 / f.w_sum), p.draws)
    cs = f.c[cell] + rng.normal(0.0, 1.0, p.draws) * np.sqrt(s2 / f.suu[cell])
    return cell, level - cs * f.u_mean[cell], cs


def _leak_thresholds(p: PrognosisParams, leak: NDArray[np.float64], ratio: NDArray[np.float64]) -> tuple[float, float]:
    """The low warning and end of life as extra leakage (l/min): ratios through the line of the
    deficit on the leakage (NaN where that line does not rise)."""
    d = 100.0 - ratio
    lc = leak - leak.mean()
    var = float(lc @ lc)
    gain = float(lc @ (d - d.mean())) / var if var > 0 else 0.0
    icpt = float(d.mean()) - gain * float(leak.mean())

    def from_ratio(pct: float) -> float:
        return (100.0 - pct - icpt) / gain if gain > 0 else math.nan

    eol = p.eol_value if p.eol_kind == "leak_lpm" else from_ratio(p.eol_value)
    return from_ratio(p.low_pct), eol


def _hours_to(
    y: float,
    b: NDArray[np.float64],
    c: NDArray[np.float64],
    t0: NDArray[np.float64],
    k: NDArray[np.float64],
    T: float,
) -> NDArray[np.float64]:
    """Per drawn curve, operating hours from ``T`` until it reaches ``y`` (0: reached already)."""
    if not math.isfinite(y):
        return np.full(len(b), math.nan)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        frac = (y - b) / c  # the curve's value at T is b + c
        t = t0 + (T - t0) * np.power(np.maximum(frac, 0.0), 1.0 / k) - T
    t = np.where(c > 0, t, _NEVER_H)
    return np.clip(np.nan_to_num(t, nan=_NEVER_H, posinf=_NEVER_H), 0.0, _NEVER_H)


def _quantiles(t: NDArray[np.float64]) -> Triple:
    if not len(t) or np.isnan(t).any():
        return _NAN3
    q = np.quantile(t, (0.1, 0.5, 0.9))
    a, b, c = (math.inf if x >= _NEVER_H else float(x) for x in q.tolist())
    return (a, b, c)


# -- the stage on the evaluated ticks ------------------------------------------------------------------

# A tick's prognosis state and direction (the CAN signals' values): 0 where no prognosis is
# configured, and the direction 0 without a trend
STATE_CODES = {NONE: 1, TREND: 2, IMMINENT: 3}
DIRECTION_CODES = {"": 0, LOW: 1, HIGH: 2}
FIELDS = (
    "prognosis_state",
    "prognosis_direction",
    "prognosis_to_warning_h",
    "prognosis_to_eol_p10_h",
    "prognosis_to_eol_p50_h",
    "prognosis_to_eol_p90_h",
)


class Stage:
    """The prognosis at every tick: the evaluated ticks' rows wait in a list and go into the history,
    and the estimate is made, at the first tick of each ``every_h`` of operating hours (the same ticks
    in both forms); between estimates the hours count down. One tick at a time (:meth:`tick`) or a
    stretch of ticks (:meth:`run_columns`), the same state and fields."""

    def __init__(self, params: PrognosisParams, saved: Any = None) -> None:
        self.params = params
        self.every_h = params.estimate_every_h
        self.note = ""  # why a saved history was not continued
        self.history = Prognosis(params)
        self.clock = OperatingClock(params.max_gap_h * 3600.0)
        if saved is not None:
            try:
                self.history = Prognosis.from_dict(saved, params)
                self.note = self.history.restarted
                try:
                    self.clock.operating_s, self.clock.last_t_s = _clock_from(saved, self.history)
                except ValueError as exc:  # the history is good: its clock goes on from its newest hour
                    self.clock.operating_s, self.clock.last_t_s = _clock_from({}, self.history)
                    self.note = f"the saved operating clock could not be used ({exc}): it goes on from the history"
            except ValueError as exc:  # the rest of the state is good: a new history, said
                self.note = f"the saved prognosis history could not be used ({exc}): a new history begins"
        self.block: int | None = None
        self._rows: list[tuple[float, float, float, float, float]] = []
        self.est = self.history.estimate() if self.history.points else Estimate()

    def hours(self, t_run_s: float, has_input: bool = True) -> float:
        """The operating hour of a tick at ``t_run_s`` (:mod:`cmcan.monitor.operating`)."""
        return self.clock.hours(t_run_s, has_input)

    def hours_columns(self, t_run_s: NDArray[np.float64], has_input: NDArray[np.bool_]) -> NDArray[np.float64]:
        """:meth:`hours` at every tick of a stretch: the same additions in the same order."""
        return self.clock.seconds_columns(t_run_s, has_input) / 3600.0

    def tick(self, hour: float) -> None:
        """The start of a tick at operating ``hour``: at a new block of hours the rows so far go into
        the history and a new estimate is made."""
        blk = math.floor(hour / self.every_h) if math.isfinite(hour) else self.block
        if blk == self.block or blk is None:
            return
        first = self.block is None
        self.block = blk
        if not first:
            self.fold()
            self.est = self.history.estimate()

    def add(self, hour: float, leak_lpm: float, ratio_pct: float, dp_bar: float, temp_c: float) -> None:
        """An evaluated tick's row (its raw leakage and ratio, its dp and oil temperature)."""
        self._rows.append((hour, leak_lpm, ratio_pct, dp_bar, temp_c))

    def fold(self) -> None:
        if self._rows:
            a = np.array(self._rows, dtype=np.float64)
            self._rows = []
            self.history.add_columns(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], np.ones(len(a), dtype=bool))

    def restart(self) -> None:
        """A replaced unit or a new reference: the wear so far no longer applies."""
        self._rows = []
        self.history.restart()
        self.est = Estimate()

    def fields(self, hour: float) -> dict[str, Any]:
        """A tick's fields: the state and the hours of the last estimate, less the hours since."""
        e = self.est
        since = hour - e.at_h if math.isfinite(e.at_h) else 0.0
        return {
            "prognosis_state": STATE_CODES[e.state],
            "prognosis_direction": DIRECTION_CODES[e.direction],
            "prognosis_to_warning_h": _left(e.to_warning_h[1], since),
            "prognosis_to_eol_p10_h": _left(e.to_eol_h[0], since),
            "prognosis_to_eol_p50_h": _left(e.to_eol_h[1], since),
            "prognosis_to_eol_p90_h": _left(e.to_eol_h[2], since),
        }

    def run_columns(
        self,
        hours: NDArray[np.float64],
        evaluated: NDArray[np.bool_],
        leak_lpm: NDArray[np.float64],
        ratio_pct: NDArray[np.float64],
        dp_bar: NDArray[np.float64],
        temp_c: NDArray[np.float64],
    ) -> dict[str, NDArray[Any]]:
        """:meth:`tick`, :meth:`add` and :meth:`fields` at every tick of a stretch (``leak_lpm`` and
        ``ratio_pct`` at every tick, used where ``evaluated``)."""
        n = len(hours)
        fin = np.isfinite(hours)
        blk = np.floor(np.where(fin, hours, 0.0) / self.every_h)
        # as tick() one after another: a tick without a finite hour stays in the block before it
        have = np.flatnonzero(fin)
        eff = np.full(n, np.nan if self.block is None else float(self.block))
        if len(have):
            fill = np.maximum.accumulate(np.where(fin, np.arange(n), -1))
            eff = np.where(fill >= 0, blk[np.maximum(fill, 0)], eff)
        before = np.concatenate([[np.nan if self.block is None else float(self.block)], eff[:-1]])
        change = np.flatnonzero(~np.isnan(eff) & (eff != before))
        out: dict[str, NDArray[Any]] = {name: np.empty(n) for name in FIELDS}
        out["prognosis_state"] = np.empty(n, dtype=np.int8)
        out["prognosis_direction"] = np.empty(n, dtype=np.int8)
        cols = (hours, leak_lpm, ratio_pct, dp_bar, temp_c)
        starts = set(change.tolist())
        edges = [0, *sorted(starts - {0}), n]
        for a, z in itertools.pairwise(edges):
            if a in starts:
                first = self.block is None
                self.block = int(eff[a])
                if not first:
                    self.fold()
                    self.est = self.history.estimate()
            if z <= a:
                continue
            sel = np.flatnonzero(evaluated[a:z]) + a
            if len(sel):
                self._rows.extend(zip(*(v[sel].tolist() for v in cols), strict=True))
            e = self.est
            since = hours[a:z] - e.at_h if math.isfinite(e.at_h) else np.zeros(z - a)
            out["prognosis_state"][a:z] = STATE_CODES[e.state]
            out["prognosis_direction"][a:z] = DIRECTION_CODES[e.direction]
            for name, v in zip(FIELDS[2:], (e.to_warning_h[1], *e.to_eol_h), strict=True):
                out[name][a:z] = _left_columns(v, since)
        return out

    def to_dict(self) -> dict[str, Any]:
        self.fold()
        return {**self.history.to_dict(), "clock": self.clock.to_dict()}


def _clock_from(saved: dict[str, Any], history: Prognosis) -> tuple[float, float]:
    """The saved operating clock; a history saved without one goes on from its newest hour."""
    c = saved.get("clock")
    if c is None:
        return history.newest_h() * 3600.0, math.nan
    return OperatingClock.state_from(c, "clock")


def _left(hours: float, since: float) -> float:
    """Hours left of an estimate ``since`` hours ago (NaN: no estimate; inf: never)."""
    if math.isnan(hours) or math.isinf(hours):
        return hours
    return max(hours - since, 0.0)


def _left_columns(hours: float, since: NDArray[np.float64]) -> NDArray[np.float64]:
    if math.isnan(hours) or math.isinf(hours):
        return np.full(len(since), hours)
    return np.maximum(hours - since, 0.0)
