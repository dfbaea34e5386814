"""Candidate unmodelled effects: physical terms that can be added to the simulator, with parameters.

Each effect maps the measured inputs and its parameters to the simulated output with the effect
added. Leakages are stated as l/min at a reference point (300 bar, 50 C), the way a test rig would
report them, so fitted values read as physical quantities.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from cmcan.sim.physics import DriveParams, UnitLosses, steady_motor_speed_rpm

REF_DP_BAR = 300.0
REF_TEMP_C = 50.0


@dataclass(frozen=True)
class Inputs:
    """Measured inputs at the analysis points (block means), with the segment each point is in."""

    t_s: NDArray[np.float64]
    pump_speed_rpm: NDArray[np.float64]
    pump_disp_cc: NDArray[np.float64]
    dp_bar: NDArray[np.float64]
    temp_c: NDArray[np.float64]
    dp_rate_bar_s: NDArray[np.float64]  # d(dp)/dt, for the line-compressibility flow
    segment: NDArray[np.int64]

    def subset(self, mask: NDArray[np.bool_]) -> Inputs:
        return Inputs(*(getattr(self, f)[mask] for f in self.__dataclass_fields__))


@dataclass(frozen=True)
class Param:
    name: str
    unit: str
    plausible: tuple[float, float]
    start: float
    bound_lo: float = -np.inf  # hard limit of the fit (a time constant cannot be negative)


def base_output(
    p: DriveParams,
    x: Inputs,
    extra_leak_lpm: NDArray[np.float64] | float = 0.0,
    disp_offset_cc: float = 0.0,
    motor_disp_factor: float = 1.0,
) -> NDArray[np.float64]:
    """The simulator on measured inputs: the flow balance at the measured pressure, minus the flow
    the high-pressure line takes to build pressure up (V_line / K * d(dp)/dt) and what the relief
    valve lets through above its setting."""
    line_lpm = p.line_volume_l / p.bulk_modulus_bar * x.dp_rate_bar_s * 60.0
    relief_lpm = p.relief_gain_lpm_per_bar * np.clip(x.dp_bar - p.relief_dp_bar, 0.0, None)
    return steady_motor_speed_rpm(
        p,
        x.pump_speed_rpm,
        x.pump_disp_cc - disp_offset_cc,
        x.dp_bar,
        x.temp_c,
        extra_leak_lpm=np.asarray(extra_leak_lpm) + line_lpm + relief_lpm,
        motor_disp_factor=motor_disp_factor,
    )


def first_order_lag(
    y: NDArray[np.float64], t: NDArray[np.float64], segment: NDArray[np.int64], tau_s: float
) -> NDArray[np.float64]:
    """What a sensor with time constant ``tau_s`` reports for ``y`` (exact for a hold between points)."""
    if tau_s <= 0:
        return y.copy()
    out = np.empty_like(y)
    dt = np.diff(t, prepend=t[0])
    a = np.exp(-dt / tau_s)
    new_seg = np.r_[True, segment[1:] != segment[:-1]]
    acc = y[0]
    yl, al, nl = y.tolist(), a.tolist(), new_seg.tolist()
    for i in range(len(yl)):
        acc = yl[i] if nl[i] else al[i] * acc + (1.0 - al[i]) * yl[i]
        out[i] = acc
    return out


@dataclass
class Mods:
    """What the added effects change in the simulator, accumulated over all of them."""

    extra_leak_lpm: NDArray[np.float64] | float = 0.0
    compress_add: float = 0.0
    disp_offset_cc: float = 0.0
    motor_disp_factor: float = 1.0
    lag_tau_s: float = 0.0


@dataclass(frozen=True)
class Effect:
    name: str
    formula: str
    description: str
    params: tuple[Param, ...]
    apply: Callable[[DriveParams, Inputs, NDArray[np.float64], Mods], None]

    def describe(self) -> dict:
        return {
            "name": self.name,
            "formula": self.formula,
            "description": self.description,
            "parameters": [{"name": q.name, "unit": q.unit, "plausible": list(q.plausible)} for q in self.params],
        }


def simulate(p: DriveParams, x: Inputs, effects: list[tuple[Effect, NDArray[np.float64]]]) -> NDArray[np.float64]:
    """The simulator on measured inputs with ``effects`` (each with its parameter vector) added."""
    m = Mods()
    for eff, th in effects:
        eff.apply(p, x, th, m)
    if m.compress_add:
        pump = p.pump
        p = replace(p, pump=UnitLosses(pump.laminar_cs, pump.turbulent_ct, pump.compress_factor + m.compress_add))
    y = base_output(p, x, m.extra_leak_lpm, m.disp_offset_cc, m.motor_disp_factor)
    return first_order_lag(y, x.t_s, x.segment, m.lag_tau_s) if m.lag_tau_s > 0 else y


def _mu_ratio(p: DriveParams, temp_c: NDArray[np.float64]) -> NDArray[np.float64]:
    return float(p.oil.dynamic_viscosity_pa_s(REF_TEMP_C)) / p.oil.dynamic_viscosity_pa_s(temp_c)


def _laminar(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.extra_leak_lpm = m.extra_leak_lpm + th[0] * x.dp_bar / REF_DP_BAR * _mu_ratio(p, x.temp_c)


def _pressure(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.extra_leak_lpm = m.extra_leak_lpm + th[0] * x.dp_bar / REF_DP_BAR


def _turbulent(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.extra_leak_lpm = m.extra_leak_lpm + th[0] * np.sign(x.dp_bar) * np.sqrt(np.abs(x.dp_bar) / REF_DP_BAR)


def _compress(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.compress_add += float(th[0])


def _lag(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.lag_tau_s = max(float(th[0]), 0.0)


def _disp_offset(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.disp_offset_cc += float(th[0])


def _motor_disp(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.motor_disp_factor *= 1.0 + float(th[0]) / 100.0


LIBRARY: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "laminar_leakage",
            "Q = q_ref * (dp / 300 bar) * (mu(50 C) / mu(T))",
            "gap flow in a rotating group (Wilson): grows with pressure and with thinner, hotter oil",
            (Param("q_ref_lpm", "l/min at 300 bar, 50 C", (0.0, 60.0), 1.0),),
            _laminar,
        ),
        Effect(
            "pressure_leakage",
            "Q = q_ref * (dp / 300 bar)",
            "leakage proportional to pressure and independent of viscosity",
            (Param("q_ref_lpm", "l/min at 300 bar", (0.0, 60.0), 1.0),),
            _pressure,
        ),
        Effect(
            "turbulent_leakage",
            "Q = q_ref * sqrt(dp / 300 bar)",
            "orifice-like leakage (Schloesser): grows with the square root of pressure",
            (Param("q_ref_lpm", "l/min at 300 bar", (0.0, 60.0), 1.0),),
            _turbulent,
        ),
        Effect(
            "compressibility",
            "Q = f * n_P * V_P * dp / K",
            "oil compressed in the pump's dead volume, on top of the modelled share",
            (Param("factor", "share of n_P V_P dp / K", (0.0, 3.0), 0.1),),
            _compress,
        ),
        Effect(
            "motor_speed_lag",
            "n_meas' = (n_true - n_meas) / tau",
            "the motor speed reading lags the true speed (sensor or filter time constant)",
            (Param("tau_s", "s", (0.005, 2.0), 0.1, bound_lo=0.0),),
            _lag,
        ),
        Effect(
            "disp_sensor_offset",
            "V_P,true = V_P,meas - offset",
            "the pump displacement reading has a zero offset",
            (Param("offset_cc", "cm3/rev", (-8.0, 8.0), 0.1),),
            _disp_offset,
        ),
        Effect(
            "motor_disp_offset",
            "V_M,true = V_M * (1 + pct / 100)",
            "the motor's real displacement differs from nominal: a constant factor on speed",
            (Param("pct", "%", (-15.0, 15.0), 0.1),),
            _motor_disp,
        ),
    )
}
