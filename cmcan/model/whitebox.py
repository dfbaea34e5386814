"""The white-box law n_M = n_P * V_P / V_M * eta_vol_P * eta_vol_M and its "light gray" fit.

From motor speed alone only the product of the two volumetric efficiencies is identifiable; it is
fitted by least squares through the origin on steady training points.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def ideal_motor_speed_rpm(
    pump_speed_rpm: NDArray[np.float64], pump_disp_cc: NDArray[np.float64], motor_disp_cc: float
) -> NDArray[np.float64]:
    return np.abs(pump_speed_rpm) * np.abs(pump_disp_cc) / motor_disp_cc


def fit_eta_vol(ideal_rpm: NDArray[np.float64], measured_rpm: NDArray[np.float64]) -> float:
    """Least-squares constant efficiency product: argmin || measured - eta * ideal ||."""
    denom = float(np.dot(ideal_rpm, ideal_rpm))
    if denom <= 0:
        raise ValueError("no flow in the training data: cannot fit volumetric efficiency")
    return float(np.dot(ideal_rpm, measured_rpm) / denom)


def whitebox_rpm(x: NDArray[np.float64], motor_disp_cc: float, eta_vol: float) -> NDArray[np.float64]:
    """White-box prediction for model inputs ``x`` (n, 4) in MODEL_INPUTS order."""
    return eta_vol * ideal_motor_speed_rpm(x[:, 0], x[:, 1], motor_disp_cc)
