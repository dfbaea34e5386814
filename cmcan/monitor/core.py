"""The monitor core: frames with timestamps in, output frames and a timeline out. No I/O, no clock.

``Monitor.feed`` takes one received frame. It is matched to a mapped input message by its channel,
identifier and format (:mod:`cmcan.monitor.inputs`) and checked (:mod:`cmcan.monitor.health`); an
accepted frame updates the trailing windows of its roles (:mod:`cmcan.monitor.windows`). The tick
clock (:mod:`cmcan.monitor.clock`) says which evaluation ticks a frame completes; each tick gates the
operating point, asks the model for its prediction, updates the ratio filter and the warning machine,
and returns the CM frames due (:mod:`cmcan.monitor.payloads`) and, on a J1939 machine, DM1
(:mod:`cmcan.monitor.diagnostics`). The daemon and the replay drive this same object.

One tick, in order (:meth:`Monitor._evaluate`), each step a function of the windows and the state
the previous ticks left:

1. window statistics of every gated role at the tick's time; a role the machine holds constant
   (``MonitorParams.constants``) is that value, fresh, with no spread;
2. the gate (:func:`cmcan.monitor.gating.gate_point`) with the model's envelope: a verdict of
   ``EVALUATING`` or ``EXTRAPOLATED`` (outside the envelope) evaluates the point, any other names why
   not; an erratic input message (:func:`cmcan.monitor.health.tick`) makes it ``IMPLAUSIBLE_INPUT``;
3. for an evaluated point one model call; a prediction that is not a positive finite number within
   the output's plausible range (:func:`cmcan.monitor.gating.prediction_ok`) makes the tick
   ``MODEL_ERROR`` (counted in ``model_errors``; for ``fault_after_s`` it is a fault with reason
   ``model_error``);
4. raw ratio = measured / predicted * 100 and leakage = (predicted - measured) * ``lpm_per_unit``
   into the moving-average filter, extrapolated points included;
5. the warning machine steps with the gate and, when the point was evaluated and the filter is
   valid, the filtered ratio: extrapolated points may raise a warning, never clear one
   (:mod:`cmcan.monitor.warnings`);
6. the CM frames due at this tick (``cm_gate`` carries the verdict, so a receiver sees that a ratio
   came from an extrapolated point), and DM1 where configured.

Output order: every output frame carries its time (a tick's time, or later for the packets of a
J1939 transport session). ``feed(f)``, ``advance(t)`` and ``due(t)`` return, in order of time (equal
times in the order they were made), the output frames not returned before whose time is at most the
frame's time (``t``): the frames of the ticks evaluated and the transport packets that fell due.
``flush()`` returns the rest. A step back of the frames' time (the wall clock) first returns every
pending packet.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from cmcan.frame import Frame
from cmcan.monitor import health
from cmcan.monitor.clock import TickClock
from cmcan.monitor.diagnostics import Dm1Params, Dm1Producer
from cmcan.monitor.filter import RatioFilter
from cmcan.monitor.gating import EVALUATED, Gate, GateLimits, gate_point, prediction_ok
from cmcan.monitor.health import OK, OUT_OF_RANGE, REASONS, Stream
from cmcan.monitor.inputs import MEMO_MAX, Channels, InputMessage, Matcher
from cmcan.monitor.payloads import Outputs, Payloads
from cmcan.monitor.tick import LEVEL_NAMES, Tick
from cmcan.monitor.totals import HISTORY_MAX, Totals
from cmcan.monitor.warnings import Level, Reason, Thresholds, WarningMachine
from cmcan.monitor.windows import Affine, RoleWindow
from cmcan.roles import DP, HIGH_PRESSURE, LOW_PRESSURE, MODEL_INPUTS, gated_roles

COUNTERS = (
    "frames_total",
    "accepted",
    "unknown_id",
    "bad_length",
    "out_of_range",
    "error_frame",
    "remote_frame",
    "late",
    "unknown_channel",
    "bad_fd",
    "checksum",
    "counter_frozen",
    "counter_jump",
    "timeout",
)
# What each decoded value of an input frame does.
_WINDOW, _HIGH, _LOW, _IGNORED = 0, 1, 2, 3


class Predictor(Protocol):
    def predict_one(
        self, pump_speed_rpm: float, pump_disp_cc: float, dp_bar: float, temp_c: float
    ) -> tuple[float, float]: ...


@dataclass(frozen=True)
class DpFromHighLow:
    """dp = high - low, exact in integers: raw_dp = p * raw_high - q * raw_low (see
    :func:`cmcan.monitor.windows.commensurate`), taken at each high-pressure sample with the newest
    low-pressure sample."""

    p: int
    q: int


@dataclass(frozen=True)
class MonitorParams:
    rate_hz: float
    limits: GateLimits
    max_age_s: Mapping[str, float]
    envelope: Mapping[str, tuple[float, float]] | None
    filter_samples: int
    filter_min_samples: int
    thresholds: Thresholds
    lpm_per_unit: float  # l/min per unit of the output quantity: V_M / 1000 for motor speed, 1 for flow
    affine: Mapping[str, Affine]  # per gated role: its raw samples to the role's unit
    dp_from_high_low: DpFromHighLow | None = None
    # Model inputs the machine holds constant instead of measuring (role -> value in its unit).
    constants: Mapping[str, float] = field(default_factory=dict)

    @property
    def output_role(self) -> str:
        return self.limits.output_role


class _Input:
    """A mapped input message at run time: its spec, what each decoded value does, its health."""

    __slots__ = ("checked", "decode", "length", "plan", "spec", "stream")

    def __init__(self, spec: InputMessage, plan: tuple[tuple[RoleWindow | None, int], ...]) -> None:
        self.spec = spec
        self.length = spec.length
        self.decode = spec.decode
        self.plan = plan
        self.stream = Stream(spec.health)
        self.checked = spec.health.counter is not None or spec.health.checksum is not None


class _Channel:
    """A channel name as frames carry it: its configured channel (index -1: none), FD or not, and
    the input of each identifier seen on it so far (a cache of the pure matching function)."""

    __slots__ = ("ext", "fd", "index", "std")

    def __init__(self, index: int, fd: bool) -> None:
        self.index = index
        self.fd = fd
        self.std: dict[int, _Input | None] = {}  # by 11-bit identifier
        self.ext: dict[int, _Input | None] = {}  # by 29-bit identifier


_MISS = object()


@dataclass
class Monitor:
    params: MonitorParams
    inputs: Sequence[InputMessage]
    model: Predictor
    outputs: Outputs
    totals: Totals = field(default_factory=Totals)
    keep_timeline: bool = False
    channels: Channels = field(default_factory=Channels)
    dm1: Dm1Params | None = None

    def __post_init__(self) -> None:
        p = self.params
        self.period = 1.0 / p.rate_hz
        self.clock = TickClock(p.rate_hz, max_gap_s=max(p.limits.window_s, 1.0))
        self.windows = {r: RoleWindow() for r in gated_roles(p.output_role) if r not in p.constants}
        self._constants = [(r, float(p.constants[r])) for r in MODEL_INPUTS if r in p.constants]
        self.inputs = tuple(self.inputs)
        self._inputs = {id(m): _Input(m, tuple(self._plan(r) for r in m.roles)) for m in self.inputs}
        self._streams = [x.stream for x in self._inputs.values()]
        self._matcher = Matcher(self.inputs, self.channels)
        self._chans: dict[str, _Channel] = {}
        self._later: list[tuple[float, int, Frame]] = []  # output frames due later (transport packets)
        self._seq = 0
        self._dm1 = Dm1Producer(self.dm1, self.totals) if self.dm1 is not None else None
        self._low: int | None = None
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.counters.update(ticks=0, evaluated=0, extrapolated=0, model_errors=0, clock_steps=0)
        # The wall clock's steps undone: frame time t is ``t + run_shift_s`` on the run's own continuous
        # time base (a clock correction is no time the machine ran), which operating hours count on.
        self.run_shift_s = 0.0
        self.machine = WarningMachine(p.thresholds)
        self.machine.condition = {"ok": Level.OK, "low": Level.LOW, "high": Level.HIGH}[self.totals.condition]
        self.machine.condition_reason = {
            Level.OK: Reason.NONE,
            Level.LOW: Reason.RATIO_LOW,
            Level.HIGH: Reason.RATIO_HIGH,
        }[self.machine.condition]
        n = p.filter_samples
        self.filter = RatioFilter(
            n, p.filter_min_samples, self.totals.filter_ratios[-n:], self.totals.filter_leaks[-n:]
        )
        self.payloads = Payloads(self.outputs)
        self.last_tick: Tick | None = None
        self.timeline: list[Tick] = []
        self.transitions_since_save = 0

    def _plan(self, role: str) -> tuple[RoleWindow | None, int]:
        hl = self.params.dp_from_high_low is not None
        if role == HIGH_PRESSURE and hl:
            return None, _HIGH
        if role == LOW_PRESSURE and hl:
            return None, _LOW
        if role in self.windows:
            return self.windows[role], _WINDOW
        return None, _IGNORED

    # -- frames in ---------------------------------------------------------------------------------

    def feed(self, frame: Frame) -> list[Frame]:
        """Take one received frame; returns the output frames due by its time (see the module)."""
        t, channel, fid, extended, remote, error, fd, data = frame
        c = self.counters
        c["frames_total"] += 1
        if error or remote:
            c["error_frame" if error else "remote_frame"] += 1
            return []
        ch = self._chans.get(channel) or self._channel(channel)
        if ch.index < 0:
            c["unknown_channel"] += 1
            return []
        if fd and not ch.fd:
            c["bad_fd"] += 1
            return []
        inp = (ch.ext if extended else ch.std).get(fid, _MISS)
        if inp is _MISS:
            inp = self._lookup(ch, fid, extended)
        if inp is None:
            c["unknown_id"] += 1
            return []
        n = len(data)
        if n != inp.length:
            if n < inp.length:
                c["bad_length"] += 1
                inp.stream.counts["bad_length"] += 1
                return []
            # longer than its message (a CAN FD frame padded to the next FD length): the message is its
            # first bytes, and only they are checked (a J1939 checksum covers the 8-byte message)
            data = data[: inp.length]
        out: list[Frame] = []
        clock = self.clock
        if not clock.in_step(t):  # a tick is due, or the frame is late (or its time is not a number)
            step = clock.step(t)
            if step.late:
                c["late"] += 1
                return []
            if step.back_by_s:
                out = self._release(out, math.inf)
                self.shift_time(-step.back_by_s)
            for k in step.ticks:
                out += self._evaluate(k)
        stream = inp.stream
        if inp.checked:
            verdict = stream.check(t, fid, data)
            if verdict != OK:
                c[REASONS[verdict]] += 1
                stream.note(t, verdict)
                return self._release(out, t) if self._later else out
        raws = inp.decode(data)
        if raws is None:
            c["out_of_range"] += 1
            stream.note(t, OUT_OF_RANGE)
            return self._release(out, t) if self._later else out
        c["accepted"] += 1
        if t >= stream.newest_t:  # stream.note(t, OK), inlined: the common case
            stream.newest_t = t
            stream.newest_ok = True
        clock.started(t)
        high = None
        for raw, (win, kind) in zip(raws, inp.plan, strict=True):
            if kind == _WINDOW:
                win.add(t, raw)  # type: ignore[union-attr]
            elif kind == _HIGH:
                high = raw
            elif kind == _LOW:
                self._low = raw
        if high is not None and self._low is not None:
            hl = self.params.dp_from_high_low
            assert hl is not None
            self.windows[DP].add(t, hl.p * high - hl.q * self._low)
        return self._release(out, t) if self._later else out

    def _channel(self, name: str) -> _Channel:
        i = self.channels.resolve(name)
        ch = _Channel(-1, False) if i is None else _Channel(i, self.channels.fd[i])
        if len(self._chans) < MEMO_MAX:
            self._chans[name] = ch
        return ch

    def _lookup(self, ch: _Channel, fid: int, extended: bool) -> _Input | None:
        spec = self._matcher.match(ch.index, fid, extended)
        inp = self._inputs[id(spec)] if spec is not None else None
        memo = ch.ext if extended else ch.std
        if len(memo) < MEMO_MAX:
            memo[fid] = inp
        return inp

    def advance(self, t: float) -> list[Frame]:
        """Time passes without frames (the daemon's idle timer): evaluate up to ``t``."""
        out: list[Frame] = []
        for k in self.clock.advance(t):
            out += self._evaluate(k)
        return self._release(out, t) if self._later else out

    def due(self, t: float) -> list[Frame]:
        """The pending transport packets due by ``t``, without evaluating (the daemon's timer, the
        columnar replay at the end of a stretch)."""
        return self._release([], t) if self._later else []

    @property
    def next_due_t(self) -> float:
        """The time of the next pending output frame (inf when none)."""
        return self._later[0][0] if self._later else math.inf

    def flush(self) -> list[Frame]:
        """Evaluate the ticks up to the last frame (end of a replayed log); every pending frame."""
        out: list[Frame] = []
        for k in self.clock.flush():
            out += self._evaluate(k)
        return self._release(out, math.inf)

    def _release(self, out: list[Frame], t: float) -> list[Frame]:
        """``out`` (frames of ticks, in time order) merged with the pending frames due by ``t``."""
        later = self._later
        if not later or later[0][0] > t:
            return out
        merged: list[Frame] = []
        for f in out:
            while later and later[0][0] <= f.timestamp_s:
                merged.append(heapq.heappop(later)[2])
            merged.append(f)
        while later and later[0][0] <= t:
            merged.append(heapq.heappop(later)[2])
        return merged

    def shift_time(self, delta_s: float) -> None:
        """The wall clock stepped by ``delta_s``: move the windows and the tick clock onto the new
        time base (by whole evaluation periods, so the tick grid stays and no tick is lost or doubled),
        so the drive's samples keep their ages and the ratio goes on without a pause. The core finds
        steps back itself; the daemon tells it of steps forward."""
        self.counters["clock_steps"] += 1
        ticks = self.clock.whole_ticks(delta_s)
        self.run_shift_s -= ticks * self.period
        for w in self.windows.values():
            w.shift(ticks * self.period)
        for st in self._streams:
            st.shift(ticks * self.period)
        self.clock.shift(ticks)

    def take_over(self, old: Monitor) -> list[str]:
        """Go on where ``old`` (this machine's monitor under the previous configuration or model, the
        daemon's SIGHUP reload) left off: the totals and warning history, the warning machine with
        its debounce and fault timers (under the new thresholds), the ratio filter (its newest
        ``filter_samples``), the counters, the alive counter, the DM1 state and the output frames
        still due carry over. The input windows and input health carry over when the inputs are
        matched, read and scaled as before, and the tick clock too when the rate is the same;
        otherwise they start afresh. Returns what started afresh (empty: nothing)."""
        p = self.params
        self.totals = old.totals
        ratios, leaks = old.filter.saved()
        n = p.filter_samples
        self.filter = RatioFilter(n, p.filter_min_samples, ratios[-n:], leaks[-n:])
        self.machine = replace(old.machine, th=p.thresholds)
        self.counters.update(old.counters)
        self.run_shift_s = old.run_shift_s
        self.payloads.alive = old.payloads.alive
        self.payloads.last_warning = old.payloads.last_warning
        self.last_tick = old.last_tick
        self.transitions_since_save = old.transitions_since_save
        self._later, self._seq = old._later, old._seq
        if old._dm1 is not None:
            self.totals.dtc_active = list(old._dm1.active)
        if self.dm1 is not None:
            same_dm1 = old._dm1 is not None and self.dm1 == old.dm1
            self._dm1 = old._dm1 if same_dm1 else Dm1Producer(self.dm1, self.totals)
        afresh = []
        same_inputs = (
            self.inputs == old.inputs
            and self.channels == old.channels
            and p.affine == old.params.affine
            and p.constants == old.params.constants
            and p.dp_from_high_low == old.params.dp_from_high_low
            and set(self.windows) == set(old.windows)
        )
        if same_inputs:  # the old windows, and the old plans and streams that point at them
            self.windows = old.windows
            self._inputs, self._streams, self._matcher = old._inputs, old._streams, old._matcher
            self._chans = old._chans
            self._low = old._low
        else:
            afresh.append("the input windows and health (inputs read differently: about a second of warming up)")
        if same_inputs and self.period == old.period and self.clock.max_gap_s == old.clock.max_gap_s:
            self.clock = old.clock
        else:
            afresh.append("the tick clock (it starts on the next frame)")
        return afresh

    # -- evaluation --------------------------------------------------------------------------------

    def _evaluate(self, k: int) -> list[Frame]:
        """One evaluation tick (the steps in the module's docstring)."""
        p = self.params
        t = k * self.period
        window_s = p.limits.window_s
        mean, std, count, age = {}, {}, {}, {}
        for role, w in self.windows.items():
            mean[role], std[role], count[role] = w.stats(t, window_s, p.affine[role])
            age[role] = t - w.last_t
        for role, value in self._constants:
            mean[role], std[role], count[role], age[role] = value, 0.0, p.limits.min_samples, 0.0
        g = gate_point(mean, std, count, age, p.limits, p.max_age_s, p.envelope)
        g = self._health_gate(t, g)
        out = p.output_role
        meas = mean[out] if count[out] else 0.0
        pred = wb = raw = 0.0
        flt = self.filter
        if g in EVALUATED:
            try:
                pred, wb = self.model.predict_one(
                    mean["pump_speed_rpm"], mean["pump_disp_cc"], mean[DP], mean["temp_c"]
                )
            except Exception:  # a model that fails must not take the daemon down
                pred = math.nan
            if not prediction_ok(pred, p.limits):
                self.counters["model_errors"] += 1
                g = Gate.MODEL_ERROR
                pred = wb = 0.0
            else:
                raw = meas / pred * 100.0
                flt.add(raw, (pred - meas) * p.lpm_per_unit)
                self.counters["evaluated"] += 1
                if g == Gate.EXTRAPOLATED:
                    self.counters["extrapolated"] += 1
                self.totals.evaluated_s += self.period
        filt_valid = flt.valid
        filt = flt.ratio_pct
        evaluated = g in EVALUATED
        m = self.machine
        cond_before, fault_before = m.condition, m.fault_reason
        for tr in m.step(t, self.period, g, filt if (filt_valid and evaluated) else None):
            self._record(tr.t_s, tr.level_from, tr.level_to, tr.reason, tr.ratio_pct)
        if m.condition != cond_before and m.condition in (Level.LOW, Level.HIGH):
            self.totals.warning_count += 1
        if fault_before == Reason.NONE and m.fault_reason != Reason.NONE:
            self.totals.fault_count += 1
        self.totals.condition = LEVEL_NAMES[m.condition]
        level, reason = m.level, m.reason
        self.totals.time_in_level_s[LEVEL_NAMES[level]] += self.period
        self.counters["ticks"] += 1
        tick = Tick(
            t_s=t,
            gate=g,
            measured=meas,
            predicted=pred,
            whitebox=wb,
            ratio_raw_pct=raw if evaluated else 0.0,
            ratio_filt_pct=filt,
            extra_leak_lpm=flt.leak_lpm,
            filt_valid=filt_valid,
            level=level,
            reason=reason,
            time_below_s=m.time_below_s,
            run_shift_s=self.run_shift_s,
        )
        self.last_tick = tick
        if self.keep_timeline:
            self.timeline.append(tick)
        return self._emit(k, tick)

    def _health_gate(self, t: float, g: Gate) -> Gate:
        """An erratic input message makes the point implausible (:mod:`cmcan.monitor.health`)."""
        return Gate.IMPLAUSIBLE_INPUT if health.tick(self._streams, t, self.counters) else g

    def _emit(self, k: int, tick: Tick) -> list[Frame]:
        """The output frames of an evaluated tick: CM frames, and DM1 where configured; frames for
        later (transport packets) wait in the pending queue."""
        out = self.payloads.frames(k, tick, self.totals.warning_count)
        if self._dm1 is not None:
            m = self.machine
            ratio = tick.ratio_filt_pct if tick.filt_valid and tick.gate == Gate.EVALUATING else None
            dm = self._dm1.step(k, tick.t_s, m.condition, m.fault_reason, ratio)
            if dm:  # most ticks send no DM1
                self.queue(dm, tick.t_s, out)
        return out

    def queue(self, frames: list[Frame], t: float, out: list[Frame]) -> None:
        """Output frames of the tick at ``t``: those due now go to ``out``, the transport packets due
        later into the pending queue (the columnar replay queues its DM1 frames here too)."""
        for f in frames:
            if f.timestamp_s > t:
                heapq.heappush(self._later, (f.timestamp_s, self._seq, f))
                self._seq += 1
            else:
                out.append(f)

    def _record(self, t: float, frm: Level, to: Level, reason: Reason, ratio: float | None) -> None:
        tot = self.totals
        tot.history.append(
            {
                "t_s": t,
                "from": LEVEL_NAMES[frm],
                "to": LEVEL_NAMES[to],
                "reason": reason.name.lower(),
                "ratio_filt_pct": ratio,
                "t_run_s": t + self.run_shift_s,  # on the continuous time base (``run_shift_s``)
            }
        )
        del tot.history[:-HISTORY_MAX]
        self.transitions_since_save += 1

    # -- views -------------------------------------------------------------------------------------

    def save_totals(self) -> Totals:
        """The totals with the filter contents, ready to persist."""
        self.totals.filter_ratios, self.totals.filter_leaks = self.filter.saved()
        self.totals.condition = LEVEL_NAMES[self.machine.condition]
        self.transitions_since_save = 0
        return self.totals

    def channels_seen(self) -> dict[str, str | None]:
        """Each channel name frames came with so far, and the configured channel it was read as."""
        names = self.channels.names
        return {k: (names[c.index] if c.index >= 0 else None) for k, c in self._chans.items()}

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
            "inputs": {x.spec.name or hex(x.spec.frame_id): dict(x.stream.counts) for x in self._inputs.values()},
            "dtcs_active": list(self.totals.dtc_active),
        }
