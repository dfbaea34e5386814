"""Time integration of the closed-circuit drive: high-side pressure, motor speed and oil temperature.

States: delta pressure across the motor (pressure build-up from line compressibility), motor shaft
speed (torque balance with inertia) and oil temperature (heat balance, unless prescribed).

The loop is stiff (the relief valve and the leakage conductances act within milliseconds), so each
step is a linearly implicit (Rosenbrock-Euler) step on pressure and speed: stable at the sensor sample
period. It runs over plain floats because per-step numpy calls on scalars would be ten times slower.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.io import native
from cmcan.oil import KELVIN
from cmcan.sim.physics import BAR, CC, LPM, TWO_PI, DriveParams

_MIN_DP_FOR_SQRT = 1.0 * BAR  # the sqrt law's slope is unbounded at zero; clamp for the Jacobian


@dataclass(frozen=True)
class DriveInputs:
    """Per-step inputs (arrays of equal length, one value per step of ``dt_s``)."""

    pump_speed_rpm: NDArray[np.float64]
    pump_disp_cc: NDArray[np.float64]
    load_torque_nm: NDArray[np.float64]
    # Oil temperature where prescribed, NaN where the heat balance decides.
    temp_c: NDArray[np.float64]
    ambient_c: NDArray[np.float64]
    # Extra leakage from degradation, as conductances (see cmcan.sim.degradation):
    # laminar wear in pump or motor, Q = g * dp / mu; a bypass orifice, Q = h * sqrt(dp).
    wear_g_pump: NDArray[np.float64]
    wear_g_motor: NDArray[np.float64]
    bypass_h: NDArray[np.float64]
    motor_disp_factor: NDArray[np.float64]


@dataclass(frozen=True)
class DriveState:
    dp_pa: float
    motor_speed_rad_s: float
    temp_c: float


@dataclass(frozen=True)
class DriveOutputs:
    dp_bar: NDArray[np.float64]
    motor_speed_rpm: NDArray[np.float64]
    temp_c: NDArray[np.float64]
    extra_leak_lpm: NDArray[np.float64]
    final: DriveState


def integrate(p: DriveParams, u: DriveInputs, dt_s: float, start: DriveState) -> DriveOutputs:
    """The run of ``u``'s steps from ``start``: the C loop of ``_drive_fast.c`` where the library is
    built (the same numbers to the bit), else :func:`integrate_python`'s loop, the reference."""
    k = _hoisted(p)
    raw = _loop_native(k, u, dt_s, start)
    if raw is None:
        raw = _loop_python(k, u, dt_s, start)
    return _outputs(*raw)


def integrate_python(p: DriveParams, u: DriveInputs, dt_s: float, start: DriveState) -> DriveOutputs:
    """:func:`integrate` by the Python loop, whether or not the C loop is there."""
    return _outputs(*_loop_python(_hoisted(p), u, dt_s, start))


def _hoisted(p: DriveParams) -> tuple[float, ...]:
    """The loop's constants, in the order of ``_drive_fast.c``'s ``K_...`` (the module constants it
    uses and the base and exponent of its ``**`` at the end)."""
    # Constants hoisted out of the loop.
    a_w, b_w = p.oil.walther_ab
    rho15, drho = p.oil.density15_kg_m3, p.oil.density_per_k
    k_line = p.bulk_modulus_bar * BAR / (p.line_volume_l * 1e-3)
    bulk = p.bulk_modulus_bar * BAR
    d_m_nom = p.motor_disp_cc * CC / TWO_PI
    vp_max, vm_max = p.pump_disp_max_cc * CC, p.motor_disp_max_cc * CC
    lam_p = p.pump.laminar_cs * vp_max / TWO_PI
    lam_m = p.motor.laminar_cs * vm_max / TWO_PI
    turb = p.pump.turbulent_ct * vp_max ** (2 / 3) + p.motor.turbulent_ct * vm_max ** (2 / 3)
    comp_p = (p.pump.compress_factor + p.extra.compress_factor) / bulk
    # Extra loss terms (0 unless a scenario or the gap bench adds them; adding 0.0 changes no bit).
    lam_x = p.extra.laminar_g(p.oil)
    lin_x = p.extra.pressure_g()
    orf_x = p.extra.turbulent_h()
    fill_x = p.extra.filling_c()
    comp_m = p.motor.compress_factor / bulk
    relief_dp = p.relief_dp_bar * BAR
    relief_gain = p.relief_gain_lpm_per_bar * LPM / BAR
    inertia = p.motor_inertia_kgm2
    friction = p.motor_friction_nm
    viscous = p.motor_viscous_nm_per_krpm * 60.0 / (TWO_PI * 1000.0)  # Nm per rad/s
    fade = max(p.load_fade_rpm * TWO_PI / 60.0, 1e-3)
    heat_cap = p.heat_capacity_kj_per_k * 1e3
    cooler = p.cooler_w_per_k
    hm_loss = p.hm_loss_fraction
    return (
        a_w,
        b_w,
        rho15,
        drho,
        k_line,
        d_m_nom,
        lam_p,
        lam_m,
        turb,
        comp_p,
        lam_x,
        lin_x,
        orf_x,
        fill_x,
        comp_m,
        relief_dp,
        relief_gain,
        inertia,
        friction,
        viscous,
        fade,
        heat_cap,
        cooler,
        hm_loss,
        KELVIN,
        CC,
        _MIN_DP_FOR_SQRT,
        10.0,  # the base of 10.0 ** x
        2.0,  # the exponent of cosh(x) ** 2 (an int there, a float to float_pow)
    )


_INPUTS = (
    "pump_speed_rpm",
    "pump_disp_cc",
    "load_torque_nm",
    "temp_c",
    "ambient_c",
    "wear_g_pump",
    "wear_g_motor",
    "bypass_h",
    "motor_disp_factor",
)


def _loop_native(
    k: tuple[float, ...], u: DriveInputs, dt_s: float, start: DriveState
) -> tuple[list[float] | NDArray[np.float64], ...] | None:
    """The C loop's raw outputs and final state; None where it is not built, where the inputs are not
    plain float64 arrays or the start, step and constants not Python floats or ints (float64 is a
    float; the Python loop's arithmetic on Python ints or objects, or in float32 where a numpy float32
    meets a Python float, is its own), or where the Python loop raises an exception at some step (it is
    left to raise it)."""
    lib = native.LIB
    if lib is None or not hasattr(lib, "cmcan_drive_integrate"):
        return None
    n = len(u.pump_speed_rpm)
    arrays = [getattr(u, name) for name in _INPUTS]
    if n == 0 or not all(
        isinstance(a, np.ndarray) and a.dtype == np.float64 and a.ndim == 1 and len(a) >= n for a in arrays
    ):
        return None
    scalars = (*k, dt_s, start.dp_pa, start.motor_speed_rad_s, start.temp_c)
    if int(lib.cmcan_drive_constants()) != len(k) or not all(isinstance(x, (float, int)) for x in scalars):
        return None
    try:
        consts = np.array(k, dtype=np.float64)
        state = np.array([start.dp_pa, start.motor_speed_rad_s, start.temp_c], dtype=np.float64)
        dt = float(dt_s)
    except (TypeError, ValueError, OverflowError):
        return None
    ins = [np.ascontiguousarray(a[:n]) for a in arrays]
    outs = [np.empty(n) for _ in range(4)]
    done = lib.cmcan_drive_integrate(
        n, consts.ctypes.data, dt, *(a.ctypes.data for a in ins), state.ctypes.data, *(o.ctypes.data for o in outs)
    )
    if done != n:
        return None
    dp, w, temp = (float(x) for x in state)
    return (*outs, dp, w, temp)


def _loop_python(
    k: tuple[float, ...], u: DriveInputs, dt_s: float, start: DriveState
) -> tuple[list[float] | NDArray[np.float64], ...]:
    """The loop itself (the reference of ``_drive_fast.c``): raw outputs and final state."""
    n_steps = len(u.pump_speed_rpm)
    (
        a_w,
        b_w,
        rho15,
        drho,
        k_line,
        d_m_nom,
        lam_p,
        lam_m,
        turb,
        comp_p,
        lam_x,
        lin_x,
        orf_x,
        fill_x,
        comp_m,
        relief_dp,
        relief_gain,
        inertia,
        friction,
        viscous,
        fade,
        heat_cap,
        cooler,
        hm_loss,
        *_,
    ) = k

    n_p_l = u.pump_speed_rpm.tolist()
    v_p_l = u.pump_disp_cc.tolist()
    tl_l = u.load_torque_nm.tolist()
    tp_l = u.temp_c.tolist()
    ta_l = u.ambient_c.tolist()
    gp_l = u.wear_g_pump.tolist()
    gm_l = u.wear_g_motor.tolist()
    hb_l = u.bypass_h.tolist()
    mf_l = u.motor_disp_factor.tolist()

    out_dp = [0.0] * n_steps
    out_w = [0.0] * n_steps
    out_t = [0.0] * n_steps
    out_x = [0.0] * n_steps

    dp, w, temp = start.dp_pa, start.motor_speed_rad_s, start.temp_c
    sqrt, log10, tanh, cosh = math.sqrt, math.log10, math.tanh, math.cosh
    for i in range(n_steps):
        t_pres = tp_l[i]
        if t_pres == t_pres:  # not NaN: prescribed temperature
            temp = t_pres
        nu = 10.0 ** (10.0 ** (a_w - b_w * log10(temp + KELVIN))) - 0.7
        rho = rho15 * (1.0 - drho * (temp - 15.0))
        mu = nu * 1e-6 * rho
        n_p = n_p_l[i]
        q_geo = n_p / 60.0 * v_p_l[i] * CC
        q_fill = fill_x * n_p * n_p
        d_m = d_m_nom * mf_l[i]

        # Leakage conductance (linear part) and sqrt-law part at the current pressure.
        g_lin = (lam_p + lam_m + lam_x + gp_l[i] + gm_l[i]) / mu + lin_x + comp_p * q_geo
        adp = dp if dp >= 0.0 else -dp
        root = sqrt(2.0 * adp / rho)
        h_b = hb_l[i] + orf_x
        h_sq = turb * root + h_b * sqrt(adp)
        q_sq = h_sq if dp >= 0.0 else -h_sq
        adp_c = adp if adp > _MIN_DP_FOR_SQRT else _MIN_DP_FOR_SQRT
        dq_sq = 0.5 * (turb * sqrt(2.0 / (rho * adp_c)) + h_b / sqrt(adp_c))
        q_motor = w * d_m * (1.0 + comp_m * dp)
        q_base = g_lin * dp + q_sq
        fd_base = -k_line * (g_lin + dq_sq + w * d_m * comp_m)
        fw = -k_line * d_m * (1.0 + comp_m * dp)

        # Load torque opposes motion and fades to zero at standstill (it does not drive the motor back).
        th = tanh(w / fade)
        t_load = tl_l[i] * th
        t_fric = friction * th + viscous * w
        g0 = (d_m * dp - t_load - t_fric) / inertia
        gd = d_m / inertia
        sech2 = 1.0 / cosh(w / fade) ** 2 if abs(w / fade) < 50.0 else 0.0
        gw = -((tl_l[i] + friction) * sech2 / fade + viscous) / inertia

        # Linearly implicit step: (I - dt J) dx = dt f. The relief valve is a linear conductance above
        # its setting; where the step would cross it, the step is solved again with the valve open.
        relief_open = dp > relief_dp
        for _ in range(2):
            if relief_open:
                q_leak = q_base + relief_gain * (dp - relief_dp)
                fd = fd_base - k_line * relief_gain
            else:
                q_leak = q_base
                fd = fd_base
            f0 = k_line * (q_geo - q_fill - q_leak - q_motor)
            a11 = 1.0 - dt_s * fd
            a12 = -dt_s * fw
            a21 = -dt_s * gd
            a22 = 1.0 - dt_s * gw
            det = a11 * a22 - a12 * a21
            r1 = dt_s * f0
            r2 = dt_s * g0
            dp_new = dp + (r1 * a22 - a12 * r2) / det
            w_new = w + (a11 * r2 - a21 * r1) / det
            if relief_open or dp_new <= relief_dp:
                break
            relief_open = True
        dp, w = dp_new, w_new

        extra = (gp_l[i] + gm_l[i]) / mu * dp + hb_l[i] * sqrt(abs(dp))
        if t_pres != t_pres:
            p_loss = q_leak * dp + hm_loss * q_geo * abs(dp) + t_fric * w
            temp += dt_s * (p_loss - cooler * (temp - ta_l[i])) / heat_cap

        out_dp[i] = dp
        out_w[i] = w
        out_t[i] = temp
        out_x[i] = extra

    return out_dp, out_w, out_t, out_x, dp, w, temp


def _outputs(out_dp: Any, out_w: Any, out_t: Any, out_x: Any, dp: float, w: float, temp: float) -> DriveOutputs:
    return DriveOutputs(
        dp_bar=np.asarray(out_dp) / BAR,
        motor_speed_rpm=np.asarray(out_w) * 60.0 / TWO_PI,
        temp_c=np.asarray(out_t),
        extra_leak_lpm=np.asarray(out_x) / LPM,
        final=DriveState(dp, w, temp),
    )


def load_torque_for_dp(p: DriveParams, dp_bar: NDArray[np.float64]) -> NDArray[np.float64]:
    """Load torque (Nm) that the nominal motor balances at ``dp_bar``: duty cycles state their load as
    the delta pressure it takes, the usual way test rigs and machine data describe it."""
    return np.asarray(dp_bar, dtype=float) * BAR * p.motor_disp_cc * CC / TWO_PI


def steady_state(
    p: DriveParams,
    pump_speed_rpm: float,
    pump_disp_cc: float,
    load_torque_nm: float,
    temp_c: float,
    motor_disp_factor: float = 1.0,
    wear_g: float = 0.0,
    bypass_h: float = 0.0,
) -> DriveState:
    """Operating point where flow and torque balance: the state a run starts from, so that runs and
    bursts do not begin with an artificial run-up transient. Fixed-point iteration on dp and speed."""
    from cmcan.sim.physics import steady_motor_speed_rpm

    d_m = p.motor_disp_cc * CC * motor_disp_factor / TWO_PI
    mu = float(p.oil.dynamic_viscosity_pa_s(temp_c))
    dp_bar = 0.0
    speed_rpm = 0.0
    for _ in range(30):
        extra_lpm = (wear_g * dp_bar * BAR / mu + bypass_h * math.sqrt(dp_bar * BAR)) / LPM
        speed_rpm = float(
            steady_motor_speed_rpm(
                p,
                pump_speed_rpm,
                pump_disp_cc,
                dp_bar,
                temp_c,
                extra_leak_lpm=extra_lpm,
                motor_disp_factor=motor_disp_factor,
            )
        )
        w = speed_rpm * TWO_PI / 60.0
        fade = math.tanh(w / max(p.load_fade_rpm * TWO_PI / 60.0, 1e-3))
        torque = (load_torque_nm + p.motor_friction_nm) * fade + p.motor_viscous_nm_per_krpm * speed_rpm / 1000.0
        new_dp = min(torque / d_m / BAR, p.relief_dp_bar)
        if abs(new_dp - dp_bar) < 1e-6:
            break
        dp_bar = new_dp
    return DriveState(dp_bar * BAR, speed_rpm * TWO_PI / 60.0, temp_c)
