"""The CM output frames of an evaluated tick: which messages are due, their signal values, encoding.

Kept apart from the evaluation so that what the ratio *is* and how the bus *carries* it change
independently (another DBC, other periods, another channel).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from cmcan.codec import Layout, frame_encoder
from cmcan.frame import Frame
from cmcan.monitor.gating import EVALUATED
from cmcan.monitor.tick import Tick
from cmcan.roles import MOTOR_SPEED, QUANTITY_SIGNALS

ALIVE_MODULO = 16


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


class Payloads:
    """Builds the frames of each tick; keeps the alive counter and the last warning state sent."""

    __slots__ = ("alive", "last_warning", "outputs")

    def __init__(self, outputs: Outputs) -> None:
        self.outputs = outputs
        self.alive = 0
        self.last_warning: tuple[int, int] | None = None

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
                        "warning_count": float(warning_count % 65536),
                    },
                )
            )
        return out
