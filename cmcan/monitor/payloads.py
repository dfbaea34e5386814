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

from cmcan.codec import Layout, encode_all, frame_encoder
from cmcan.frame import Frame, FrameColumns
from cmcan.monitor.baseline import Mode
from cmcan.monitor.gating import EVALUATED, Gate
from cmcan.monitor.tick import PROGNOSIS_HOURS, Tick, TickColumns
from cmcan.monitor.warnings import Level, Reason
from cmcan.roles import MOTOR_SPEED, QUANTITY_SIGNALS

_EVALUATED = np.array(sorted(int(g) for g in EVALUATED), dtype=np.int8)
ALIVE_MODULO = 16
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
        self.last_warning: tuple[int, int] | None = None
        self.last_baseline = -1  # the baseline state last sent (CM_BASELINE goes at once on a change)
        self.last_prognosis = -1  # the prognosis state and direction last sent (likewise CM_PROGNOSIS)

    def continue_from(self, old: Payloads) -> None:
        """Go on with the alive counter and warning state of the payloads this one replaces."""
        self.alive, self.last_warning, self.last_baseline = old.alive, old.last_warning, old.last_baseline
        self.last_prognosis = old.last_prognosis

    def _frame(self, t: float, msg: OutputMessage, values: Mapping[str, float]) -> Frame:
        return Frame(t, self.outputs.channel, msg.frame_id, msg.extended, False, False, False, msg.encode(values))

    def frames(self, k: int, tick: Tick, warning_count: int) -> list[Frame]:
        o = self.outputs
        out = []
        evaluated = tick.gate in EVALUATED
        if k % o.ratio.every_ticks == 0:
            out.append(
                self._frame(
                    tick.t_s,
                    o.ratio,
                    {
                        "cm_ratio_raw_pct": tick.ratio_raw_pct,
                        "cm_ratio_filt_pct": tick.ratio_filt_pct if tick.filt_valid else 0.0,
                        "extra_leakage_lpm": tick.extra_leak_lpm if tick.filt_valid else 0.0,
                        "cm_raw_valid": float(evaluated),
                        "cm_filt_valid": float(tick.filt_valid),
                        "cm_gate": float(int(tick.gate)),
                        "cm_alive_counter": float(self.alive),
                    },
                )
            )
        if k % o.quantity.every_ticks == 0:
            meas = tick.measured
            name_meas, name_pred, name_wb, name_valid = o.quantity_signals
            out.append(
                self._frame(
                    tick.t_s,
                    o.quantity,
                    {
                        name_meas: meas if math.isfinite(meas) else 0.0,
                        name_pred: tick.predicted,
                        name_wb: tick.whitebox,
                        name_valid: float(evaluated),
                        "cm_alive_counter": float(self.alive),
                    },
                )
            )
        if k % o.ratio.every_ticks == 0:
            self.alive = (self.alive + 1) % ALIVE_MODULO
        state = (int(tick.level), int(tick.reason))
        if state != self.last_warning or k % o.warning.every_ticks == 0:
            self.last_warning = state
            out.append(
                self._frame(
                    tick.t_s,
                    o.warning,
                    {
                        "warning_level": float(int(tick.level)),
                        "warning_reason": float(int(tick.reason)),
                        "time_below_threshold_s": float(int(tick.time_below_s)),
                        "warning_count": float(warning_count % WARNING_COUNT_MODULO),
                    },
                )
            )
        if o.baseline is not None or o.prognosis is not None:
            self._stage_frames(k, tick, out)
        return out

    def _stage_frames(self, k: int, tick: Tick, out: list[Frame]) -> None:
        """CM_BASELINE and CM_PROGNOSIS where configured: on each change of their state, and periodically."""
        bm, pm = self.outputs.baseline, self.outputs.prognosis
        if bm is not None and (tick.baseline_state != self.last_baseline or k % bm.every_ticks == 0):
            self.last_baseline = tick.baseline_state
            out.append(self._frame(tick.t_s, bm, _baseline_values(tick)))
        key = _prognosis_key(tick.prognosis_state, tick.prognosis_direction)
        if pm is not None and (key != self.last_prognosis or k % pm.every_ticks == 0):
            self.last_prognosis = key
            out.append(self._frame(tick.t_s, pm, _prognosis_values(tick)))

    def frames_columns(self, ks: NDArray[np.int64], c: TickColumns, wcount: NDArray[np.int64]) -> FrameColumns:
        """The frames of the ticks ``ks`` (their values ``c``, the warning count after each
        ``wcount``) as :meth:`frames` makes them tick after tick, in that order."""
        o = self.outputs
        is_ratio = ks % o.ratio.every_ticks == 0
        # the alive counter a tick's frames carry: its value before this tick's ratio frame counts it
        alive = ((self.alive + np.cumsum(is_ratio) - is_ratio) % ALIVE_MODULO).astype(np.float64)
        state = c.level.astype(np.int64) * 256 + c.reason.astype(np.int64)
        prev = np.empty(len(ks), dtype=np.int64)
        prev[0] = -1 if self.last_warning is None else self.last_warning[0] * 256 + self.last_warning[1]
        prev[1:] = state[:-1]
        prev_baseline, prev_prognosis = self.last_baseline, self.last_prognosis
        self.skip_columns(ks, c)
        evaluated = np.isin(c.gate, _EVALUATED).astype(np.float64)
        valid = c.filt_valid
        name_meas, name_pred, name_wb, name_valid = o.quantity_signals
        parts = (
            _encode(
                o.ratio,
                np.flatnonzero(is_ratio),
                {
                    "cm_ratio_raw_pct": c.ratio_raw_pct,
                    "cm_ratio_filt_pct": np.where(valid, c.ratio_filt_pct, 0.0),
                    "extra_leakage_lpm": np.where(valid, c.extra_leak_lpm, 0.0),
                    "cm_raw_valid": evaluated,
                    "cm_filt_valid": valid.astype(np.float64),
                    "cm_gate": c.gate.astype(np.float64),
                    "cm_alive_counter": alive,
                },
            ),
            _encode(
                o.quantity,
                np.flatnonzero(ks % o.quantity.every_ticks == 0),
                {
                    name_meas: np.where(np.isfinite(c.measured), c.measured, 0.0),
                    name_pred: c.predicted,
                    name_wb: c.whitebox,
                    name_valid: evaluated,
                    "cm_alive_counter": alive,
                },
            ),
            _encode(
                o.warning,
                np.flatnonzero((state != prev) | (ks % o.warning.every_ticks == 0)),
                {
                    "warning_level": c.level.astype(np.float64),
                    "warning_reason": c.reason.astype(np.float64),
                    "time_below_threshold_s": np.floor(c.time_below_s),
                    "warning_count": (wcount % WARNING_COUNT_MODULO).astype(np.float64),
                },
            ),
        )
        if o.baseline is not None:
            parts = (*parts, _baseline_part(o.baseline, ks, c, prev_baseline))
        if o.prognosis is not None:
            parts = (*parts, _prognosis_part(o.prognosis, ks, c, prev_prognosis))
        return self._interleave(c.t_s, parts)

    def skip_columns(self, ks: NDArray[np.int64], c: TickColumns) -> None:
        """The state :meth:`frames_columns` leaves, without making the frames (nobody wants them)."""
        is_ratio = ks % self.outputs.ratio.every_ticks == 0
        self.alive = int((self.alive + int(is_ratio.sum())) % ALIVE_MODULO)
        self.last_warning = (int(c.level[-1]), int(c.reason[-1]))
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


def _baseline_values(tick: Tick) -> dict[str, float]:
    """CM_BASELINE's signals of one tick."""
    return {
        "baseline_state": float(tick.baseline_state),
        "baseline_learned_h": min(tick.baseline_learned_h, BASELINE_LEARNED_SPAN_H[1]),
        "baseline_coverage_pct": tick.baseline_coverage_pct,
        "baseline_distance_lpm": tick.baseline_distance_lpm,
    }


def _baseline_part(
    msg: OutputMessage, ks: NDArray[np.int64], c: TickColumns, prev_state: int
) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
    """CM_BASELINE of a stretch of ticks: on each change of state (``prev_state``: the one last sent)
    and every ``every_ticks``, as :meth:`Payloads.frames` sends it tick after tick."""
    state = c.baseline_state.astype(np.int64)
    prev = np.empty(len(ks), dtype=np.int64)
    prev[0] = prev_state
    prev[1:] = state[:-1]
    values = {
        "baseline_state": state.astype(np.float64),
        "baseline_learned_h": np.minimum(c.baseline_learned_h, BASELINE_LEARNED_SPAN_H[1]),
        "baseline_coverage_pct": c.baseline_coverage_pct,
        "baseline_distance_lpm": c.baseline_distance_lpm,
    }
    return _encode(msg, np.flatnonzero((state != prev) | (ks % msg.every_ticks == 0)), values)


def _prognosis_hours(h: float) -> float:
    """Hours as CM_PROGNOSIS carries them: 0 without an estimate, saturated where far or never."""
    return 0.0 if math.isnan(h) else min(h, PROGNOSIS_SPAN_H[1])


def _prognosis_values(tick: Tick) -> dict[str, float]:
    """CM_PROGNOSIS's signals of one tick."""
    return {
        "prognosis_state": float(tick.prognosis_state),
        "prognosis_direction": float(tick.prognosis_direction),
        **{name: _prognosis_hours(getattr(tick, name)) for name in PROGNOSIS_HOURS},
    }


def _prognosis_part(
    msg: OutputMessage, ks: NDArray[np.int64], c: TickColumns, prev_state: int
) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
    """CM_PROGNOSIS of a stretch of ticks, on each change of state and every ``every_ticks``."""
    state = c.prognosis_state.astype(np.int64)
    key = _prognosis_key(state, c.prognosis_direction.astype(np.int64))
    prev = np.empty(len(ks), dtype=np.int64)
    prev[0] = prev_state
    prev[1:] = key[:-1]
    values = {
        "prognosis_state": state.astype(np.float64),
        "prognosis_direction": c.prognosis_direction.astype(np.float64),
    }
    for name in PROGNOSIS_HOURS:
        h = getattr(c, name)
        values[name] = np.where(np.isnan(h), 0.0, np.minimum(h, PROGNOSIS_SPAN_H[1]))
    return _encode(msg, np.flatnonzero((key != prev) | (ks % msg.every_ticks == 0)), values)


def _prognosis_key(state: Any, direction: Any) -> Any:
    """The prognosis's state and direction as one number: a change of either sends CM_PROGNOSIS at
    once (scalars or arrays)."""
    return state * 4 + direction


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
