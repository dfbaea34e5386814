"""Sensor errors: what a miscalibrated or slow transducer reports for the true value.

The most common sim-to-real gap in the field is not missing physics but a sensor that reads off: a zero
offset, a gain (span) error or a time constant. A scenario states them per channel
(``sensors.errors``); the gap bench uses them to put a sensor error into the dynamic simulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class SensorError:
    """reading = (1 + gain_pct / 100) * lagged(true) + offset; lag a first-order time constant."""

    offset: float = 0.0
    gain_pct: float = 0.0
    lag_s: float = 0.0

    @property
    def any(self) -> bool:
        return self.offset != 0.0 or self.gain_pct != 0.0 or self.lag_s != 0.0

    def apply(self, true: NDArray[np.float64], dt_s: float, bursts: list[tuple[int, int]]) -> NDArray[np.float64]:
        x = first_order_lag(true, dt_s, self.lag_s, bursts) if self.lag_s > 0 else np.asarray(true, dtype=float)
        return x * (1.0 + self.gain_pct / 100.0) + self.offset


def first_order_lag(
    x: NDArray[np.float64], dt_s: float, tau_s: float, bursts: list[tuple[int, int]]
) -> NDArray[np.float64]:
    """A first-order sensor (exact for a hold between samples); each burst starts settled."""
    a = math.exp(-dt_s / tau_s)
    b = 1.0 - a
    out = np.asarray(x, dtype=float).copy()
    for lo, hi in bursts:
        if hi <= lo:
            continue
        seg = out[lo:hi].tolist()  # a plain loop over floats: no scipy in the simulator
        acc = seg[0]
        for k, v in enumerate(seg):
            acc = a * acc + b * v
            seg[k] = acc
        out[lo:hi] = seg
    return out
