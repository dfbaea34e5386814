"""The monitor core: frames with timestamps in, output frames and a timeline out. No I/O, no clock.

``Monitor.feed`` takes one received frame; evaluation ticks fall on multiples of the evaluation
period in the frames' own time and are evaluated when the first frame after them arrives, so a log
replayed gives exactly the frames the daemon sends. After a gap in the data (the machine was off, or
a burst-sampled log) the ticks inside the gap are skipped, as training skips them.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from operator import mul
from typing import Any, Protocol

from cmcan.monitor.gating import GATED_ROLES, TIME_EPS_S, Gate, GateLimits, gate_point
from cmcan.monitor.totals import HISTORY_MAX, Totals
from cmcan.monitor.warnings import Level, Reason, Thresholds, WarningMachine

LEVEL_NAMES = {Level.OK: "ok", Level.LOW: "low", Level.HIGH: "high", Level.FAULT: "fault"}
_OTHER, _HIGH, _LOW = 0, 1, 2
COUNTERS = (
    "frames_total",
    "accepted",
    "unknown_id",
    "bad_length",
    "out_of_range",
    "error_frame",
    "remote_frame",
    "late",
)


class Predictor(Protocol):
    def predict_one(
        self, pump_speed_rpm: float, pump_disp_cc: float, dp_bar: float, temp_c: float
    ) -> tuple[float, float]: ...


@dataclass(frozen=True)
class InputFrame:
    """How to read one input message: a decoder that returns each signal in its role's unit, or
    None when a value is outside its DBC range (an implausible frame), and the roles in order."""

    frame_id: int
    length: int
    decode: Callable[[bytes], tuple[float, ...] | None]
    roles: tuple[str, ...]


@dataclass(frozen=True)
class OutputFrame:
    timestamp_s: float
    frame_id: int
    data: bytes


@dataclass(frozen=True)
class Outputs:
    """Encoders of the three output messages (physical values in, payload out) and their ids."""

    ratio_id: int
    speed_id: int
    warning_id: int
    encode_ratio: Callable[[dict[str, float]], bytes]
    encode_speed: Callable[[dict[str, float]], bytes]
    encode_warning: Callable[[dict[str, float]], bytes]
    cm_every_ticks: int
    speed_every_ticks: int
    warning_every_ticks: int


@dataclass(frozen=True)
class MonitorParams:
    rate_hz: float
    limits: GateLimits
    max_age_s: dict[str, float]
    envelope: dict[str, tuple[float, float]] | None
    filter_samples: int
    filter_min_samples: int
    thresholds: Thresholds
    motor_disp_cc: float
    dp_from_high_low: bool


@dataclass
class Tick:
    """One evaluation: what the CM frames of this tick carry, plus the warning state."""

    t_s: float
    gate: Gate
    motor_speed_meas_rpm: float
    motor_speed_pred_rpm: float
    motor_speed_whitebox_rpm: float
    ratio_raw_pct: float
    ratio_filt_pct: float
    extra_leak_lpm: float
    filt_valid: bool
    level: Level
    reason: Reason
    time_below_s: float


class _Window:
    """Samples of one role: the trailing window for statistics, and the newest sample's time."""

    __slots__ = ("last_t", "ts", "vs")

    def __init__(self) -> None:
        self.ts: deque[float] = deque()
        self.vs: deque[float] = deque()
        self.last_t = -math.inf

    def add(self, t: float, v: float) -> None:
        self.ts.append(t)
        self.vs.append(v)
        if t > self.last_t:
            self.last_t = t

    def clear(self) -> None:
        self.ts.clear()
        self.vs.clear()
        self.last_t = -math.inf

    def stats(self, t_end: float, window_s: float) -> tuple[float, float, int]:
        ts, vs = self.ts, self.vs
        cut = t_end - window_s + TIME_EPS_S
        while ts and ts[0] <= cut:
            ts.popleft()
            vs.popleft()
        n = len(vs)
        if n == 0:
            return math.nan, math.nan, 0
        # Plain sums in C: for sensor magnitudes (< 1e5) the one-pass variance loses < 1e-8 absolute.
        mean = sum(vs) / n
        var = sum(map(mul, vs, vs)) / n - mean * mean
        return mean, math.sqrt(var) if var > 0.0 else 0.0, n


@dataclass
class Monitor:
    params: MonitorParams
    inputs: dict[int, InputFrame]
    model: Predictor
    outputs: Outputs
    totals: Totals = field(default_factory=Totals)
    keep_timeline: bool = False

    def __post_init__(self) -> None:
        p = self.params
        self.period = 1.0 / p.rate_hz
        self.max_gap_s = max(p.limits.window_s, 1.0)
        self.windows = {r: _Window() for r in GATED_ROLES}
        # Per input frame, per decoded value: the window it goes to, or what else it is.
        self._plans = {
            fid: tuple(
                (
                    self.windows.get(r),
                    _HIGH
                    if r == "high_pressure_bar" and p.dp_from_high_low
                    else _LOW
                    if r == "low_pressure_bar" and p.dp_from_high_low
                    else _OTHER,
                )
                for r in spec.roles
            )
            for fid, spec in self.inputs.items()
        }
        self._low: float | None = None
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.counters.update(ticks=0, evaluated=0, model_errors=0, time_resets=0)
        self._set_next(None)
        self.last_frame_t = -math.inf
        self.machine = WarningMachine(p.thresholds)
        self.machine.condition = {"ok": Level.OK, "low": Level.LOW, "high": Level.HIGH}[self.totals.condition]
        self.machine.condition_reason = {
            Level.OK: Reason.NONE,
            Level.LOW: Reason.RATIO_LOW,
            Level.HIGH: Reason.RATIO_HIGH,
        }[self.machine.condition]
        self.ring_ratio: deque[float] = deque(self.totals.filter_ratios[-p.filter_samples :], maxlen=p.filter_samples)
        self.ring_leak: deque[float] = deque(self.totals.filter_leaks[-p.filter_samples :], maxlen=p.filter_samples)
        self.alive = 0
        self.last_sent_warning: tuple[int, int] | None = None
        self.last_tick: Tick | None = None
        self.timeline: list[Tick] = []
        self.transitions_since_save = 0

    # -- frames in ---------------------------------------------------------------------------------

    def feed(
        self,
        t: float,
        frame_id: int,
        data: bytes,
        is_extended: bool = False,
        is_remote: bool = False,
        is_error: bool = False,
    ) -> list[OutputFrame]:
        """Take one received frame; returns the output frames of the ticks it completes."""
        c = self.counters
        c["frames_total"] += 1
        if is_error or is_remote or is_extended:
            c["error_frame" if is_error else "remote_frame" if is_remote else "unknown_id"] += 1
            return []
        spec = self.inputs.get(frame_id)
        if spec is None:
            c["unknown_id"] += 1
            return []
        if len(data) < spec.length:
            c["bad_length"] += 1
            return []
        out: list[OutputFrame] = []
        if not (self._late_t <= t <= self._due_t):  # a tick is due, or the frame is late (or NaN)
            ticks = self._time_step(t)
            if ticks is None:
                c["late"] += 1
                return []
            out = ticks
        values = spec.decode(data)
        if values is None:
            c["out_of_range"] += 1
            return out
        c["accepted"] += 1
        if self.next_k is None:
            self._set_next(math.floor(t / self.period) + 1)
        if t > self.last_frame_t:
            self.last_frame_t = t
        high = None
        for v, (win, kind) in zip(values, self._plans[frame_id], strict=True):
            if win is not None:
                win.ts.append(t)
                win.vs.append(v)
                if t > win.last_t:
                    win.last_t = t
            elif kind == _HIGH:
                high = v
            elif kind == _LOW:
                self._low = v
        if high is not None and self._low is not None:
            w = self.windows["dp_bar"]
            w.add(t, high - self._low)
        return out

    def _time_step(self, t: float) -> list[OutputFrame] | None:
        """Ticks due before ``t``, or None when the frame is too old to use."""
        if not math.isfinite(t):
            return None
        if self.next_k is None:
            return []
        if t < self._late_t:
            if t < self._late_t - 60.0:
                self._reset_time()  # time went back a long way: a new log, or a clock reset
                return []
            return None  # older than a tick already evaluated: cannot be used any more
        return self._ticks_before(t)

    def _set_next(self, k: int | None) -> None:
        self.next_k = k
        if k is None:
            self._due_t, self._late_t = math.inf, -math.inf
        else:
            self._due_t = k * self.period + TIME_EPS_S
            self._late_t = (k - 1) * self.period - TIME_EPS_S

    def advance(self, t: float) -> list[OutputFrame]:
        """Time passes without frames (the daemon's idle timer): evaluate up to ``t``."""
        if self.next_k is None or not math.isfinite(t):
            return []
        return self._ticks_before(t, idle=True)

    def flush(self) -> list[OutputFrame]:
        """Evaluate the ticks up to the last frame (end of a replayed log)."""
        if self.next_k is None:
            return []
        out = []
        k = self.next_k
        while k * self.period <= self.last_frame_t + TIME_EPS_S:
            out += self._evaluate(k)
            k += 1
        self._set_next(k)
        return out

    def _ticks_before(self, t: float, idle: bool = False) -> list[OutputFrame]:
        out: list[OutputFrame] = []
        assert self.next_k is not None
        if t - self.last_frame_t > self.max_gap_s:
            out += self.flush()  # finish the span that ended with the last frame
            k_last = math.ceil(t / self.period) - 1  # the last tick strictly before t
            if idle:
                if k_last >= self.next_k:  # keep broadcasting while the bus is silent: the newest tick
                    out += self._evaluate(k_last)
                    self._set_next(k_last + 1)
            else:
                self._set_next(math.floor(t / self.period) + 1)
            return out
        k = self.next_k
        while k * self.period < t - TIME_EPS_S:
            out += self._evaluate(k)
            k += 1
        self._set_next(k)
        return out

    def _reset_time(self) -> None:
        self.counters["time_resets"] += 1
        for w in self.windows.values():
            w.clear()
        self._low = None
        self._set_next(None)
        self.last_frame_t = -math.inf

    # -- evaluation --------------------------------------------------------------------------------

    def _evaluate(self, k: int) -> list[OutputFrame]:
        p = self.params
        t = k * self.period
        mean, std, count, age = {}, {}, {}, {}
        for role, w in self.windows.items():
            mean[role], std[role], count[role] = w.stats(t, p.limits.window_s)
            age[role] = t - w.last_t
        g = gate_point(mean, std, count, age, p.limits, p.max_age_s, p.envelope)
        meas = mean["motor_speed_rpm"] if count["motor_speed_rpm"] else 0.0
        pred = wb = raw = 0.0
        if g == Gate.EVALUATING:
            try:
                pred, wb = self.model.predict_one(
                    mean["pump_speed_rpm"], mean["pump_disp_cc"], mean["dp_bar"], mean["temp_c"]
                )
            except Exception:  # a model that fails must not take the daemon down
                pred = math.nan
            if not (math.isfinite(pred) and pred > 0.0):
                self.counters["model_errors"] += 1
                g = Gate.IMPLAUSIBLE_INPUT
                pred = wb = 0.0
            else:
                raw = meas / pred * 100.0
                self.ring_ratio.append(raw)
                self.ring_leak.append((pred - meas) * p.motor_disp_cc / 1000.0)
                self.counters["evaluated"] += 1
                self.totals.evaluated_s += self.period
        n = len(self.ring_ratio)
        filt_valid = n >= p.filter_min_samples
        filt = math.fsum(self.ring_ratio) / n if n else 0.0
        leak = math.fsum(self.ring_leak) / n if n else 0.0
        evaluated = g == Gate.EVALUATING
        m = self.machine
        cond_before, fault_before = m.condition, m.fault_reason
        for tr in m.step(t, self.period, g, filt if (filt_valid and evaluated) else None):
            self._record(tr.t_s, tr.level_from, tr.level_to, tr.reason, tr.ratio_pct)
        if m.condition != cond_before and m.condition in (Level.LOW, Level.HIGH):
            self.totals.warning_count += 1
        if fault_before == Reason.NONE and m.fault_reason != Reason.NONE:
            self.totals.fault_count += 1
        self.totals.condition = LEVEL_NAMES[m.condition]
        level, reason = self.machine.level, self.machine.reason
        self.totals.time_in_level_s[LEVEL_NAMES[level]] += self.period
        self.counters["ticks"] += 1
        tick = Tick(
            t,
            g,
            meas,
            pred,
            wb,
            raw if evaluated else 0.0,
            filt,
            leak,
            filt_valid,
            level,
            reason,
            self.machine.time_below_s,
        )
        self.last_tick = tick
        if self.keep_timeline:
            self.timeline.append(tick)
        return self._frames(k, tick)

    def _record(self, t: float, frm: Level, to: Level, reason: Reason, ratio: float | None) -> None:
        tot = self.totals
        tot.history.append(
            {
                "t_s": t,
                "from": LEVEL_NAMES[frm],
                "to": LEVEL_NAMES[to],
                "reason": reason.name.lower(),
                "ratio_filt_pct": ratio,
            }
        )
        del tot.history[:-HISTORY_MAX]
        self.transitions_since_save += 1

    def _frames(self, k: int, tick: Tick) -> list[OutputFrame]:
        o = self.outputs
        out = []
        evaluated = tick.gate == Gate.EVALUATING
        if k % o.cm_every_ticks == 0:
            out.append(
                OutputFrame(
                    tick.t_s,
                    o.ratio_id,
                    o.encode_ratio(
                        {
                            "cm_ratio_raw_pct": tick.ratio_raw_pct,
                            "cm_ratio_filt_pct": tick.ratio_filt_pct if tick.filt_valid else 0.0,
                            "extra_leakage_lpm": tick.extra_leak_lpm if tick.filt_valid else 0.0,
                            "cm_raw_valid": float(evaluated),
                            "cm_filt_valid": float(tick.filt_valid),
                            "cm_gate": float(int(tick.gate)),
                            "cm_alive_counter": float(self.alive),
                        }
                    ),
                )
            )
        if k % o.speed_every_ticks == 0:
            out.append(
                OutputFrame(
                    tick.t_s,
                    o.speed_id,
                    o.encode_speed(
                        {
                            "motor_speed_meas_rpm": tick.motor_speed_meas_rpm
                            if math.isfinite(tick.motor_speed_meas_rpm)
                            else 0.0,
                            "motor_speed_pred_rpm": tick.motor_speed_pred_rpm,
                            "motor_speed_whitebox_rpm": tick.motor_speed_whitebox_rpm,
                            "cm_speed_valid": float(evaluated),
                            "cm_alive_counter": float(self.alive),
                        }
                    ),
                )
            )
        if k % o.cm_every_ticks == 0:
            self.alive = (self.alive + 1) % 16
        state = (int(tick.level), int(tick.reason))
        if state != self.last_sent_warning or k % o.warning_every_ticks == 0:
            self.last_sent_warning = state
            out.append(
                OutputFrame(
                    tick.t_s,
                    o.warning_id,
                    o.encode_warning(
                        {
                            "warning_level": float(int(tick.level)),
                            "warning_reason": float(int(tick.reason)),
                            "time_below_threshold_s": float(int(tick.time_below_s)),
                            "warning_count": float(self.totals.warning_count % 65536),
                        }
                    ),
                )
            )
        return out

    # -- views -------------------------------------------------------------------------------------

    def save_totals(self) -> Totals:
        """The totals with the filter contents, ready to persist."""
        self.totals.filter_ratios = list(self.ring_ratio)
        self.totals.filter_leaks = list(self.ring_leak)
        self.totals.condition = LEVEL_NAMES[self.machine.condition]
        self.transitions_since_save = 0
        return self.totals

    def snapshot(self) -> dict[str, Any]:
        tk = self.last_tick
        return {
            "level": LEVEL_NAMES[self.machine.level],
            "reason": self.machine.reason.name.lower(),
            "ratio_filt_pct": tk.ratio_filt_pct if tk and tk.filt_valid else None,
            "gate": tk.gate.name.lower() if tk else None,
            "counters": dict(self.counters),
            "warning_count": self.totals.warning_count,
            "evaluated_h": self.totals.evaluated_s / 3600.0,
        }
