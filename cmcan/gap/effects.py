"""Candidate unmodelled effects: physical terms and sensor errors that can be added to the simulator.

Each effect maps the measured inputs and its parameters to the simulated output with the effect
added. Leakages are stated as l/min at a reference point (300 bar, 50 C), the way a test rig would
report them; a sensor error is stated the way a calibration sheet would (reading = (1 + gain) * true +
offset), so fitted values read as physical quantities. Plausible ranges are relative to the machine
(fractions of its pump size, its flows, speeds and pressures in the data), so one library serves a
78 cm3 drive and a 4.6 cm3 test-rig pump alike.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from cmcan.roles import DP, FLOW, MOTOR_SPEED, PUMP_DISP, PUMP_SPEED, QUANTITIES, TEMP
from cmcan.sim.physics import REF_DP_BAR, REF_TEMP_C, DriveParams, UnitLosses, steady_motor_speed_rpm

OUTPUT_UNIT = "output unit"  # a parameter in the output's own unit (rpm or l/min)


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
class Scale:
    """Sizes of the machine and of the data that plausible ranges are fractions of."""

    pump_disp_max_cc: float
    speed_max_rpm: float  # the highest pump speed in the data
    dp_max_bar: float  # the highest delta pressure in the data
    flow_max_lpm: float  # the highest geometric pump flow n_P * V_P in the data
    output_mean: float  # the mean output (rpm or l/min)

    @classmethod
    def of(cls, p: DriveParams, x: Inputs, y: NDArray[np.float64]) -> Scale:
        flow = x.pump_speed_rpm * np.clip(x.pump_disp_cc, 0.0, None) / 1000.0
        return cls(
            p.pump_disp_max_cc,
            float(np.max(np.abs(x.pump_speed_rpm))) if len(x.t_s) else 1.0,
            float(np.max(np.abs(x.dp_bar))) if len(x.t_s) else 1.0,
            float(np.max(flow)) if len(flow) else 1.0,
            float(np.mean(np.abs(y))) if len(y) else 1.0,
        )

    def ref(self, per: str | None) -> float:
        return {
            None: 1.0,
            "pump_disp_max_cc": self.pump_disp_max_cc,
            "speed_max_rpm": self.speed_max_rpm,
            "dp_max_bar": self.dp_max_bar,
            "flow_max_lpm": self.flow_max_lpm,
            "output_mean": self.output_mean,
        }[per]


_PER_TEXT = {
    "pump_disp_max_cc": "of the pump's maximum displacement",
    "speed_max_rpm": "of the highest pump speed",
    "dp_max_bar": "of the highest delta pressure",
    "flow_max_lpm": "of the highest geometric pump flow",
    "output_mean": "of the mean output",
}


@dataclass(frozen=True)
class Param:
    name: str
    unit: str
    lo: float  # plausible range: [lo, hi] times the machine size ``per`` (absolute where per is None)
    hi: float
    start: float  # start of the fit, as a fraction of the plausible range's larger end
    per: str | None = None
    bound_lo: float = -np.inf  # hard limit of the fit (a time constant cannot be negative)

    def plausible(self, s: Scale) -> tuple[float, float]:
        r = s.ref(self.per)
        return self.lo * r, self.hi * r

    def x0(self, s: Scale) -> float:
        lo, hi = self.plausible(s)
        return self.start * max(abs(lo), abs(hi))

    def describe_range(self) -> str:
        if self.per is None:
            return f"{self.lo:g} .. {self.hi:g} {self.unit}"
        return f"{100 * self.lo:g} .. {100 * self.hi:g} % {_PER_TEXT[self.per]}"


@dataclass
class Mods:
    """What the added effects change in the simulator, accumulated over all of them. Sensor errors
    are stated as reading = (1 + gain) * true + offset, so the true value is recovered from the reading."""

    leak_lpm: dict[str, float] = field(default_factory=dict)  # l/min at the reference point, by law
    compress_add: float = 0.0
    motor_disp_factor: float = 1.0
    sensor_offset: dict[str, float] = field(default_factory=dict)
    sensor_gain: dict[str, float] = field(default_factory=dict)  # fractions, not %
    lag_tau_s: float = 0.0

    def true_value(self, role: str, reading: NDArray[np.float64]) -> NDArray[np.float64]:
        off, gain = self.sensor_offset.get(role, 0.0), self.sensor_gain.get(role, 0.0)
        if off == 0.0 and gain == 0.0:
            return reading
        return (reading - off) / (1.0 + gain)

    def reading(self, role: str, true: NDArray[np.float64]) -> NDArray[np.float64]:
        off, gain = self.sensor_offset.get(role, 0.0), self.sensor_gain.get(role, 0.0)
        if off == 0.0 and gain == 0.0:
            return true
        return true * (1.0 + gain) + off


@dataclass(frozen=True)
class Effect:
    name: str
    formula: str
    description: str
    params: tuple[Param, ...]
    apply: Callable[[DriveParams, Inputs, NDArray[np.float64], Mods], None]
    kind: str = "physical"  # or "sensor"
    needs_time: bool = False  # shows only in a time series (a lag)
    quantities: tuple[str, ...] = QUANTITIES

    def describe(self) -> dict:
        return {
            "name": self.name,
            "kind": self.kind,
            "formula": self.formula,
            "description": self.description,
            "parameters": [{"name": q.name, "unit": q.unit, "plausible": q.describe_range()} for q in self.params],
        }


def output_scale(p: DriveParams, quantity: str) -> float:
    """Factor from motor speed (rpm) to the output quantity: delivered flow is speed times V_M."""
    return p.motor_disp_cc / 1000.0 if quantity == FLOW else 1.0


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


def simulate(
    p: DriveParams,
    x: Inputs,
    effects: list[tuple[Effect, NDArray[np.float64]]],
    quantity: str = MOTOR_SPEED,
) -> NDArray[np.float64]:
    """The simulator on measured inputs with ``effects`` (each with its parameter vector) added: the
    flow balance at the measured pressure, minus the flow the high-pressure line takes to build
    pressure up (V_line / K * d(dp)/dt) and what the relief valve lets through above its setting,
    in the output's unit; sensor errors turn readings into true values and the true output into what
    its sensor reports."""
    m = Mods()
    for eff, th in effects:
        eff.apply(p, x, th, m)
    if m.compress_add:
        pump = p.pump
        p = replace(p, pump=UnitLosses(pump.laminar_cs, pump.turbulent_ct, pump.compress_factor + m.compress_add))
    n = m.true_value(PUMP_SPEED, x.pump_speed_rpm)
    v = m.true_value(PUMP_DISP, x.pump_disp_cc)
    dp = m.true_value(DP, x.dp_bar)
    temp = m.true_value(TEMP, x.temp_c)
    dp_rate = x.dp_rate_bar_s / (1.0 + m.sensor_gain.get(DP, 0.0))
    line_lpm = p.line_volume_l / p.bulk_modulus_bar * dp_rate * 60.0
    relief_lpm = p.relief_gain_lpm_per_bar * np.clip(dp - p.relief_dp_bar, 0.0, None)
    y = steady_motor_speed_rpm(
        p,
        n,
        v,
        dp,
        temp,
        extra_leak_lpm=_leaks(p, m, dp, temp) + line_lpm + relief_lpm,
        motor_disp_factor=m.motor_disp_factor,
    ) * output_scale(p, quantity)
    if m.lag_tau_s > 0:
        y = first_order_lag(y, x.t_s, x.segment, m.lag_tau_s)
    return m.reading("output", y)


def mu_ratio(p: DriveParams, temp_c: NDArray[np.float64]) -> NDArray[np.float64]:
    return float(p.oil.dynamic_viscosity_pa_s(REF_TEMP_C)) / p.oil.dynamic_viscosity_pa_s(temp_c)


def _leaks(p: DriveParams, m: Mods, dp: NDArray[np.float64], temp: NDArray[np.float64]) -> NDArray[np.float64]:
    """The added leakages at the true pressure and temperature (after every sensor error is undone,
    whatever order the effects came in)."""
    q = m.leak_lpm
    out = np.zeros_like(dp)
    if q.get("laminar"):
        out = out + q["laminar"] * dp / REF_DP_BAR * mu_ratio(p, temp)
    if q.get("pressure"):
        out = out + q["pressure"] * dp / REF_DP_BAR
    if q.get("turbulent"):
        out = out + q["turbulent"] * np.sign(dp) * np.sqrt(np.abs(dp) / REF_DP_BAR)
    return out


def _leak(law: str) -> Callable[[DriveParams, Inputs, NDArray[np.float64], Mods], None]:
    def apply(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
        m.leak_lpm[law] = m.leak_lpm.get(law, 0.0) + float(th[0])

    return apply


def _compress(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.compress_add += float(th[0])


def _motor_disp(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.motor_disp_factor *= 1.0 + float(th[0]) / 100.0


def _lag(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
    m.lag_tau_s = max(float(th[0]), 0.0)


def _offset(role: str) -> Callable[[DriveParams, Inputs, NDArray[np.float64], Mods], None]:
    def apply(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
        m.sensor_offset[role] = m.sensor_offset.get(role, 0.0) + float(th[0])

    return apply


def _gain(role: str) -> Callable[[DriveParams, Inputs, NDArray[np.float64], Mods], None]:
    def apply(p: DriveParams, x: Inputs, th: NDArray[np.float64], m: Mods) -> None:
        m.sensor_gain[role] = m.sensor_gain.get(role, 0.0) + float(th[0]) / 100.0

    return apply


# Leakages up to a quarter of the highest pump flow in the data: beyond that the drive would not work.
_LEAK = Param("q_ref_lpm", "l/min at 300 bar, 50 C", 0.0, 0.25, 0.01, per="flow_max_lpm")


def _sensor(prefix: str, role: str, label: str, offset: Param, gain_pct: float) -> tuple[Effect, Effect]:
    """Offset and gain of the sensor of ``role`` (``output``: the output's own sensor)."""
    return (
        Effect(
            f"{prefix}_sensor_offset",
            f"{label}_read = {label}_true + offset",
            f"the {label} reading has a zero offset",
            (offset,),
            _offset(role),
            kind="sensor",
        ),
        Effect(
            f"{prefix}_sensor_gain",
            f"{label}_read = {label}_true * (1 + pct / 100)",
            f"the {label} reading has a gain (span) error",
            (Param("pct", "%", -gain_pct, gain_pct, 0.01),),
            _gain(role),
            kind="sensor",
        ),
    )


# Sensor errors a calibration would find: speed within 3 % of its top, displacement within 10 % of the
# pump's size, pressure within 5 % of the top pressure, temperature within 15 C, the output within 5 %.
_SENSORS = (
    *_sensor("pump_speed", PUMP_SPEED, "n_P", Param("offset_rpm", "rpm", -0.03, 0.03, 0.01, "speed_max_rpm"), 5),
    *_sensor("disp", PUMP_DISP, "V_P", Param("offset_cc", "cm3/rev", -0.1, 0.1, 0.01, "pump_disp_max_cc"), 10),
    *_sensor("pressure", DP, "dp", Param("offset_bar", "bar", -0.05, 0.05, 0.01, "dp_max_bar"), 10),
    *_sensor("temp", TEMP, "T", Param("offset_c", "C", -15.0, 15.0, 0.01), 15),
    *_sensor("output", "output", "y", Param("offset", OUTPUT_UNIT, -0.05, 0.05, 0.01, "output_mean"), 10),
)


LIBRARY: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "laminar_leakage",
            "Q = q_ref * (dp / 300 bar) * (mu(50 C) / mu(T))",
            "gap flow in a rotating group (Wilson): grows with pressure and with thinner, hotter oil",
            (_LEAK,),
            _leak("laminar"),
        ),
        Effect(
            "pressure_leakage",
            "Q = q_ref * (dp / 300 bar)",
            "leakage proportional to pressure and independent of viscosity",
            (replace(_LEAK, unit="l/min at 300 bar"),),
            _leak("pressure"),
        ),
        Effect(
            "turbulent_leakage",
            "Q = q_ref * sqrt(dp / 300 bar)",
            "orifice-like leakage (Schloesser): grows with the square root of pressure",
            (replace(_LEAK, unit="l/min at 300 bar"),),
            _leak("turbulent"),
        ),
        Effect(
            "compressibility",
            "Q = f * n_P * V_P * dp / K",
            "oil compressed in the pump's dead volume, on top of the modelled share",
            (Param("factor", "share of n_P V_P dp / K", 0.0, 3.0, 0.03),),
            _compress,
        ),
        Effect(
            "motor_disp_offset",
            "V_M,true = V_M * (1 + pct / 100)",
            "the motor's real displacement differs from nominal: a constant factor on speed",
            (Param("pct", "%", -15.0, 15.0, 0.01),),
            _motor_disp,
            quantities=(MOTOR_SPEED,),
        ),
        *_SENSORS,
        Effect(
            "output_sensor_lag",
            "y_read' = (y_true - y_read) / tau",
            "the output reading lags the true value (sensor or filter time constant)",
            (Param("tau_s", "s", 0.005, 2.0, 0.05, bound_lo=0.0),),
            _lag,
            kind="sensor",
            needs_time=True,
        ),
    )
}
