"""An operating point's prediction, CM ratio and extra leakage: steps 3 and 4 of a tick.

A point the gate lets through (``EVALUATING`` or ``EXTRAPOLATED``) gets one model call. A prediction
that is not a positive finite number within the output's plausible range
(:func:`cmcan.monitor.gating.prediction_ok`) makes the point ``MODEL_ERROR`` (counted in
``model_errors``); a model that raises is such an error too, never the monitor's end. Otherwise the
raw ratio is measured / predicted * 100 and the extra leakage (predicted - measured) * ``lpm_per_unit``
(counted in ``evaluated``, and ``extrapolated`` outside the envelope).

One point (:meth:`Ratio.point`) or every tick of a stretch in one batched model call
(:meth:`Ratio.points`). onnxruntime rounds a row of a batch and a row alone alike only to about
1e-15 relative, far below anything the outputs carry (0.01 % ratio resolution).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np
from numpy.typing import NDArray

from cmcan.monitor.gating import EVALUATED, Gate, GateLimits, is_evaluated, prediction_ok
from cmcan.roles import DP, MODEL_INPUTS, PUMP_DISP, PUMP_SPEED, TEMP

COUNTED = ("evaluated", "extrapolated", "model_errors")


class Predictor(Protocol):
    def predict_one(
        self, pump_speed_rpm: float, pump_disp_cc: float, dp_bar: float, temp_c: float
    ) -> tuple[float, float]: ...

    def predict(self, x: NDArray[np.float64]) -> tuple[Any, Any]: ...


class Point(NamedTuple):  # (one a tick: a frozen dataclass's init costs microseconds)
    """One tick's point: its gate after the model call, the measured output, the prediction and its
    white-box part, the raw ratio (0 unless evaluated) and the extra leakage."""

    gate: Gate
    measured: float
    predicted: float
    whitebox: float
    ratio_raw_pct: float
    leak_lpm: float

    @property
    def evaluated(self) -> bool:
        return self.gate in EVALUATED


@dataclass(frozen=True)
class Points:
    """:class:`Point` at every tick of a stretch; ``evaluated`` holds the indexes of the evaluated ticks,
    ``leak_lpm`` their extra leakage."""

    gate: NDArray[np.int8]
    measured: NDArray[np.float64]
    predicted: NDArray[np.float64]
    whitebox: NDArray[np.float64]
    ratio_raw_pct: NDArray[np.float64]
    evaluated: NDArray[np.int64]
    leak_lpm: NDArray[np.float64]


def ratio_and_leak(measured: Any, predicted: Any, lpm_per_unit: float) -> tuple[Any, Any]:
    """The raw CM ratio (%) and the extra leakage (l/min) of the measured output against a
    prediction: floats or arrays alike (the one definition of both)."""
    return measured / predicted * 100.0, (predicted - measured) * lpm_per_unit


def corrected_prediction(predicted: Any, correction_lpm: Any, lpm_per_unit: float) -> tuple[Any, Any]:
    """The type model's prediction plus the machine's own correction (l/min, the on-board baseline),
    and whether it is usable (positive; where not, the type model's prediction stands): floats or
    arrays alike."""
    corrected = predicted + correction_lpm / lpm_per_unit
    return corrected, corrected > 0.0


class Ratio:
    def __init__(self, model: Predictor, limits: GateLimits, lpm_per_unit: float) -> None:
        self.model = model
        self.limits = limits
        self.lpm_per_unit = lpm_per_unit
        self.counts = dict.fromkeys(COUNTED, 0)

    def point(self, mean: Mapping[str, float], count: Mapping[str, int], gate: Gate) -> Point:
        out = self.limits.output_role
        meas = mean[out] if count[out] else 0.0
        if gate not in EVALUATED:
            return Point(gate, meas, 0.0, 0.0, 0.0, 0.0)
        try:
            pred, wb = self.model.predict_one(mean[PUMP_SPEED], mean[PUMP_DISP], mean[DP], mean[TEMP])
        except Exception:  # a model that fails must not take the daemon down
            pred, wb = math.nan, 0.0
        if not prediction_ok(pred, self.limits):
            self.counts["model_errors"] += 1
            return Point(Gate.MODEL_ERROR, meas, 0.0, 0.0, 0.0, 0.0)
        self.counts["evaluated"] += 1
        if gate == Gate.EXTRAPOLATED:
            self.counts["extrapolated"] += 1
        return Point(gate, meas, pred, wb, *ratio_and_leak(meas, pred, self.lpm_per_unit))

    def points(
        self, mean: Mapping[str, NDArray[np.float64]], count: Mapping[str, NDArray[np.int64]], gates: NDArray[np.int8]
    ) -> Points:
        out = self.limits.output_role
        n = len(gates)
        meas = np.where(count[out] > 0, mean[out], 0.0)
        pred, wb = np.zeros(n), np.zeros(n)
        ev = np.flatnonzero(is_evaluated(gates))
        if len(ev):
            x = np.column_stack([mean[r][ev] for r in MODEL_INPUTS])
            try:
                pe, we = self.model.predict(x)
            except Exception:  # as one point: a failing model call is a model error
                pe, we = np.full(len(ev), np.nan), np.zeros(len(ev))
            pe = np.asarray(pe, dtype=np.float64)
            bad = ~prediction_ok(pe, self.limits)
            self.counts["model_errors"] += int(bad.sum())
            gates[ev[bad]] = Gate.MODEL_ERROR
            pred[ev] = np.where(bad, 0.0, pe)
            wb[ev] = np.where(bad, 0.0, we)
        e_idx = np.flatnonzero(is_evaluated(gates))
        raw = np.zeros(n)
        raw[e_idx], leak = ratio_and_leak(meas[e_idx], pred[e_idx], self.lpm_per_unit)
        self.counts["evaluated"] += len(e_idx)
        self.counts["extrapolated"] += int(np.count_nonzero(gates[e_idx] == Gate.EXTRAPOLATED))
        return Points(gates, meas, pred, wb, raw, e_idx, leak)
