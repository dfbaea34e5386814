"""The CM output frames of an evaluated tick: which messages are due, their signal values, encoding.

Kept apart from the evaluation so that what the ratio *is* and how the bus *carries* it change
independently (another DBC, other periods, another channel). One tick's frames
(:meth:`Payloads.frames`) or a stretch of ticks' frames as columns (:meth:`Payloads.frames_columns`),
with the same alive counter and warning-change state.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can.codec import Layout, encode_all, frame_encoder, insert
from cmcan.can.frame import Frame, FrameColumns
from cmcan.monitor.baseline import Mode
from cmcan.monitor.gating import Gate, is_evaluated
from cmcan.monitor.tick import PROGNOSIS_HOURS, Tick, TickColumns
from cmcan.monitor.warnings import Level, Reason
from cmcan.roles import MOTOR_SPEED, QUANTITY_SIGNALS

ALIVE_MODULO = 16
ALIVE_SIGNAL = "cm_alive_counter"
WARNING_COUNT_MODULO = 65536  # warning_count is sent modulo this (a 16-bit counter wraps)
# The CM ratios an output must carry: a drive that delivers nothing to twice its prediction. Beyond
# that the ratio says "broken" either way; a signal that saturates there loses nothing a reader uses.
RATIO_SPAN_PCT = (0.0, 200.0)
# time_below_threshold_s in whole seconds: at least 18 h of a low episode (16 bits of seconds);
# longer episodes may saturate at the signal's maximum.
TIME_BELOW_SPAN_S = (0.0, 65535.0)
# The hours the on-board baseline has learned: a learning that has not ended after this is a
# configuration to look at, not a number to display exactly.
BASELINE_LEARNED_SPAN_H = (0.0, 1000.0)
# The prognosis's hours: further out than this is "not for a long time" (sent as this, saturated),
# as is a curve that never gets there; without a trend they are sent as 0 with the state none.
PROGNOSIS_SPAN_H = (0.0, 4000.0)
# The output quantity in normal operation: up to the drive's nominal delivery (nominal pump speed at
# full displacement, over V_M for motor speed) with this headroom (a load pulling the motor, a pump
# above its nominal speed). The gate's plausible range is wider still: a bound for broken sensors,
# which a display need not show.
OUTPUT_HEADROOM = 1.25


def output_span(nominal_flow_lpm: float, lpm_per_unit: float) -> tuple[float, float]:
    """The output quantity's span in normal operation, in its own unit (rpm or l/min)."""
    return 0.0, OUTPUT_HEADROOM * nominal_flow_lpm / lpm_per_unit


@dataclass(frozen=True)
class Span:
    """The values cmcan sends in a signal in normal operation, and why (for messages)."""

    lo: float
    hi: float
    why: str


def output_spans(
    quantity_signals: tuple[str, str, str, str], output_range: tuple[float, float], leak_max_lpm: float
) -> dict[str, Span]:
    """Per output signal :meth:`Payloads.frames` fills in, the span it sends in normal operation:
    ratios over :data:`RATIO_SPAN_PCT`; the measured, predicted and white-box quantity over
    ``output_range`` (what the drive can deliver: :func:`output_span`); the extra leakage either way
    up to ``leak_max_lpm`` (the drive's nominal flow: a ratio of 0 or 200 % at nominal flow); flags,
    enumerations and counters over all their values."""
    lo_pct, hi_pct = RATIO_SPAN_PCT
    ratio = Span(lo_pct, hi_pct, f"CM ratios of {lo_pct:g} to {hi_pct:g} %")
    flag = Span(0.0, 1.0, "a flag")
    alive = Span(0.0, ALIVE_MODULO - 1.0, f"an alive counter modulo {ALIVE_MODULO}")
    meas, pred, wb, valid = quantity_signals
    quantity = Span(*output_range, f"up to {OUTPUT_HEADROOM:g} x the drive's nominal delivery")
    return {
        "cm_ratio_raw_pct": ratio,
        "cm_ratio_filt_pct": ratio,
        "extra_leakage_lpm": Span(-leak_max_lpm, leak_max_lpm, "up to the drive's nominal flow either way"),
        "cm_raw_valid": flag,
        "cm_filt_valid": flag,
        "cm_gate": Span(0.0, float(max(Gate)), "every gate verdict"),
        "cm_alive_counter": alive,
        meas: quantity,
        pred: quantity,
        wb: quantity,
        valid: flag,
        "warning_level": Span(0.0, float(max(Level)), "every warning level"),
        "warning_reason": Span(0.0, float(max(Reason)), "every warning reason"),
        "time_below_threshold_s": Span(*TIME_BELOW_SPAN_S, "18 h of a low episode"),
        "warning_count": Span(0.0, WARNING_COUNT_MODULO - 1.0, f"a count modulo {WARNING_COUNT_MODULO}"),
        "baseline_state": Span(0.0, float(max(Mode)), "every baseline state"),
        "baseline_learned_h": Span(*BASELINE_LEARNED_SPAN_H, "a learning of up to 1000 h"),
        "baseline_coverage_pct": Span(0.0, 100.0, "a share of the envelope"),
        "baseline_distance_lpm": Span(-leak_max_lpm, leak_max_lpm, "up to the drive's nominal flow either way"),
        "prognosis_state": Span(0.0, 3.0, "every prognosis state"),
        "prognosis_direction": Span(0.0, 2.0, "every trend direction"),
        **{name: Span(*PROGNOSIS_SPAN_H, "up to 4000 operating hours") for name in PROGNOSIS_HOURS},
    }


@dataclass(frozen=True)
class OutputMessage:
    """One output message: its identifier, its signals' layouts (read as ``size`` bytes, sent as
    ``length``), its period in ticks, and ``fill``: bytes ORed into every frame (J1939 sends the bits
    of no signal as 1). ``encode`` makes one frame from physical values."""

    frame_id: int
    extended: bool
    layouts: tuple[Layout, ...]
    size: int
    length: int
    every_ticks: int
    fill: bytes = b""
    encode: Callable[[Mapping[str, float]], bytes] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        fill = int.from_bytes(self.fill.ljust(self.size, b"\0"), "big")
        object.__setattr__(self, "encode", frame_encoder(self.layouts, self.size, self.length, fill))


@dataclass(frozen=True)
class Outputs:
    """The CM messages: the ratio, the output quantity's measured and predicted values (CM_SPEED for
    motor speed, CM_FLOW for flow: ``quantity_signals`` names its signals), the warning."""

    ratio: OutputMessage
    quantity: OutputMessage
    warning: OutputMessage
    channel: str = ""
    quantity_signals: tuple[str, str, str, str] = QUANTITY_SIGNALS[MOTOR_SPEED]
    baseline: OutputMessage | None = None  # CM_BASELINE where the on-board baseline is configured
    prognosis: OutputMessage | None = None  # CM_PROGNOSIS where the prognosis is configured


class Payloads:
    """Builds the frames of each tick; keeps the alive counter and the last warning state sent."""

    __slots__ = ("alive", "last_baseline", "last_prognosis", "last_warning", "outputs")

    def __init__(self, outputs: Outputs) -> None:
        self.outputs = outputs
        self.alive = 0
        self.last_warning = -1  # the warning's level and reason last sent (_warning_key)
        self.last_baseline = -1  # the baseline state last sent (CM_BASELINE goes at once on a change)
        self.last_prognosis = -1  # the prognosis state and direction last sent (likewise CM_PROGNOSIS)

    def continue_from(self, old: Payloads) -> None:
        """Go on with the alive counter and warning state of the payloads this one replaces."""
        self.alive, self.last_warning, self.last_baseline = old.alive, old.last_warning, old.last_baseline
        self.last_prognosis = old.last_prognosis

    def _frame(self, t: float, msg: OutputMessage, values: Mapping[str, float]) -> Frame:
        return Frame(t, self.outputs.channel, msg.frame_id, msg.extended, False, False, False, msg.encode(values))

    def answer(self, last: Frame, t: float) -> Frame:
        """The frame answering a request for an output message: ``last`` (its last frame sent) at ``t``
        with the alive counter's next value where it carries one; the counter moves on, so no
        receiver sees a value twice in a row (the periodic frames after it step by 2 at most)."""
        msg = next(
            (
                m
                for m in self._messages()
                if m.extended == last.extended and (m.frame_id ^ last.arbitration_id) & ~0xFF == 0
            ),
            None,
        )
        lay = None if msg is None else next((x for x in msg.layouts if x.name == ALIVE_SIGNAL), None)
        if msg is None or lay is None:
            return last._replace(timestamp_s=t)
        data = with_raw(bytes(last.data), lay, msg.size, self.alive)
        self.alive = (self.alive + 1) % ALIVE_MODULO
        return last._replace(timestamp_s=t, data=data)

    def _messages(self) -> tuple[OutputMessage, ...]:
        o = self.outputs
        return (o.ratio, o.quantity, o.warning, *(m for m in (o.baseline, o.prognosis) if m is not None))

    def frames(self, k: int, tick: Tick, warning_count: int) -> list[Frame]:
        """The frames of tick ``k``: each message due by its send rule, its values by
        :func:`_values` (the same definitions :meth:`frames_columns` applies over arrays)."""
        o = self.outputs
        out: list[Frame] = []
        periodic_ratio = _due(k, o.ratio)
        values = _values(o, tick, float(self.alive), warning_count)
        if periodic_ratio:
            out.append(self._frame(tick.t_s, o.ratio, values["ratio"]))
        if _due(k, o.quantity):
            out.append(self._frame(tick.t_s, o.quantity, values["quantity"]))
        if periodic_ratio:
            self.alive = (self.alive + 1) % ALIVE_MODULO
        state = _warning_key(tick.level, tick.reason)
        if _due(k, o.warning, state, self.last_warning):
            self.last_warning = state
            out.append(self._frame(tick.t_s, o.warning, values["warning"]))
        bm, pm = o.baseline, o.prognosis
        if bm is not None and _due(k, bm, tick.baseline_state, self.last_baseline):
            self.last_baseline = tick.baseline_state
            out.append(self._frame(tick.t_s, bm, values["baseline"]))
        key = _prognosis_key(tick.prognosis_state, tick.prognosis_direction)
        if pm is not None and _due(k, pm, key, self.last_prognosis):
            self.last_prognosis = key
            out.append(self._frame(tick.t_s, pm, values["prognosis"]))
        return out

    def frames_columns(self, ks: NDArray[np.int64], c: TickColumns, wcount: NDArray[np.int64]) -> FrameColumns:
        """The frames of the ticks ``ks`` (their values ``c``, the warning count after each
        ``wcount``) as :meth:`frames` makes them tick after tick, in that order."""
        o = self.outputs
        is_ratio = _due(ks, o.ratio)
        # the alive counter a tick's frames carry: its value before this tick's ratio frame counts it
        alive = ((self.alive + np.cumsum(is_ratio) - is_ratio) % ALIVE_MODULO).astype(np.float64)
        values = _values(o, c, alive, wcount)
        warning = _warning_key(c.level.astype(np.int64), c.reason.astype(np.int64))
        due_warning = _due(ks, o.warning, warning, _before(warning, self.last_warning))
        parts = [
            _encode(o.ratio, np.flatnonzero(is_ratio), values["ratio"]),
            _encode(o.quantity, np.flatnonzero(_due(ks, o.quantity)), values["quantity"]),
            _encode(o.warning, np.flatnonzero(due_warning), values["warning"]),
        ]
        if o.baseline is not None:
            state = c.baseline_state.astype(np.int64)
            due = _due(ks, o.baseline, state, _before(state, self.last_baseline))
            parts.append(_encode(o.baseline, np.flatnonzero(due), values["baseline"]))
        if o.prognosis is not None:
            key = _prognosis_key(c.prognosis_state.astype(np.int64), c.prognosis_direction.astype(np.int64))
            due = _due(ks, o.prognosis, key, _before(key, self.last_prognosis))
            parts.append(_encode(o.prognosis, np.flatnonzero(due), values["prognosis"]))
        self.skip_columns(ks, c)
        return self._interleave(c.t_s, tuple(parts))

    def skip_columns(self, ks: NDArray[np.int64], c: TickColumns) -> None:
        """The state :meth:`frames_columns` leaves, without making the frames (nobody wants them)."""
        is_ratio = ks % self.outputs.ratio.every_ticks == 0
        self.alive = int((self.alive + int(is_ratio.sum())) % ALIVE_MODULO)
        self.last_warning = int(_warning_key(int(c.level[-1]), int(c.reason[-1])))
        if self.outputs.baseline is not None:
            self.last_baseline = int(c.baseline_state[-1])
        if self.outputs.prognosis is not None:
            self.last_prognosis = int(_prognosis_key(c.prognosis_state[-1], c.prognosis_direction[-1]))

    def _interleave(
        self, t_s: NDArray[np.float64], parts: tuple[tuple[NDArray[np.int64], NDArray[np.uint8]], ...]
    ) -> FrameColumns:
        """Per tick its ratio, quantity, warning and baseline frames, in that order."""
        o = self.outputs
        msgs = (o.ratio, o.quantity, o.warning, *(m for m in (o.baseline, o.prognosis) if m is not None))
        tick_of = np.concatenate([rows for rows, _ in parts])
        kind_of = np.concatenate([np.full(len(rows), k, dtype=np.int64) for k, (rows, _) in enumerate(parts)])
        data = np.zeros((len(tick_of), 8), dtype=np.uint8)
        at = 0
        for rows, payload in parts:
            data[at : at + len(rows), : payload.shape[1]] = payload[:, :8]
            at += len(rows)
        order = np.lexsort((kind_of, tick_of))
        tick_of, kind_of, data = tick_of[order], kind_of[order], data[order]
        no = np.zeros(len(tick_of), dtype=bool)
        return FrameColumns(
            timestamp_s=t_s[tick_of],
            channel=np.zeros(len(tick_of), dtype=np.int16),
            channel_names=(o.channel,),
            arbitration_id=np.array([m.frame_id for m in msgs], dtype=np.uint32)[kind_of],
            extended=np.array([m.extended for m in msgs], dtype=bool)[kind_of],
            remote=no,
            error=no,
            fd=no,
            dlc=np.array([m.length for m in msgs], dtype=np.int16)[kind_of],
            data=data,
        )


def with_raw(data: bytes, lay: Layout, size: int, raw: int) -> bytes:
    """``data`` (a frame of a message of ``size`` bytes) with one signal's bits set to ``raw``."""
    order = "big" if lay.big_endian else "little"  # the word the encoder builds for this byte order
    word = int.from_bytes(data.ljust(size, b"\0"), order) & ~(lay.mask << lay.shift)
    return int(insert(word, raw, lay)).to_bytes(size, order)[: len(data)]


# -- what each message carries and when: one definition for one tick (floats) and for columns ------


def _as_float(x: Any) -> Any:
    return x.astype(np.float64) if isinstance(x, np.ndarray) else float(x)


def _pick(cond: Any, a: Any, b: Any) -> Any:
    """``a`` where ``cond`` holds, else ``b``: for one tick or per tick of columns."""
    return np.where(cond, a, b) if isinstance(cond, np.ndarray) else (a if cond else b)


# numpy's functions over one tick's floats cost a microsecond each: these take the float path there


def _isfinite(x: Any) -> Any:
    return np.isfinite(x) if isinstance(x, np.ndarray) else math.isfinite(x)


def _floor(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return np.floor(x)
    return float(math.floor(x)) if math.isfinite(x) else x


def _at_most(x: Any, hi: float) -> Any:
    """``np.minimum(x, hi)``: NaN stays NaN."""
    return np.minimum(x, hi) if isinstance(x, np.ndarray) else (hi if x > hi else x)


def _due(k: Any, msg: OutputMessage, key: Any = None, last: Any = None) -> Any:
    """A message's send rule at tick ``k`` (an int or an array of ticks): every ``every_ticks``, and
    with a ``key`` (its state) at once on each change from ``last`` (the key last sent; per tick in
    columns, the key of the tick before)."""
    periodic = k % msg.every_ticks == 0
    return periodic if key is None else (key != last) | periodic


def _before(key: NDArray[np.int64], last: int) -> NDArray[np.int64]:
    """Per tick of a stretch, the key of the tick before it (``last``: the one last sent)."""
    prev = np.empty(len(key), dtype=np.int64)
    prev[0] = last
    prev[1:] = key[:-1]
    return prev


def _warning_key(level: Any, reason: Any) -> Any:
    """The warning's level and reason as one number: a change of either sends CM_WARNING at once."""
    return level * 256 + reason


def _prognosis_key(state: Any, direction: Any) -> Any:
    """The prognosis's state and direction as one number: a change of either sends CM_PROGNOSIS at
    once (scalars or arrays)."""
    return state * 4 + direction


def _prognosis_hours(h: Any) -> Any:
    """Hours as CM_PROGNOSIS carries them: 0 without an estimate, saturated where far or never."""
    return _pick(h != h, 0.0, _at_most(h, PROGNOSIS_SPAN_H[1]))


def _values(o: Outputs, c: Tick | TickColumns, alive: Any, warning_count: Any) -> dict[str, dict[str, Any]]:
    """Per message the values of its signals, of one tick (floats) or of a stretch (arrays): the one
    definition of what the CM frames carry."""
    g, valid = c.gate, c.filt_valid
    evaluated = _as_float(is_evaluated(g))
    name_meas, name_pred, name_wb, name_valid = o.quantity_signals
    out = {
        "ratio": {
            "cm_ratio_raw_pct": c.ratio_raw_pct,
            "cm_ratio_filt_pct": _pick(valid, c.ratio_filt_pct, 0.0),
            "extra_leakage_lpm": _pick(valid, c.extra_leak_lpm, 0.0),
            "cm_raw_valid": evaluated,
            "cm_filt_valid": _as_float(valid),
            "cm_gate": _as_float(g),
            "cm_alive_counter": alive,
        },
        "quantity": {
            name_meas: _pick(_isfinite(c.measured), c.measured, 0.0),
            name_pred: c.predicted,
            name_wb: c.whitebox,
            name_valid: evaluated,
            "cm_alive_counter": alive,
        },
        "warning": {
            "warning_level": _as_float(c.level),
            "warning_reason": _as_float(c.reason),
            "time_below_threshold_s": _as_float(_floor(c.time_below_s)),
            "warning_count": _as_float(warning_count % WARNING_COUNT_MODULO),
        },
    }
    if o.baseline is not None:
        out["baseline"] = {
            "baseline_state": _as_float(c.baseline_state),
            "baseline_learned_h": _at_most(c.baseline_learned_h, BASELINE_LEARNED_SPAN_H[1]),
            "baseline_coverage_pct": c.baseline_coverage_pct,
            "baseline_distance_lpm": c.baseline_distance_lpm,
        }
    if o.prognosis is not None:
        out["prognosis"] = {
            "prognosis_state": _as_float(c.prognosis_state),
            "prognosis_direction": _as_float(c.prognosis_direction),
            **{name: _prognosis_hours(getattr(c, name)) for name in PROGNOSIS_HOURS},
        }
    return out


def _encode(
    msg: OutputMessage, rows: NDArray[np.int64], values: dict[str, NDArray[np.float64]]
) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
    """Payloads of ``msg`` for the tick rows (n, length), as its per-frame encoder gives them."""
    if msg.length > 8:
        raise ValueError("an output message longer than 8 bytes: the array path writes classic frames")
    data = encode_all(msg.layouts, msg.size, msg.length, {k: v[rows] for k, v in values.items()})
    if msg.fill:  # J1939: the bits of no signal sent as 1
        data |= np.frombuffer(msg.fill, dtype=np.uint8)[None, : msg.length]
    return rows, data
