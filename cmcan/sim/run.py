"""Simulate a scenario: set points, degradation and oil temperature in, sensor time series out."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can.codec import quantize
from cmcan.can.dbccache import load_compiled
from cmcan.roles import DEFAULT_INPUTS, MOTOR_FORWARD, MOTOR_STOPPED
from cmcan.sim import degradation, duty
from cmcan.sim.drive import DriveInputs, integrate, load_torque_for_dp, steady_state
from cmcan.sim.physics import DriveParams
from cmcan.sim.scenario import Scenario
from cmcan.sim.sensors import SensorError

if TYPE_CHECKING:  # a hint only: cantools imports python-can, which imports asammdf (issue 37)
    from cantools.database.can import Database

# Columns of a run, in file order. Measured quantities first, then the ground truth (never on the bus).
MEASURED = (
    "pump_speed_rpm",
    "pump_disp_cc",
    "high_pressure_bar",
    "low_pressure_bar",
    "dp_bar",
    "temp_c",
    "motor_speed_rpm",
)
TRUTH = (
    "true_motor_speed_rpm",
    "true_dp_bar",
    "true_temp_c",
    "true_extra_leak_lpm",
    "true_misposition_pct",
    "true_failed",
)
COLUMNS = ("time_s", "operating_h", *MEASURED, *TRUTH)
MOTOR_STOPPED_RPM = 5.0


@dataclass
class Run:
    """A simulated run: one array per column, sampled at ``sample_rate_hz`` (with gaps for bursts)."""

    name: str
    sample_rate_hz: float
    start_epoch_s: float
    columns: dict[str, NDArray[np.float64]]
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.columns["time_s"])

    def __getitem__(self, key: str) -> NDArray[np.float64]:
        return self.columns[key]


def time_grid(s: Scenario) -> tuple[NDArray[np.float64], list[tuple[int, int]]]:
    """Operating seconds of every sample, and the [start, stop) index range of each burst."""
    dt = 1.0 / s.sample_rate_hz
    total = s.duration_h * 3600.0
    smp = s.sampling
    if not smp.bursts:
        n = round(total / dt)
        return np.arange(n) * dt, [(0, n)]
    per = round(smp.burst_s / dt)
    starts = np.arange(0.0, total, smp.every_min * 60.0)
    t = (starts[:, None] + np.arange(per)[None, :] * dt).ravel()
    return t, [(i * per, (i + 1) * per) for i in range(len(starts))]


def oil_temperatures(s: Scenario, t_s: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(prescribed oil temperature or NaN where the heat balance decides, ambient temperature)."""
    oil = s.oil
    t_h = t_s / 3600.0
    if oil["model"] == "prescribed":
        temp = oil["temp_c"] + oil["swing_c"] * np.sin(2 * np.pi * t_h / oil["period_h"])
        return temp, np.full_like(t_s, 25.0)
    if oil["model"] == "profile":
        pts = np.asarray(oil["points"], dtype=float)
        x = np.mod(t_h, pts[-1, 0]) if oil["repeat"] and pts[-1, 0] > 0 else t_h
        return np.interp(x, pts[:, 0], pts[:, 1]), np.full_like(t_s, 25.0)
    amb = oil["ambient_c"] + oil["ambient_swing_c"] * np.sin(2 * np.pi * t_h / oil["ambient_period_h"])
    return np.full_like(t_s, np.nan), amb


def simulate(s: Scenario, db: Database | None = None, mapping: dict[str, tuple[Any, ...]] | None = None) -> Run:
    """The scenario's run; ``mapping`` (role -> (message, signal[, scale, offset])) says which DBC
    signal carries each sensor, for its resolution and range (default: the shipped DBC's)."""
    db = db if db is not None else load_compiled()
    mapping = mapping if mapping is not None else DEFAULT_INPUTS
    p: DriveParams = s.params
    rng_duty, rng_noise, rng_jitter = (np.random.default_rng(x) for x in np.random.SeedSequence(s.seed).spawn(3))
    dt = 1.0 / s.sample_rate_hz
    t_s, bursts = time_grid(s)
    t_h = t_s / 3600.0

    sp = duty.setpoints(s.duty, t_s, rng_duty)
    pump_disp_cc = sp.pump_disp_pct / 100.0 * p.pump_disp_max_cc
    load_nm = load_torque_for_dp(p, sp.dp_bar)
    deg = degradation.evaluate(list(s.events), t_h, p.oil)
    disp_factor = deg.motor_disp_factor
    temp_presc, ambient = oil_temperatures(s, t_s)

    n = len(t_s)
    true_dp = np.empty(n)
    true_speed = np.empty(n)
    true_temp = np.empty(n)
    extra = np.empty(n)
    temp_state = s.oil.get("initial_c") or (float(ambient[0]) + 20.0 if n else 40.0)
    for a, b in bursts:
        if b <= a:
            continue
        t0 = float(temp_presc[a]) if np.isfinite(temp_presc[a]) else temp_state
        start = steady_state(
            p,
            float(sp.pump_speed_rpm[a]),
            float(pump_disp_cc[a]),
            float(load_nm[a]),
            t0,
            float(disp_factor[a]),
            float(deg.wear_g_pump[a] + deg.wear_g_motor[a]),
            float(deg.bypass_h[a]),
        )
        u = DriveInputs(
            sp.pump_speed_rpm[a:b],
            pump_disp_cc[a:b],
            load_nm[a:b],
            temp_presc[a:b],
            ambient[a:b],
            deg.wear_g_pump[a:b],
            deg.wear_g_motor[a:b],
            deg.bypass_h[a:b],
            disp_factor[a:b],
        )
        out = integrate(p, u, dt, start)
        true_dp[a:b] = out.dp_bar
        true_speed[a:b] = out.motor_speed_rpm
        true_temp[a:b] = out.temp_c
        extra[a:b] = out.extra_leak_lpm
        temp_state = out.final.temp_c

    truth = {
        "pump_speed_rpm": sp.pump_speed_rpm,
        "pump_disp_cc": pump_disp_cc,
        "high_pressure_bar": true_dp + p.charge_pressure_bar,
        "low_pressure_bar": np.full(n, p.charge_pressure_bar),
        "temp_c": true_temp,
        "motor_speed_rpm": np.abs(true_speed),
    }
    measured = sense(truth, s.sensors.noise, db, mapping, t_s, bursts, rng_noise, dict(s.sensors.errors))
    measured["dp_bar"] = measured["high_pressure_bar"] - measured["low_pressure_bar"]
    cols: dict[str, NDArray[np.float64]] = {"time_s": t_s, "operating_h": t_h}
    for k in MEASURED:
        cols[k] = measured[k]
    cols.update(
        true_motor_speed_rpm=true_speed,
        true_dp_bar=true_dp,
        true_temp_c=true_temp,
        true_extra_leak_lpm=extra,
        true_misposition_pct=deg.misposition_pct,
        true_failed=deg.failed.astype(float),
    )
    meta = {
        "scenario": s.name,
        "seed": s.seed,
        "jitter_ms": s.sensors.jitter_ms,
        "jitter_seed": int(rng_jitter.integers(2**31)),
        "bursts": len(bursts),
        "scheduled_failures": degradation.scheduled_failures(list(s.events)),
        "motor_disp_cc": p.motor_disp_cc,
    }
    return Run(s.name, s.sample_rate_hz, s.start_epoch_s, cols, meta)


def sense(
    truth: dict[str, NDArray[np.float64]],
    noise: dict[str, float],
    db: Database,
    mapping: dict[str, tuple[Any, ...]],
    t_s: NDArray[np.float64],
    bursts: list[tuple[int, int]],
    rng: np.random.Generator,
    errors: dict[str, SensorError] | None = None,
) -> dict[str, NDArray[np.float64]]:
    """Sensor readings as they reach the bus: the sensor's own error (lag, gain, offset) where the
    scenario states one, noise, then the DBC's resolution and range, held between sends of the message
    that carries them (a 100 ms message updates every 10th 10 ms sample)."""
    out = {}
    dt = float(t_s[1] - t_s[0]) if len(t_s) > 1 else 0.01
    errors = errors or {}
    for key, true in truth.items():
        if key in errors:
            true = errors[key].apply(true, dt, bursts)
        noisy = true + rng.normal(0.0, noise[key], size=len(true)) if noise[key] > 0 else true.copy()
        if key not in mapping:  # not on this machine's bus (one that sends dp_bar, not high and low)
            out[key] = noisy
            continue
        msg = db.get_message_by_name(mapping[key][0])
        scale, offset = role_conversion(mapping[key])
        if scale == 1.0 and offset == 0.0:
            q = quantize(msg, mapping[key][1], noisy)
        else:  # the signal carries another unit: value_in_role_unit = signal * scale + offset
            q = quantize(msg, mapping[key][1], (noisy - offset) / scale) * scale + offset
        out[key] = hold_between_sends(q, send_every(msg.cycle_time, dt), bursts)
    return out


def role_conversion(ref: tuple[Any, ...]) -> tuple[float, float]:
    """(scale, offset) of a mapping entry (message, signal[, scale, offset]): role = signal * scale + offset."""
    return (float(ref[2]), float(ref[3])) if len(ref) >= 4 else (1.0, 0.0)


def send_every(cycle_time_ms: int | None, dt_s: float) -> int:
    if not cycle_time_ms:
        return 1
    return max(1, round(cycle_time_ms / 1000.0 / dt_s))


def send_mask(n: int, every: int, bursts: list[tuple[int, int]]) -> NDArray[np.bool_]:
    """Samples at which a message with period ``every`` samples goes out; each burst restarts it."""
    mask = np.zeros(n, dtype=bool)
    for a, b in bursts:
        mask[a:b:every] = True
    return mask


def hold_between_sends(x: NDArray[np.float64], every: int, bursts: list[tuple[int, int]]) -> NDArray[np.float64]:
    if every == 1:
        return x
    mask = send_mask(len(x), every, bursts)
    idx = np.maximum.accumulate(np.where(mask, np.arange(len(x)), 0))
    return x[idx]


def motor_direction(motor_speed_rpm: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.where(np.abs(motor_speed_rpm) > MOTOR_STOPPED_RPM, MOTOR_FORWARD, MOTOR_STOPPED).astype(float)
