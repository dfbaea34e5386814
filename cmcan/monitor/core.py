"""The monitor core: frames with timestamps in, output frames and ticks out. No I/O, no clock.

``Monitor.feed`` takes one received frame, ``Monitor.feed_columns`` a chunk of frames as arrays; both
drive the same stages through their two forms (one frame or tick at a time, many at once as
arrays), each stage owning its state:

- :mod:`~cmcan.monitor.inputs` routes a frame to its mapped input message (or counts why not);
- :mod:`~cmcan.monitor.clock` says which evaluation ticks a frame completes and which frames are late;
- :mod:`~cmcan.monitor.health` checks checksums, alive counters and timeouts per message;
- :mod:`~cmcan.monitor.windows` keeps each role's trailing window of accepted samples;
- at each tick: :func:`~cmcan.monitor.gating.gate_point` (or ``gate_columns``) gates the operating
  point, :mod:`~cmcan.monitor.ratio` asks the model and forms the raw ratio and leakage,
  :mod:`~cmcan.monitor.filter` averages them, :mod:`~cmcan.monitor.warnings` steps the warning machine,
  :mod:`~cmcan.monitor.totals` keeps what survives a restart, :mod:`~cmcan.monitor.payloads` and
  :mod:`~cmcan.monitor.diagnostics` make the CM frames and DM1, :mod:`~cmcan.monitor.release` orders
  the output.

One tick, in order (:meth:`Monitor._evaluate`), each step a function of the windows and the state
the previous ticks left:

1. window statistics of every gated role at the tick's time; a role the machine holds constant
   (``MonitorParams.constants``) is that value, fresh, with no spread;
2. the gate with the model's envelope: ``EVALUATING`` or ``EXTRAPOLATED`` (outside the envelope)
   evaluates the point, any other verdict names why not; an erratic input message
   (:meth:`~cmcan.monitor.health.Health.tick`) makes it ``IMPLAUSIBLE_INPUT``;
3. for an evaluated point one model call; an implausible prediction makes the tick ``MODEL_ERROR``
   (:mod:`cmcan.monitor.ratio`);
4. raw ratio = measured / predicted * 100 and leakage = (predicted - measured) * ``lpm_per_unit``
   into the moving-average filter, extrapolated points included;
5. the warning machine steps with the gate and, when the point was evaluated and the filter is
   valid, the filtered ratio: extrapolated points may raise a warning, never clear one;
6. the tick goes to the listeners (:class:`~cmcan.monitor.tick.TickListener`), and its CM frames due
   (``cm_gate`` carries the verdict) and DM1, where configured, are made.

Output order: every output frame carries its time (a tick's time, or later for the packets of a
J1939 transport session). ``feed(f)``, ``advance(t)`` and ``due(t)`` return, in order of time (equal
times in the order they were made), the output frames not returned before whose time is at most the
frame's time (``t``). ``flush()`` returns the rest. A step back of the frames' time (the wall clock)
first returns every pending packet. ``feed_columns`` returns a chunk's output frames the same way.

The array path takes a chunk in *regular stretches* (input frames whose times move forward without
gaps, time resets or unreadable stamps): the clock's decisions from running maxima, the checks and
decoding per message, each tick's window statistics from prefix sums, the gate for all ticks at once,
the model in one batched call, the filter from exact sums; then the warning machine and DM1 tick by
tick where something can change. A frame no stretch can take goes through the per-frame path. Both
paths give the same ticks, frames and state, bit for bit.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can.frame import Frame, FrameColumns
from cmcan.can.j1939 import ids as j1939_ids
from cmcan.monitor.baseline import Baseline, BaselineParams, BaselineStateError, Mode
from cmcan.monitor.clock import TickClock
from cmcan.monitor.diagnostics import Dm1Params, Dm1Producer
from cmcan.monitor.filter import RatioFilter
from cmcan.monitor.gating import Gate, GateLimits, gate_columns, gate_point
from cmcan.monitor.health import NOT_AVAILABLE, OK, OUT_OF_RANGE, Health, Stream
from cmcan.monitor.inputs import NODE, Channels, InputMessage, Router, payload_rows
from cmcan.monitor.node import Clear, Node, NodeParams
from cmcan.monitor.payloads import Outputs, Payloads
from cmcan.monitor.prognosis import PrognosisParams, Stage
from cmcan.monitor.ratio import Point, Points, Predictor, Ratio, corrected_prediction, ratio_and_leak
from cmcan.monitor.release import OutputQueue
from cmcan.monitor.tick import LEVEL_NAMES, OPERATING_POINT, Tick, TickColumns, TickListener
from cmcan.monitor.totals import Totals
from cmcan.monitor.warnings import Level, Reason, Thresholds, Transition, WarningMachine, fault_raised, warning_raised
from cmcan.monitor.windows import Affine, DpFromHighLow, Target, Windows
from cmcan.roles import DP, MODEL_INPUTS, PUMP_DISP, PUMP_SPEED, TEMP, gated_roles

# The first window a stretch is looked for in (frames); then twice the last stretch's length.
STRETCH_WINDOW_MIN = 4096

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
    "ticks",
    "evaluated",
    "extrapolated",
    "model_errors",
    "clock_steps",
    "own_address",
    "other_sender",
    "error_code",
    "not_available",
    "counter_not_available",
    "checksum_not_available",
    "node_frames",
)
_CONDITION = {
    "ok": (Level.OK, Reason.NONE),
    "low": (Level.LOW, Reason.RATIO_LOW),
    "high": (Level.HIGH, Reason.RATIO_HIGH),
}


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


class Slot:
    """A mapped input message at run time: its spec, its health stream, where its values go."""

    __slots__ = ("add", "checked", "decode", "index", "length", "spec", "stream", "targets")

    def __init__(self, index: int, spec: InputMessage, stream: Stream, windows: Windows) -> None:
        self.index = index
        self.spec = spec
        self.length = spec.length
        self.decode = spec.decode
        self.stream = stream
        self.checked = spec.health.checked
        self.targets: tuple[Target, ...] = windows.targets(spec.roles)
        self.add = windows.adder(spec.roles)


class NodeSlot:
    """What the router hands back for a frame of cmcan's J1939 node (a Request, an Address Claimed)."""

    index = -1
    length = 0


NODE_SLOT = NodeSlot()


class Monitor:
    def __init__(
        self,
        params: MonitorParams,
        inputs: Sequence[InputMessage],
        model: Predictor,
        outputs: Outputs,
        totals: Totals | None = None,
        channels: Channels | None = None,
        dm1: Dm1Params | None = None,
        own_address: int | None = None,
        node: NodeParams | None = None,
        baseline: BaselineParams | None = None,
        prognosis: PrognosisParams | None = None,
    ) -> None:
        p = self.params = params
        self.inputs = tuple(inputs)
        self.outputs = outputs
        self.channels = channels or Channels()
        self.dm1 = dm1
        self.totals = totals or Totals()
        self.period = 1.0 / p.rate_hz
        self.clock = TickClock(p.rate_hz, max_gap_s=max(p.limits.window_s, 1.0))
        roles = gated_roles(p.output_role)
        self.windows = Windows(
            roles,
            p.affine,
            p.limits.window_s,
            p.limits.min_samples,
            p.constants,
            p.dp_from_high_low,
            p.limits.role_window_s,
        )
        self.health = Health([m.health for m in self.inputs])
        self.slots = tuple(
            Slot(i, m, s, self.windows) for i, (m, s) in enumerate(zip(self.inputs, self.health.streams, strict=True))
        )
        # cmcan as a J1939 node where configured: the router hands it its frames (:mod:`.node`)
        self.node = Node(node) if node is not None else None
        self.router = Router(self.inputs, self.channels, self.slots, own_address, *_node_route(node, self.channels))
        self.ratio = Ratio(model, p.limits, p.lpm_per_unit)
        self.queue = OutputQueue()
        self.dm1_producer = Dm1Producer(dm1, self.totals) if dm1 is not None else None
        self.accepted = 0
        self.n_ticks = 0
        self._window = STRETCH_WINDOW_MIN  # where the columnar engine looks for its next stretch
        # The wall clock's steps undone: frame time t is ``t + run_shift_s`` on the run's own continuous
        # time base (a clock correction is no time the machine ran), which operating hours count on.
        self.run_shift_s = 0.0
        self._stages(baseline, prognosis)
        level, reason = _CONDITION[self.totals.condition]
        self.machine = WarningMachine(self._thresholds(), condition=level, condition_reason=reason)
        n = p.filter_samples
        self.filter = RatioFilter(
            n, p.filter_min_samples, self.totals.filter_ratios[-n:], self.totals.filter_leaks[-n:]
        )
        self.payloads = Payloads(self.outputs)
        self.last_tick: Tick | None = None
        self.listeners: list[TickListener] = []
        self.transitions_since_save = 0

    @property
    def model(self) -> Predictor:
        return self.ratio.model

    @model.setter
    def model(self, model: Predictor) -> None:
        self.ratio.model = model

    @property
    def counters(self) -> dict[str, int]:
        """What happened to the frames and ticks so far (:data:`COUNTERS`), from each stage's counts."""
        c = {**self.router.counts, **self.health.counts(), **self.clock.counts, **self.ratio.counts}
        c.update(accepted=self.accepted, ticks=self.n_ticks)
        c["node_frames"] = self.node.counts["node_frames"] if self.node is not None else 0
        return {k: c[k] for k in COUNTERS}

    @property
    def clock_steps(self) -> int:
        """The steps of the wall clock the monitor moved its state by so far."""
        return self.clock.counts["clock_steps"]

    # -- one frame ---------------------------------------------------------------------------------

    def feed(self, frame: Frame) -> list[Frame]:
        """Take one received frame; returns the output frames due by its time (see the module)."""
        if self.node is not None:
            return self._feed_node(frame)
        slot = self.router.route(frame)
        return [] if slot is None else self.take(slot, frame)

    def _feed_node(self, frame: Frame) -> list[Frame]:
        """:meth:`feed` on a J1939 node: it starts (claims) at the first frame with a time, takes its
        own frames, and gates what goes out."""
        node = self.node
        assert node is not None
        pre = self.start(frame[0]) if not node.started and math.isfinite(frame[0]) else []
        slot = self.router.route(frame)
        if slot is None:
            out = []
        elif slot is NODE_SLOT:
            out = self._node_frame(frame)
        else:
            out = node.outgoing(self.take(slot, frame))
        return pre + out if pre else out

    def start(self, t: float, why: str = "start") -> list[Frame]:
        """The node's start at ``t``: its address claim (the daemon calls it when a link comes up, at
        its start and after a bus-off; a replay at the log's first frame)."""
        if self.node is None:
            return []
        return self.node.outgoing(self.node.start(t, why))

    def _node_frame(self, frame: Frame) -> list[Frame]:
        """A Request or Address Claimed for cmcan's node: the ticks before it first (so its answers
        follow them in time), then the answers; a DM3 or DM11 is carried out before its ACK."""
        node = self.node
        assert node is not None
        t = frame[0]
        out: list[Frame] = []
        if math.isfinite(t):
            for k in self.clock.passing(t):
                out += self._evaluate(k)
            if self.queue.later:
                out = self.queue.release(out, t)
        out = node.outgoing(out)
        answers, clear = node.handle(frame, self.dm1_producer, self.payloads)
        if clear is not None:
            self._clear(clear)
        now: list[Frame] = []
        self.queue.queue(answers, t, now)  # later ones (a delayed Cannot Claim, BAM packets) wait
        return out + node.outgoing(now)

    def _clear(self, c: Clear) -> None:
        """DM3 (previously active DTCs) or DM11 (active ones: the DTCs and their counts, and a condition
        the filtered ratio no longer shows; one it still shows stays, so its DTC is active again at the
        next tick with count 1), recorded with who asked and when."""
        dm = self.dm1_producer
        assert dm is not None
        if c.kind == "dm11":
            keys = dm.clear_active()
            old = self.machine.level
            self.machine.clear(self.filter.ratio_pct if self.filter.valid else None)
            if self.machine.level != old:
                self._record(Transition(c.t_s, old, self.machine.level, self.machine.reason, None))
            self.totals.condition = LEVEL_NAMES[self.machine.condition]
        else:
            keys = dm.clear_previous()
        self.totals.record_clear(c.kind, c.t_s, c.t_s + self.run_shift_s, c.by_address, c.by_name, keys)

    def take(self, slot: Slot, frame: Frame) -> list[Frame]:
        """A routed frame of ``slot``'s message: the ticks it completes, its checks, its samples."""
        t, data = frame[0], frame[7]
        if len(data) > slot.length:  # a CAN FD frame padded beyond its message: the message's bytes
            data = data[: slot.length]
        out: list[Frame] = []
        clock = self.clock
        if not clock.in_step(t):  # a tick is due, or the frame is late (or its time is not a number)
            step = clock.step(t)
            if step.late:
                return []
            if step.back_by_s:
                out = self.queue.release(out, math.inf)
                self.shift_time(-step.back_by_s)
            for k in step.ticks:
                out += self._evaluate(k)
        stream = slot.stream
        raws = slot.decode(data)
        verdict = stream.check(t, frame[2], data, raws == NOT_AVAILABLE) if slot.checked else OK
        if verdict == OK:
            if raws.__class__ is tuple:  # accepted: its samples into the windows
                self.accepted += 1
                stream.note(t, OK)
                clock.started(t)
                slot.add(t, raws)  # type: ignore[arg-type]
                return self.queue.release(out, t) if self.queue.later else out
            verdict = OUT_OF_RANGE if raws is None else raws  # (or a J1939 code: error, not available)
        stream.note(t, verdict, frame[2])  # type: ignore[arg-type]
        return self.queue.release(out, t) if self.queue.later else out

    def advance(self, t: float) -> list[Frame]:
        """Time passes without frames (the daemon's idle timer): evaluate up to ``t``."""
        pre = self.start(t) if self.node is not None and not self.node.started and math.isfinite(t) else []
        out: list[Frame] = []
        for k in self.clock.advance(t):
            out += self._evaluate(k)
        if self.node is not None and math.isfinite(t):
            out += self.node.expire(t)  # an RTS/CTS connection whose time ran out: its abort
        return pre + self._gate(self.queue.release(out, t) if self.queue.later else out)

    def due(self, t: float) -> list[Frame]:
        """The pending transport packets due by ``t``, without evaluating (the daemon's timer)."""
        return self._gate(self.queue.release([], t)) if self.queue.later else []

    def _gate(self, frames: list[Frame]) -> list[Frame]:
        """Output frames through the J1939 node's gate (where there is a node)."""
        return self.node.outgoing(frames) if self.node is not None and frames else frames

    @property
    def next_due_t(self) -> float:
        """The time of the next pending output frame (inf when none)."""
        return self.queue.next_due_t

    def flush(self) -> list[Frame]:
        """Evaluate the ticks up to the last frame (end of a replayed log); every pending frame."""
        out: list[Frame] = []
        for k in self.clock.flush():
            out += self._evaluate(k)
        return self._gate(self.queue.release(out, math.inf))

    def shift_time(self, delta_s: float) -> None:
        """The wall clock stepped by ``delta_s``: move the windows and the tick clock onto the new
        time base (by whole evaluation periods, so the tick grid stays and no tick is lost or doubled),
        so the drive's samples keep their ages and the ratio goes on without a pause. The core finds
        steps back itself; the daemon tells it of steps forward."""
        ticks = self.clock.whole_ticks(delta_s)
        self.run_shift_s -= ticks * self.period
        self.windows.shift(ticks * self.period)
        self.health.shift(ticks * self.period)
        self.clock.shift(ticks)

    # -- one tick ----------------------------------------------------------------------------------

    def _evaluate(self, k: int) -> list[Frame]:
        """One evaluation tick (the steps in the module's docstring)."""
        p = self.params
        t = k * self.period
        mean, std, count, age = self.windows.stats(t)
        g = gate_point(mean, std, count, age, p.limits, p.max_age_s, p.envelope)
        if self.health.tick(t):  # an erratic input message makes the point implausible
            g = Gate.IMPLAUSIBLE_INPUT
        pt = self.ratio.point(mean, count, g)
        bl = self.baseline
        if bl is not None:
            if bl.tick(k, t, t + self.run_shift_s, pt.gate != Gate.NO_INPUT):  # the learning ended before it
                self._baseline_changed()
            if bl.applies and pt.evaluated:
                pt = self._corrected(pt, mean)
            elif pt.gate == Gate.EVALUATING and bl.mode == Mode.LEARNING:
                bl.add(t, (mean[PUMP_SPEED], mean[PUMP_DISP], mean[DP], mean[TEMP]), pt.measured, pt.predicted)
        if pt.evaluated:
            self.filter.add(pt.ratio_raw_pct, pt.leak_lpm)
        tick = self._judge(t, pt, mean)
        for listener in self.listeners:
            listener.tick(tick)
        return self._emit(k, tick)

    # -- the on-board baseline ---------------------------------------------------------------------

    def _stages(self, baseline: BaselineParams | None, prognosis: PrognosisParams | None) -> None:
        """The stages a configuration may add, their state from the totals."""
        # the machine's own baseline where configured (:mod:`.baseline`); why it restarted, if it did
        self.baseline, self.baseline_note = _baseline_from(baseline, self.totals.baseline)
        self._baseline_key: tuple[Any, ...] | None = None  # what the tick fields below were made of
        self._baseline_tick: dict[str, Any] = {}
        # the prognosis where configured (:mod:`.prognosis`), its history from the totals
        self.prognosis = Stage(prognosis, self.totals.prognosis) if prognosis is not None else None

    def _thresholds(self) -> Thresholds:
        """The warning thresholds now: wider while the type model judges a machine still learning."""
        bl = self.baseline
        if bl is not None and bl.mode == Mode.LEARNING and bl.p.learning_thresholds is not None:
            return bl.p.learning_thresholds
        return self.params.thresholds

    def _baseline_changed(self) -> None:
        """The reference changed (learning ended, or a reset): the thresholds follow, and the filter
        starts afresh when its ratios were against another reference."""
        self.machine = replace(self.machine, th=self._thresholds())
        if self.prognosis is not None:  # the leakage is against another reference from here on
            self.prognosis.restart()
        bl = self.baseline
        if bl is not None and (bl.applies or bl.mode == Mode.LEARNING):
            p = self.params
            self.filter = RatioFilter(p.filter_samples, p.filter_min_samples, [], [])

    def reset_baseline(self, reason: str, at: str | None = None) -> bool:
        """Learn the machine's baseline afresh (after service), the old one kept in its history; False
        when no baseline is configured."""
        if self.baseline is None:
            return False
        was_applied = self.baseline.applies
        self.baseline.reset(reason, at)
        self.machine = replace(self.machine, th=self._thresholds())
        if was_applied:
            p = self.params
            self.filter = RatioFilter(p.filter_samples, p.filter_min_samples, [], [])
        if self.prognosis is not None:
            self.prognosis.restart()
        return True

    def _corrected(self, pt: Point, mean: Mapping[str, float]) -> Point:
        """A point judged against the machine's own baseline: the type model's prediction plus the
        machine's correction (:func:`~cmcan.monitor.ratio.corrected_prediction`)."""
        assert self.baseline is not None
        x = np.array([[mean[r] for r in MODEL_INPUTS]])
        lpu = self.params.lpm_per_unit
        pred, ok = corrected_prediction(pt.predicted, float(self.baseline.correction_lpm(x)[0]), lpu)
        if not ok:
            return pt
        raw, leak = ratio_and_leak(pt.measured, pred, lpu)
        return pt._replace(predicted=pred, ratio_raw_pct=raw, leak_lpm=leak)

    def _corrected_columns(self, pts: Points, mean: Mapping[str, NDArray[np.float64]]) -> Points:
        """:meth:`_corrected` at every evaluated tick of a stretch."""
        assert self.baseline is not None
        e = pts.evaluated
        if not len(e):
            return pts
        x = np.column_stack([mean[r][e] for r in MODEL_INPUTS])
        lpu = self.params.lpm_per_unit
        pe, ok = corrected_prediction(pts.predicted[e], self.baseline.correction_lpm(x), lpu)
        pe = np.where(ok, pe, pts.predicted[e])
        raw_e, leak_e = ratio_and_leak(pts.measured[e], pe, lpu)
        pred, raw = pts.predicted.copy(), pts.ratio_raw_pct.copy()
        pred[e] = pe
        raw[e] = np.where(ok, raw_e, raw[e])
        leak = np.where(ok, leak_e, pts.leak_lpm)
        return replace(pts, predicted=pred, ratio_raw_pct=raw, leak_lpm=leak)

    def _judge(self, t: float, pt: Point, mean: Mapping[str, float]) -> Tick:
        """Steps 5 and 6 of a tick: the warning machine, the totals, the tick."""
        flt, m, tot = self.filter, self.machine, self.totals
        evaluated = pt.evaluated
        filt_valid, filt = flt.valid, flt.ratio_pct
        cond_before, fault_before = m.condition, m.fault_reason
        for tr in m.step(t, self.period, pt.gate, filt if (filt_valid and evaluated) else None):
            self._record(tr)
        tot.warning_count += warning_raised(cond_before, m.condition)
        tot.fault_count += fault_raised(fault_before, m.fault_reason)
        tot.condition = LEVEL_NAMES[m.condition]
        level = m.level
        tot.tick(level, evaluated, self.period)
        self.n_ticks += 1
        pg = self.prognosis
        progn: dict[str, Any] = {}
        if pg is not None:
            hour = pg.hours(t + self.run_shift_s, pt.gate != Gate.NO_INPUT)
            if _replaced(cond_before, m.condition, filt, m.th):
                pg.restart()
            pg.tick(hour)
            if evaluated:
                pg.add(hour, pt.leak_lpm, pt.ratio_raw_pct, mean[DP], mean[TEMP])
            progn = pg.fields(hour)
        self.last_tick = Tick(
            t_s=t,
            gate=pt.gate,
            measured=pt.measured,
            predicted=pt.predicted,
            whitebox=pt.whitebox,
            ratio_raw_pct=pt.ratio_raw_pct,
            ratio_filt_pct=filt,
            extra_leak_lpm=flt.leak_lpm,
            filt_valid=filt_valid,
            level=level,
            reason=m.reason,
            time_below_s=m.time_below_s,
            run_shift_s=self.run_shift_s,
            **{role: mean[role] for role in OPERATING_POINT},
            **self._baseline_fields(),
            **progn,
        )
        return self.last_tick

    def _prognosis_columns(
        self,
        t_k: NDArray[np.float64],
        evaluated: NDArray[np.bool_],
        pts: Points,
        mean: Mapping[str, NDArray[np.float64]],
        cond_before: Level,
        condition: NDArray[np.int8],
        filt: NDArray[np.float64],
    ) -> dict[str, NDArray[Any]]:
        """The prognosis at every tick of a stretch, restarted where a unit was replaced
        (:func:`_replaced`), as :meth:`_judge` tick after tick."""
        pg = self.prognosis
        if pg is None:
            return {}
        n = len(t_k)
        leak = np.zeros(n)
        leak[pts.evaluated] = pts.leak_lpm
        hours = pg.hours_columns(t_k + self.run_shift_s, pts.gate != Gate.NO_INPUT)
        prev = np.empty(n, dtype=np.int8)
        prev[0] = cond_before
        prev[1:] = condition[:-1]
        cuts = np.flatnonzero(_replaced(prev, condition, filt, self.machine.th)).tolist()
        parts = []
        for a, z in itertools.pairwise([0, *cuts, n]):
            if a in cuts:
                pg.restart()
            if z > a:
                parts.append(
                    pg.run_columns(
                        hours[a:z], evaluated[a:z], leak[a:z], pts.ratio_raw_pct[a:z], mean[DP][a:z], mean[TEMP][a:z]
                    )
                )
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    def _baseline_fields(self) -> dict[str, Any]:
        """The baseline's fields of a tick: made again only when they change (once per block at most)."""
        bl = self.baseline
        if bl is None:
            return {}
        key = (bl.mode, bl.shown, bl.distance_lpm)
        if key != self._baseline_key:
            learned_h, coverage = bl.shown_progress
            self._baseline_key = key
            self._baseline_tick = {
                "baseline_state": int(bl.mode),
                "baseline_learned_h": learned_h,
                "baseline_coverage_pct": coverage,
                "baseline_distance_lpm": bl.distance_lpm,
            }
        return self._baseline_tick

    def _emit(self, k: int, tick: Tick) -> list[Frame]:
        """The output frames of an evaluated tick: CM frames, and DM1 where configured; frames for
        later (transport packets) wait in the queue."""
        out = self.payloads.frames(k, tick, self.totals.warning_count)
        if self.dm1_producer is not None:
            m = self.machine
            ratio = tick.ratio_filt_pct if tick.filt_valid and tick.gate == Gate.EVALUATING else None
            dm = self.dm1_producer.step(k, tick.t_s, m.condition, m.fault_reason, ratio)
            if dm:  # most ticks send no DM1
                self.queue.queue(dm, tick.t_s, out)
        return out

    def _record(self, tr: Transition) -> None:
        self.totals.record(tr, self.run_shift_s)
        self.transitions_since_save += 1

    # -- a chunk of frames as arrays ---------------------------------------------------------------

    def feed_columns(self, cols: FrameColumns, frames: bool = True) -> FrameColumns | None:
        """Take a chunk of received frames: as :meth:`feed` frame after frame, the output frames in
        one piece (None when none, or when ``frames`` is False: the ticks are all the caller wants)."""
        out = _Out(frames)
        which = self.router.route_columns(cols)
        if self.node is not None:
            return self._feed_columns_node(cols, which, out)
        self._feed_routed(cols, which, 0, len(cols), out)
        return out.result()

    def _feed_columns_node(self, cols: FrameColumns, which: NDArray[np.int64], out: _Out) -> FrameColumns | None:
        """:meth:`feed_columns` on a J1939 node: the chunk in pieces between the node's own frames
        (each on the per-frame path) and its start, each piece's output through the node's gate."""
        node = self.node
        assert node is not None
        rows = set(np.flatnonzero(which == NODE).tolist())
        start = None
        if not node.started:
            finite = np.flatnonzero(np.isfinite(cols.timestamp_s))
            start = int(finite[0]) if len(finite) else None
        lo = 0
        for r in sorted({*rows, *([start] if start is not None else [])}):
            piece = _Out(out.wanted)
            self._feed_routed(cols, which, lo, r, piece)
            out.add_columns(node.outgoing_columns(piece.result()))
            lo = r
            if r == start:
                out.add_frames(self.start(float(cols.timestamp_s[r])))
            if r in rows:
                out.add_frames(self._node_frame(cols.frame(r)))
                lo = r + 1
        piece = _Out(out.wanted)
        self._feed_routed(cols, which, lo, len(cols), piece)
        out.add_columns(node.outgoing_columns(piece.result()))
        return out.result()

    def _feed_routed(self, cols: FrameColumns, which: NDArray[np.int64], lo: int, hi: int, out: _Out) -> None:
        """The routed input frames among rows ``lo`` to ``hi`` of a chunk, in regular stretches."""
        idx = np.flatnonzero(which[lo:hi] >= 0) + lo
        if not len(idx):
            return
        t = cols.timestamp_s[idx]
        groups = _groups(which[idx], len(self.slots))
        del which
        dec = self._decode(cols, idx, groups)
        pos = 0
        while pos < len(idx):
            end = pos
            if self.clock.next_k is not None and math.isfinite(t[pos]):
                end = self._stretch(t, groups, dec, pos, out)
            if end == pos:  # a frame no stretch takes: the per-frame path
                out.add_frames(self.take(self.slots[int(dec.message[pos])], cols.frame(int(idx[pos]))))
                pos += 1
            else:
                pos = end

    def _decode(self, cols: FrameColumns, idx: NDArray[np.int64], groups: list[NDArray[np.int64]]) -> _Decoded:
        """Per input message the raw values of its frames, the DBC range check per frame, each frame's
        row in its message's arrays, and its counter and checksum verdict."""
        n = len(idx)
        dec = _Decoded(
            message=np.zeros(n, np.int64),
            raws={},
            values=np.zeros(n, np.int8),
            row=np.zeros(n, np.int64),
            ctr=np.zeros(n, np.int64),
            cs_ok=np.ones(n, bool),
            sa=(cols.arbitration_id[idx] & 0xFF).astype(np.int64),
        )
        for slot, sel in zip(self.slots, groups, strict=True):
            if not len(sel):
                continue
            rows = idx[sel]
            data = payload_rows(cols, rows, slot.spec.width)
            dec.raws[slot.index], dec.values[sel] = slot.spec.decode_columns(data)
            dec.message[sel] = slot.index
            dec.row[sel] = np.arange(len(sel))
            if slot.checked:
                dec.ctr[sel], dec.cs_ok[sel] = slot.stream.integrity_columns(
                    cols.arbitration_id[rows], data, slot.length
                )
        return dec

    def _stretch(
        self, t_all: NDArray[np.float64], groups_all: list[NDArray[np.int64]], dec: _Decoded, pos: int, out: _Out
    ) -> int:
        """Take the regular stretch of routed frames starting at ``pos``; returns its end.

        The stretch is looked for in a window of the frames after ``pos``: every rule reads only the
        frames before, so a stretch cut at the window's end is one cut at a chunk's end. The window
        follows the stretches' length (twice the last), so a log of short bursts costs its frames,
        not its frames times its bursts."""
        end = min(len(t_all), pos + self._window)
        t = t_all[pos:end]
        plan = self.clock.plan(t)
        # each message's frames in the window that reach the checks (not late), in arrival order
        reach = [g[np.searchsorted(g, pos) : np.searchsorted(g, end)] - pos for g in groups_all]
        reach = [g[~plan.late[g]] for g in reach]
        sa = dec.sa[pos:end]
        values = dec.values[pos:end]
        checks, until = self.health.check_columns(
            t, reach, dec.ctr[pos:end], dec.cs_ok[pos:end], sa, values == NOT_AVAILABLE
        )
        verdict = np.where(checks != OK, checks, values).astype(np.int8)
        accepted = (verdict == OK) & ~plan.late
        stop, last_frame_t = self.clock.regular_until(plan, accepted, until)
        self._window = max(STRETCH_WINDOW_MIN, 2 * stop)
        if stop == 0:
            return pos
        self.health.commit_counters(stop)
        t, verdict, accepted = t[:stop], verdict[:stop], accepted[:stop]
        reach = [g[: np.searchsorted(g, stop)] for g in reach]
        self.accepted += int(accepted.sum())
        per_message = []
        for slot, r in zip(self.slots, reach, strict=True):
            mine = r[accepted[r]]
            at = dec.row[pos + mine]
            per_message.append((slot.targets, mine, [v[at] for v in dec.raws.get(slot.index, ())]))
        samples = self.windows.stretch(t, per_message)
        ticks, trig, k_end = self.clock.ticks_of(plan, stop)
        t_k = ticks.astype(np.float64) * self.period
        erratic = self.health.tick_columns(t, reach, verdict, trig, t_k, sa)
        if len(ticks):
            self._evaluate_columns(ticks, samples.stats(trig, t_k), erratic, out)
        self.clock.commit(plan, stop, k_end, last_frame_t)
        samples.commit()
        return pos + stop

    def _evaluate_columns(self, ks: NDArray[np.int64], stats: Any, erratic: NDArray[np.bool_], out: _Out) -> None:
        """:meth:`_evaluate` at every tick of a stretch."""
        p = self.params
        mean, std, count, age = stats
        gates = gate_columns(mean, std, count, age, p.limits, p.max_age_s, p.envelope)
        gates[erratic] = Gate.IMPLAUSIBLE_INPUT
        pts = self.ratio.points(mean, count, gates)
        bl = self.baseline
        if bl is None:
            self._filter_and_judge(ks, pts, mean, {}, out)
            return
        n = len(ks)
        mode_before, distance_before = bl.mode, bl.distance_lpm
        cand = np.flatnonzero(pts.gate == Gate.EVALUATING)
        x = np.column_stack([mean[r][cand] for r in MODEL_INPUTS])
        t_k = ks.astype(np.float64) * self.period
        # split: the first tick judged in the state the learning's end brought (n: none in this stretch)
        t_run = t_k + self.run_shift_s
        has_input = pts.gate != Gate.NO_INPUT
        split, learned, covered = bl.run_columns(
            ks, t_k, t_run, has_input, cand, x, pts.measured[cand], pts.predicted[cand]
        )
        state = np.full(n, int(mode_before), dtype=np.int8)
        distance = np.full(n, distance_before)
        state[split:], distance[split:] = int(bl.mode), bl.distance_lpm
        learned_h, coverage = bl.progress_of(learned, covered)
        cols = {
            "baseline_state": state,
            "baseline_learned_h": learned_h,
            "baseline_coverage_pct": coverage,
            "baseline_distance_lpm": distance,
        }
        if split == n:
            pts = self._corrected_columns(pts, mean) if bl.applies else pts
            self._filter_and_judge(ks, pts, mean, cols, out)
            return
        if split > 0:  # the ticks before the learning's end, judged on the type model
            first, first_mean = _take(pts, 0, split), _cut(mean, 0, split)
            self._filter_and_judge(ks[:split], first, first_mean, _cut(cols, 0, split), out)
        self._baseline_changed()
        if split < n:
            rest, rest_mean = _take(pts, split, n), _cut(mean, split, n)
            rest = self._corrected_columns(rest, rest_mean) if bl.applies else rest
            self._filter_and_judge(ks[split:], rest, rest_mean, _cut(cols, split, n), out)

    def _filter_and_judge(
        self,
        ks: NDArray[np.int64],
        pts: Points,
        mean: Mapping[str, NDArray[np.float64]],
        baseline_cols: Mapping[str, NDArray[Any]],
        out: _Out,
    ) -> None:
        filt, filt_leak, valid = self.filter.add_columns(
            pts.ratio_raw_pct[pts.evaluated], pts.leak_lpm, pts.evaluated, len(ks)
        )
        self._judge_columns(ks, pts, filt, filt_leak, valid, mean, baseline_cols, out)

    def _judge_columns(
        self,
        ks: NDArray[np.int64],
        pts: Points,
        filt: NDArray[np.float64],
        filt_leak: NDArray[np.float64],
        valid: NDArray[np.bool_],
        mean: Mapping[str, NDArray[np.float64]],
        baseline_cols: Mapping[str, NDArray[Any]],
        out: _Out,
    ) -> None:
        """:meth:`_judge` and :meth:`_emit` at every tick of a stretch."""
        t_k = ks.astype(np.float64) * self.period
        tot = self.totals
        evaluated = np.zeros(len(ks), dtype=bool)
        evaluated[pts.evaluated] = True
        ratio_arg = np.where(valid & evaluated, filt, np.nan)
        cond_before = self.machine.condition
        w = self.machine.run_columns(
            t_k, pts.gate, ratio_arg, self.period, (tot.warning_count, tot.fault_count), self._record
        )
        progn = self._prognosis_columns(t_k, evaluated, pts, mean, cond_before, w.condition, filt)
        tot.warning_count, tot.fault_count = w.warnings, w.faults
        dm1 = None
        if self.dm1_producer is not None:
            ratio = np.where(valid & (pts.gate == Gate.EVALUATING), filt, np.nan)
            dm1 = self.dm1_producer.run_columns(ks, t_k, w.condition, w.fault, ratio, self.queue.queue)
        level = w.level
        tot.condition = LEVEL_NAMES[self.machine.condition]
        tot.ticks(level, len(pts.evaluated), self.period)
        self.n_ticks += len(ks)
        ticks = TickColumns(
            t_s=t_k,
            gate=pts.gate.astype(np.int8),
            measured=pts.measured,
            predicted=pts.predicted,
            whitebox=pts.whitebox,
            ratio_raw_pct=pts.ratio_raw_pct,
            ratio_filt_pct=filt,
            extra_leak_lpm=filt_leak,
            filt_valid=valid,
            level=level,
            reason=w.reason,
            time_below_s=w.time_below_s,
            run_shift_s=np.full(len(ks), self.run_shift_s),  # no clock step within a stretch
            **{role: mean[role] for role in OPERATING_POINT},
            **baseline_cols,
            **progn,
        )
        self.last_tick = ticks.tick(len(ks) - 1)
        for listener in self.listeners:
            listener.ticks(ticks)
        if out.wanted:
            frames = self.payloads.frames_columns(ks, ticks, w.warning_count)
            out.add_columns(self.queue.merge_columns(frames, dm1, float(t_k[-1])))
        else:
            self.payloads.skip_columns(ks, ticks)
            self.queue.release([], float(t_k[-1]))  # the packets due meanwhile go, unwanted

    # -- state -------------------------------------------------------------------------------------

    def take_over(self, old: Monitor) -> list[str]:
        """Go on where ``old`` (this machine's monitor under the previous configuration or model, the
        daemon's SIGHUP reload) left off: the totals and warning history, the warning machine with
        its debounce and fault timers (under the new thresholds), the ratio filter (its newest
        ``filter_samples``), the counters, the alive counter, the DM1 state, the listeners and the
        output frames still due carry over. The input windows and input health carry over when the
        inputs are matched, read and scaled as before, and the tick clock too when the rate is the
        same; otherwise they start afresh. Returns what started afresh (empty: nothing)."""
        p = self.params
        self.totals = old.totals
        self.baseline, self.baseline_note = _baseline_taken(self.baseline, old.baseline)
        if self.prognosis is not None and old.prognosis is not None:  # the history goes on
            self.prognosis = Stage(self.prognosis.params, old.prognosis.to_dict())
        ratios, leaks = old.filter.saved()
        n = p.filter_samples
        self.filter = RatioFilter(n, p.filter_min_samples, ratios[-n:], leaks[-n:])
        self.machine = replace(old.machine, th=self._thresholds())
        self.ratio.counts.update(old.ratio.counts)
        self.accepted, self.n_ticks, self.run_shift_s = old.accepted, old.n_ticks, old.run_shift_s
        self.payloads.continue_from(old.payloads)
        self.last_tick, self.listeners = old.last_tick, old.listeners
        self.transitions_since_save = old.transitions_since_save
        self.queue = old.queue
        if old.dm1_producer is not None:
            self.totals.dtc_active = list(old.dm1_producer.active)
        if self.dm1 is not None:
            same_dm1 = old.dm1_producer is not None and self.dm1 == old.dm1
            self.dm1_producer = old.dm1_producer if same_dm1 else Dm1Producer(self.dm1, self.totals)
        if (
            self.node is not None
            and old.node is not None
            and replace(self.node.p, trust=old.node.p.trust) == old.node.p
        ):
            old.node.p = self.node.p  # (who may clear: the new configuration's)
            self.node = old.node  # the claim stands: a node claims again only with another NAME or address
        return self._take_inputs(old)

    def _take_inputs(self, old: Monitor) -> list[str]:
        p = self.params
        afresh = []
        same_inputs = (
            self.inputs == old.inputs
            and self.channels == old.channels
            and p.affine == old.params.affine
            and p.constants == old.params.constants
            and p.dp_from_high_low == old.params.dp_from_high_low
            and set(self.windows.windows) == set(old.windows.windows)
        )
        if same_inputs:  # the old windows, and the old slots and streams that point at them
            self.windows, self.health, self.slots, self.router = old.windows, old.health, old.slots, old.router
        else:
            self.router.counts.update(old.router.counts)
            self.health.base.update(old.health.counts())
            afresh.append("the input windows and health (inputs read differently: about a second of warming up)")
        if same_inputs and self.period == old.period and self.clock.max_gap_s == old.clock.max_gap_s:
            self.clock = old.clock
        else:
            self.clock.counts.update(old.clock.counts)
            afresh.append("the tick clock (it starts on the next frame)")
        return afresh

    def save_totals(self) -> Totals:
        """The totals with the filter contents, ready to persist."""
        self.totals.filter_ratios, self.totals.filter_leaks = self.filter.saved()
        self.totals.condition = LEVEL_NAMES[self.machine.condition]
        self.totals.baseline = None if self.baseline is None else self.baseline.to_dict()
        self.totals.prognosis = None if self.prognosis is None else self.prognosis.to_dict()
        self.transitions_since_save = 0
        return self.totals

    def channels_seen(self) -> dict[str, str | None]:
        """Each channel name frames came with so far, and the configured channel it was read as."""
        return self.router.channels_seen()

    def snapshot(self) -> dict[str, Any]:
        tk = self.last_tick
        return {
            "level": LEVEL_NAMES[self.machine.level],
            "reason": self.machine.reason.name.lower(),
            "ratio_filt_pct": tk.ratio_filt_pct if tk and tk.filt_valid else None,
            "gate": tk.gate.name.lower() if tk else None,
            "counters": self.counters,
            "warning_count": self.totals.warning_count,
            "evaluated_h": self.totals.evaluated_s / 3600.0,
            "inputs": {s.spec.name or hex(s.spec.frame_id): self._input_counts(s) for s in self.slots},
            "unknown_ids": [
                {"channel": ch, "id": f"0x{fid:0{8 if ext else 3}X}", "frames": n, **_j1939_fields(fid, ext)}
                for (ch, fid, ext), n in self.router.busiest_unknown()
            ],
            "dtcs_active": list(self.totals.dtc_active),
            **({"baseline": self.baseline.describe()} if self.baseline is not None else {}),
            **({"prognosis": _prognosis_snapshot(self.prognosis)} if self.prognosis is not None else {}),
            **({"j1939_node": self.node.describe()} if self.node is not None else {}),
        }

    def _input_counts(self, s: Slot) -> dict[str, Any]:
        out: dict[str, Any] = {"bad_length": self.router.bad_length[s.index], **s.stream.counts}
        if s.stream.by_source:  # J1939: the rejected and not-available frames per sender
            out["by_source"] = {f"0x{a:02X}": dict(v) for a, v in sorted(s.stream.by_source.items())}
        return out


@dataclass
class _Decoded:
    """A chunk's routed frames decoded: each frame's message, the raw values per message (one array
    per value over the message's frames), the verdict on its values, each frame's row in its
    message's arrays, its counter, whether its checksum holds, its source address."""

    message: NDArray[np.int64]
    raws: dict[int, list[NDArray[np.int64]]]
    values: NDArray[np.int8]  # the verdict on the values: OK, OUT_OF_RANGE, ERROR_CODE, NOT_AVAILABLE
    row: NDArray[np.int64]
    ctr: NDArray[np.int64]
    cs_ok: NDArray[np.bool_]
    sa: NDArray[np.int64]  # the identifier's last byte: a J1939 frame's source address


class _Out:
    """A chunk's output frames in order: pieces from stretches and frames from the per-frame path."""

    def __init__(self, wanted: bool) -> None:
        self.wanted = wanted
        self.pieces: list[FrameColumns] = []
        self.single: list[Frame] = []

    def add_frames(self, frames: list[Frame]) -> None:
        if self.wanted and frames:
            self.single.extend(frames)

    def add_columns(self, cols: FrameColumns | None) -> None:
        if cols is None or not len(cols):
            return
        if self.single:
            self.pieces.append(FrameColumns.from_frames(self.single))
            self.single = []
        self.pieces.append(cols)

    def result(self) -> FrameColumns | None:
        if self.single:
            self.pieces.append(FrameColumns.from_frames(self.single))
            self.single = []
        if not self.pieces:
            return None
        return self.pieces[0] if len(self.pieces) == 1 else FrameColumns.concat(self.pieces)


def _replaced(before: Any, now: Any, filt_pct: Any, th: Thresholds) -> Any:
    """A low or high condition back to ok with the filtered ratio near 100 % again (within half the
    band between 100 and the threshold): the unit was replaced or repaired, its trend is over. A clear
    at the band's edge (a ratio near a threshold swinging with the oil) keeps the history. Scalars or
    arrays (levels, the tick's filtered ratio: NaN never counts)."""
    with np.errstate(invalid="ignore"):
        low = (before == Level.LOW) & (filt_pct >= 100.0 - (100.0 - th.low_pct) / 2.0)
        high = (before == Level.HIGH) & (filt_pct <= 100.0 + (th.high_pct - 100.0) / 2.0)
    return (low | high) & (now == Level.OK)


def _prognosis_snapshot(pg: Stage) -> dict[str, Any]:
    e = pg.est
    return {
        "state": e.state,
        "direction": e.direction or None,
        "at_h": e.at_h if math.isfinite(e.at_h) else None,
        "to_warning_h": [_hours(v) for v in e.to_warning_h],
        "to_eol_h": [_hours(v) for v in e.to_eol_h],
        "history_points": len(pg.history.points),
        **({"note": pg.note} if pg.note else {}),
    }


def _hours(v: float) -> float | str | None:
    """Hours for JSON: None without an estimate, "never" where the curve never gets there."""
    return None if math.isnan(v) else "never" if math.isinf(v) else v


def _baseline_from(p: BaselineParams | None, saved: dict[str, Any] | None) -> tuple[Baseline | None, str | None]:
    """The baseline under ``p`` from the saved document (a fresh one where none was saved)."""
    if p is None:
        return None, None
    if saved is None:
        return Baseline(p), None
    try:
        return Baseline.from_dict(saved, p)
    except BaselineStateError as exc:
        # the rest of the state is good: learn afresh rather than refuse to monitor
        return Baseline(p), f"the saved baseline could not be used ({exc}): learning afresh"


def _baseline_taken(new: Baseline | None, old: Baseline | None) -> tuple[Baseline | None, str | None]:
    """A reload's baseline: the old one where the parameters are the same, else its document read
    under the new parameters (another envelope learns afresh)."""
    if new is None or old is None:
        return new, None
    if new.p == old.p:
        return old, None
    return _baseline_from(new.p, old.to_dict())


def _take(pts: Points, lo: int, hi: int) -> Points:
    """Ticks ``lo`` to ``hi`` of a stretch's points."""
    e = pts.evaluated
    sel = (e >= lo) & (e < hi)
    return Points(
        pts.gate[lo:hi],
        pts.measured[lo:hi],
        pts.predicted[lo:hi],
        pts.whitebox[lo:hi],
        pts.ratio_raw_pct[lo:hi],
        e[sel] - lo,
        pts.leak_lpm[sel],
    )


def _cut(cols: Mapping[str, NDArray[Any]], lo: int, hi: int) -> dict[str, NDArray[Any]]:
    return {r: v[lo:hi] for r, v in cols.items()}


def _node_route(node: NodeParams | None, channels: Channels) -> tuple[NodeSlot | None, int]:
    """What the router hands the node's frames back as, and the node's channel (its index)."""
    if node is None:
        return None, 0
    return NODE_SLOT, channels.index(node.channel) if node.channel in channels.names else 0


def _j1939_fields(fid: int, extended: bool) -> dict[str, Any]:
    """A 29-bit identifier as J1939 reads it: its PGN and source address (for people)."""
    if not extended:
        return {}
    return {"pgn": j1939_ids.pgn(fid), "source": f"0x{j1939_ids.source_address(fid):02X}"}


def _groups(ids: NDArray[np.int64], n: int) -> list[NDArray[np.int64]]:
    """The positions of each of the ``n`` input messages' frames (``ids``: 0 to n-1), each in arrival
    order: one stable sort (a radix sort on small integers) instead of a pass over all frames per
    message."""
    if n == 1:
        return [np.arange(len(ids))]
    small = ids.astype(np.int16 if n < (1 << 15) else np.int64)
    order = np.argsort(small, kind="stable")
    bounds = np.searchsorted(small[order], np.arange(n + 1))
    return [order[bounds[j] : bounds[j + 1]] for j in range(n)]
