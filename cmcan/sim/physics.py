"""Drive parameters and the loss laws of an axial piston pump and motor.

Every loss is a named term with its own coefficient; a coefficient of 0 switches it off. Flows are in
SI (m3/s) inside, the same functions serve floats (the integrator's loop) and numpy arrays (the
quasi-static law used by the gap diagnosis and by tests).

- laminar leakage (Wilson):     Q = C_s * D * dp / mu          D = V / (2 pi) in m3/rad
- turbulent leakage (Schloesser): Q = C_t * V^(2/3) * sqrt(2 dp / rho)
- compressibility loss:         Q = f_c * n * V * dp / K       n in rev/s, V in m3/rev

Extra loss terms (:class:`ExtraLosses`) are stated the way a test rig reports a leak, in l/min at
300 bar and 50 C; they are the physical effects of the gap diagnosis's library, so the simulator can
carry what a diagnosis found and the gap bench can put an effect inside the dynamic simulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from cmcan.oil import Oil

BAR = 1e5
LPM = 1e-3 / 60.0  # m3/s per l/min
CC = 1e-6  # m3 per cm3
TWO_PI = 2.0 * math.pi
# Reference point at which extra leakages are stated (l/min at 300 bar and 50 C oil).
REF_DP_BAR = 300.0
REF_TEMP_C = 50.0
REF_SPEED_RPM = 3000.0  # ... and a filling loss at 3000 rpm


@dataclass(frozen=True)
class UnitLosses:
    """Loss coefficients of one rotating group (pump or motor)."""

    laminar_cs: float = 0.0
    turbulent_ct: float = 0.0
    compress_factor: float = 0.0

    def off(self) -> UnitLosses:
        return UnitLosses()


@dataclass(frozen=True)
class ExtraLosses:
    """Loss terms beyond the units' own laws, each off at 0 (the default)."""

    laminar_lpm: float = 0.0  # Q = q * (dp / 300 bar) * (mu(50 C) / mu(T)): a gap flow
    pressure_lpm: float = 0.0  # Q = q * (dp / 300 bar): a viscosity-free leak
    turbulent_lpm: float = 0.0  # Q = q * sqrt(dp / 300 bar): an orifice
    compress_factor: float = 0.0  # added to the pump's compressibility share
    # Incomplete filling of the pump's chambers at speed: Q = q * (n_P / 3000 rpm)^2 (not in the gap
    # library: the gap bench's effect from outside it).
    filling_lpm: float = 0.0

    @property
    def any(self) -> bool:
        return any(
            v != 0.0
            for v in (self.laminar_lpm, self.pressure_lpm, self.turbulent_lpm, self.compress_factor, self.filling_lpm)
        )

    def filling_c(self) -> float:
        """The filling loss as Q = c * n^2 (SI flow, n in rpm)."""
        return self.filling_lpm * LPM / REF_SPEED_RPM**2

    def laminar_g(self, oil: Oil) -> float:
        """The laminar term as a conductance g (Q = g * dp / mu, SI)."""
        return self.laminar_lpm * LPM * float(oil.dynamic_viscosity_pa_s(REF_TEMP_C)) / (REF_DP_BAR * BAR)

    def pressure_g(self) -> float:
        """The viscosity-free term as a conductance (Q = g * dp, SI)."""
        return self.pressure_lpm * LPM / (REF_DP_BAR * BAR)

    def turbulent_h(self) -> float:
        """The orifice term as Q = h * sqrt(dp) (SI)."""
        return self.turbulent_lpm * LPM / math.sqrt(REF_DP_BAR * BAR)

    def leak_m3s(self, oil: Oil, pump_speed_rpm: Any, dp_pa: Any, mu_pas: Any) -> Any:
        """The extra terms' flow (compressibility is handled with the pump's own share)."""
        return (
            self.laminar_g(oil) * dp_pa / mu_pas
            + self.pressure_g() * dp_pa
            + self.turbulent_h() * np.sign(dp_pa) * np.sqrt(np.abs(dp_pa))
            + self.filling_c() * np.square(pump_speed_rpm)
        )


@dataclass(frozen=True)
class DriveParams:
    """The reference drive: H1P 78 pump and H1B 110 motor at 40 % on a 480 bar test rig."""

    pump_disp_max_cc: float = 78.0
    motor_disp_max_cc: float = 110.0
    motor_disp_setting: float = 0.40
    charge_pressure_bar: float = 25.0
    relief_dp_bar: float = 580.0
    relief_gain_lpm_per_bar: float = 20.0
    bulk_modulus_bar: float = 15000.0
    line_volume_l: float = 1.0
    motor_inertia_kgm2: float = 1.0
    motor_friction_nm: float = 2.0
    motor_viscous_nm_per_krpm: float = 1.0
    # Speed below which the load torque fades out (it opposes motion, it does not drive the motor back).
    load_fade_rpm: float = 30.0
    pump: UnitLosses = field(default_factory=lambda: UnitLosses(1.0e-9, 0.8e-5, 0.35))
    motor: UnitLosses = field(default_factory=lambda: UnitLosses(0.7e-9, 0.6e-5, 0.35))
    oil: Oil = field(default_factory=Oil)
    # Heat balance: loss power heats the oil, the cooler and the tank walls take it to ambient.
    heat_capacity_kj_per_k: float = 200.0
    cooler_w_per_k: float = 500.0
    hm_loss_fraction: float = 0.06
    extra: ExtraLosses = field(default_factory=ExtraLosses)

    @property
    def motor_disp_cc(self) -> float:
        return self.motor_disp_max_cc * self.motor_disp_setting

    def lossless(self) -> DriveParams:
        return replace(self, pump=UnitLosses(), motor=UnitLosses())


def laminar_leak_m3s(dp_pa: Any, mu_pas: Any, disp_m3_rad: float, cs: float) -> Any:
    return cs * disp_m3_rad * dp_pa / mu_pas


def turbulent_leak_m3s(dp_pa: Any, rho: Any, vol_m3: float, ct: float) -> Any:
    if ct == 0.0:
        return 0.0 * dp_pa
    if isinstance(dp_pa, np.ndarray):
        return ct * vol_m3 ** (2.0 / 3.0) * np.sign(dp_pa) * np.sqrt(2.0 * np.abs(dp_pa) / rho)
    return math.copysign(ct * vol_m3 ** (2.0 / 3.0) * math.sqrt(2.0 * abs(dp_pa) / rho), dp_pa)


def compress_loss_m3s(speed_rev_s: Any, vol_m3_rev: Any, dp_pa: Any, bulk_pa: float, factor: float) -> Any:
    return factor * speed_rev_s * vol_m3_rev * dp_pa / bulk_pa


def pump_loss_m3s(p: DriveParams, pump_speed_rpm: Any, pump_disp_cc: Any, dp_pa: Any, mu_pas: Any, rho: Any) -> Any:
    """Sum of the pump's loss terms. Leakage uses the maximum displacement: gap flows hardly depend on
    the swash angle, which is why the same leakage is a larger share of flow at low displacement."""
    vmax = p.pump_disp_max_cc * CC
    return (
        laminar_leak_m3s(dp_pa, mu_pas, vmax / TWO_PI, p.pump.laminar_cs)
        + turbulent_leak_m3s(dp_pa, rho, vmax, p.pump.turbulent_ct)
        + compress_loss_m3s(
            pump_speed_rpm / 60.0,
            pump_disp_cc * CC,
            dp_pa,
            p.bulk_modulus_bar * BAR,
            p.pump.compress_factor + p.extra.compress_factor,
        )
    )


def motor_leak_m3s(p: DriveParams, dp_pa: Any, mu_pas: Any, rho: Any) -> Any:
    """The motor's speed-independent leakage terms (compressibility is proportional to speed and
    handled by :func:`motor_flow_per_rev_m3`)."""
    vmax = p.motor_disp_max_cc * CC
    return laminar_leak_m3s(dp_pa, mu_pas, vmax / TWO_PI, p.motor.laminar_cs) + turbulent_leak_m3s(
        dp_pa, rho, vmax, p.motor.turbulent_ct
    )


def motor_flow_per_rev_m3(p: DriveParams, motor_disp_m3: Any, dp_pa: Any) -> Any:
    """Flow the motor swallows per revolution: its displacement plus the oil compressed into it."""
    return motor_disp_m3 * (1.0 + p.motor.compress_factor * dp_pa / (p.bulk_modulus_bar * BAR))


def steady_motor_speed_rpm(
    p: DriveParams,
    pump_speed_rpm: Any,
    pump_disp_cc: Any,
    dp_bar: Any,
    temp_c: Any,
    extra_leak_lpm: Any = 0.0,
    motor_disp_factor: Any = 1.0,
) -> Any:
    """Quasi-static flow balance: the motor speed at which the motor swallows what the pump delivers.

    This is the simulator's law run on measured inputs (pump speed, displacement, delta pressure and
    temperature), without the pressure and inertia dynamics.
    """
    n_p = np.asarray(pump_speed_rpm, dtype=float)
    v_p = np.asarray(pump_disp_cc, dtype=float)
    dp = np.asarray(dp_bar, dtype=float) * BAR
    mu = p.oil.dynamic_viscosity_pa_s(temp_c)
    rho = p.oil.density_kg_m3(temp_c)
    q_pump = n_p / 60.0 * v_p * CC - pump_loss_m3s(p, n_p, v_p, dp, mu, rho)
    q_motor = q_pump - motor_leak_m3s(p, dp, mu, rho) - np.asarray(extra_leak_lpm, dtype=float) * LPM
    if p.extra.any:
        q_motor = q_motor - p.extra.leak_m3s(p.oil, n_p, dp, mu)
    per_rev = motor_flow_per_rev_m3(p, p.motor_disp_cc * CC * np.asarray(motor_disp_factor, dtype=float), dp)
    return np.maximum(q_motor, 0.0) / per_rev * 60.0
