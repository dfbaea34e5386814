"""The gray box's theoretical part ("light gray"): the ideal flow law plus leakage terms of physical form.

Delivered flow (l/min) at the motor, or at the flow meter of an open circuit:

    Q = c_geo * Q_geo - c_lam * dp / nu(T) - c_turb * sqrt(dp) - c_comp * Q_geo * dp / 1000

with Q_geo = |n_P| |V_P| / 1000 the ideal pump flow, nu(T) the oil's kinematic viscosity (ASTM D341,
cSt) for laminar gap leakage, sqrt(dp) for turbulent (orifice) leakage, and Q_geo dp for the oil
compressed in pump and motor. Each coefficient is non-negative (a leak never adds flow), fitted by
non-negative least squares: a convex problem with one solution, so training is reproducible, and a
law that extrapolates in pressure and temperature where data-driven fits do not. A closed circuit's
motor speed is the same flow over V_M.

Real training data often leave a coefficient undetermined: a test rig whose pressure varies by 1 %
cannot tell a pressure slope from whatever else moved with the pressure. The fit therefore carries
physical priors (a Gaussian on each coefficient, a ridge penalty towards it, still one convex NNLS):
the ideal flow as configured (c_geo = 1 +- 10 %), each leakage term within about 10 % of the flow
(what a healthy piston unit loses), the compressibility of mineral oil (1000 / K, K ~ 15000 bar,
+- 100 %). The data's weight is 1 / sigma^2 per point, sigma the residual of the fit without priors,
so wherever the data determine a coefficient (hundreds of points spread over the envelope) they
decide it, and the priors only hold the directions the data cannot see.

The plain white-box law n_M = n_P V_P / V_M * eta_vol (one efficiency fitted through the origin) is
kept beside it as the baseline the gray box is judged against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cmcan.oil import Oil

TERMS: tuple[str, ...] = ("ideal_flow", "laminar", "turbulent", "compressibility")


@dataclass(frozen=True)
class Quantity:
    """What the model predicts: a closed circuit's motor speed or an open circuit's delivered flow."""

    role: str  # "motor_speed_rpm" or "flow_lpm"
    motor_disp_cc: float | None  # V_M for motor speed; None for flow

    @property
    def unit(self) -> str:
        return "rpm" if self.role == "motor_speed_rpm" else "l/min"

    @property
    def lpm_per_unit(self) -> float:
        """Flow in l/min per unit of the quantity: V_M / 1000 for motor speed, 1 for flow."""
        if self.role == "motor_speed_rpm":
            assert self.motor_disp_cc is not None
            return self.motor_disp_cc / 1000.0
        return 1.0


def ideal_flow_lpm(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """|n_P| |V_P| / 1000 for model inputs ``x`` (n, 4): pump speed, pump displacement, dp, temperature."""
    return np.abs(x[:, 0]) * np.abs(x[:, 1]) / 1000.0


def features(x: NDArray[np.float64], oil: Oil) -> NDArray[np.float64]:
    """The columns whose non-negative combination is the delivered flow, in the order of ``TERMS``."""
    qg = ideal_flow_lpm(x)
    dp = x[:, 2]
    nu = oil.kinematic_viscosity_cst(x[:, 3])
    return np.column_stack([qg, -dp / nu, -np.sign(dp) * np.sqrt(np.abs(dp)), -qg * dp / 1000.0])


# The priors (mean, standard deviation) of the coefficients; see the module's docstring.
IDEAL_FLOW_PRIOR = (1.0, 0.1)
LEAK_SHARE = 0.1  # prior std of each leakage term: this share of the mean flow, at the mean training point
BULK_MODULUS_BAR = 15000.0
SIGMA_FLOOR = 1e-6  # relative to the mean flow: noiseless data still weigh finitely


def _nnls(a: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    from scipy.optimize import nnls

    # Columns scaled to unit RMS: the same solution, better conditioned, so another BLAS agrees.
    scale = np.sqrt(np.mean(a * a, axis=0))
    scale[scale == 0.0] = 1.0
    coef, _ = nnls(a / scale, y, maxiter=50 * a.shape[1])
    return coef / scale


def priors(a: NDArray[np.float64], flow_lpm: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Prior mean and standard deviation of each coefficient for the feature columns ``a``."""
    q = float(np.mean(np.abs(flow_lpm)))
    col = np.mean(np.abs(a), axis=0)
    comp = 1000.0 / BULK_MODULUS_BAR
    mean = np.array([IDEAL_FLOW_PRIOR[0], 0.0, 0.0, comp])
    leak = [LEAK_SHARE * q / c if c > 0 and q > 0 else 1.0 for c in col[1:3]]
    std = np.array([IDEAL_FLOW_PRIOR[1], *leak, comp])
    return mean, std


def fit_coefficients(x: NDArray[np.float64], flow_lpm: NDArray[np.float64], oil: Oil) -> NDArray[np.float64]:
    """The coefficients of :func:`features` by non-negative least squares with the physical priors
    (needs scipy): rows ``a / sigma`` for the data, ``1 / std`` for the priors."""
    a = features(x, oil)
    y = np.asarray(flow_lpm, dtype=np.float64)
    free = _nnls(a, y)
    sigma = max(float(np.sqrt(np.mean((a @ free - y) ** 2))), SIGMA_FLOOR * float(np.mean(np.abs(y))), 1e-12)
    mean, std = priors(a, y)
    aug = np.vstack([a / sigma, np.diag(1.0 / std)])
    return _nnls(aug, np.concatenate([y / sigma, mean / std]))


# A coefficient this many prior standard deviations from its prior is no healthy drive of the
# configured size: data in other units, a wrong displacement, or data that cannot tell terms apart.
PRIOR_WARN_SIGMAS = 5.0


def prior_doubts(
    x: NDArray[np.float64], flow_lpm: NDArray[np.float64], coef: NDArray[np.float64], oil: Oil
) -> list[str]:
    """One sentence per fitted coefficient more than ``PRIOR_WARN_SIGMAS`` prior standard deviations
    from its prior (none for a fit the physics believes)."""
    mean, std = priors(features(x, oil), np.asarray(flow_lpm, dtype=np.float64))
    out = []
    for term, c, m, s in zip(TERMS, coef, mean, std, strict=True):
        z = (float(c) - m) / s
        if abs(z) > PRIOR_WARN_SIGMAS:
            out.append(
                f"physics term {term} = {c:.4g} is {abs(z):.1f} prior standard deviations "
                f"{'above' if z > 0 else 'below'} its prior {m:.4g} +- {s:.3g}"
                + (
                    ": the flow is not the configured pump's (check the data's units and the pump displacement)"
                    if term == "ideal_flow"
                    else ": more than a healthy unit loses (check units, or whether the data separate this term)"
                )
            )
    return out


def flow_lpm(x: NDArray[np.float64], coef: NDArray[np.float64], oil: Oil) -> NDArray[np.float64]:
    return features(x, oil) @ coef


def fit_eta_vol(x: NDArray[np.float64], flow_lpm: NDArray[np.float64]) -> float:
    """The white-box law's one efficiency: argmin || Q - eta * Q_geo || (through the origin)."""
    qg = ideal_flow_lpm(x)
    denom = float(np.dot(qg, qg))
    if denom <= 0:
        raise ValueError("no flow in the training data: cannot fit volumetric efficiency")
    return float(np.dot(qg, flow_lpm) / denom)
