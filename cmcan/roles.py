"""The vocabulary of quantities cmcan exchanges: roles, their units, the model's inputs, the outputs.

A role is what a value means (pump speed in rpm, delta pressure in bar, ...); a machine's
configuration says where each role is on its bus. The names carry their unit and double as the
simulator's CSV column names. Everything that lists roles imports them from here.
"""

from __future__ import annotations

from dataclasses import dataclass

PUMP_SPEED = "pump_speed_rpm"
PUMP_DISP = "pump_disp_cc"
HIGH_PRESSURE = "high_pressure_bar"
LOW_PRESSURE = "low_pressure_bar"
DP = "dp_bar"
TEMP = "temp_c"
MOTOR_SPEED = "motor_speed_rpm"
MOTOR_DIRECTION = "motor_direction"
FLOW = "flow_lpm"  # delivered flow at a flow meter (an open circuit)

UNITS: dict[str, str] = {
    PUMP_SPEED: "rpm",
    PUMP_DISP: "cm3/rev",
    HIGH_PRESSURE: "bar",
    LOW_PRESSURE: "bar",
    DP: "bar",
    TEMP: "degC",
    MOTOR_SPEED: "rpm",
    MOTOR_DIRECTION: "",
    FLOW: "l/min",
}

# Roles a configuration may map to DBC signals.
MAPPABLE: tuple[str, ...] = (
    PUMP_SPEED,
    PUMP_DISP,
    HIGH_PRESSURE,
    LOW_PRESSURE,
    DP,
    TEMP,
    MOTOR_SPEED,
    MOTOR_DIRECTION,
    FLOW,
)
# Inputs of the model, in its input order.
MODEL_INPUTS: tuple[str, ...] = (PUMP_SPEED, PUMP_DISP, DP, TEMP)
MODEL_UNITS: dict[str, str] = {r: UNITS[r] for r in MODEL_INPUTS}
# What the model predicts and the CM ratio compares: a closed circuit's motor speed (flow over V_M)
# or an open circuit's delivered flow.
QUANTITIES: tuple[str, ...] = (MOTOR_SPEED, FLOW)
# Model inputs a machine may hold constant instead of measuring them (a pump on a constant-speed
# electric motor, a fixed-displacement pump).
FIXABLE: tuple[str, ...] = (PUMP_SPEED, PUMP_DISP)


def gated_roles(quantity: str = MOTOR_SPEED) -> tuple[str, ...]:
    """Roles the monitor keeps windows of and gates on, in this order: the model's inputs and the output."""
    if quantity not in QUANTITIES:
        raise ValueError(f"output quantity {quantity!r} is not one of {', '.join(QUANTITIES)}")
    return (*MODEL_INPUTS, quantity)


# The reference drive's gated roles (motor speed); every role that can be gated, for configuration keys.
GATED: tuple[str, ...] = gated_roles(MOTOR_SPEED)
GATEABLE: tuple[str, ...] = (*MODEL_INPUTS, *QUANTITIES)


@dataclass(frozen=True)
class SignalRef:
    """Where a role is on the bus: value_in_role_unit = physical_value * scale + offset."""

    message: str
    signal: str
    scale: float = 1.0
    offset: float = 0.0


# role -> (DBC message, DBC signal) in the shipped dbc/cmcan.dbc
DEFAULT_INPUTS: dict[str, tuple[str, str]] = {
    PUMP_SPEED: ("PUMP_STATUS", "pump_speed_rpm"),
    PUMP_DISP: ("PUMP_STATUS", "pump_disp_cc"),
    HIGH_PRESSURE: ("LOOP_PRESSURE", "high_pressure_bar"),
    LOW_PRESSURE: ("LOOP_PRESSURE", "low_pressure_bar"),
    TEMP: ("OIL_STATUS", "oil_temp_c"),
    MOTOR_SPEED: ("MOTOR_STATUS", "motor_speed_rpm"),
    MOTOR_DIRECTION: ("MOTOR_STATUS", "motor_direction"),
}

MOTOR_FORWARD = 1
MOTOR_STOPPED = 0

# Each quantity's measured, predicted and white-box values and their validity flag, as the CM frame
# and the timelines name them.
QUANTITY_SIGNALS: dict[str, tuple[str, str, str, str]] = {
    MOTOR_SPEED: ("motor_speed_meas_rpm", "motor_speed_pred_rpm", "motor_speed_whitebox_rpm", "cm_speed_valid"),
    FLOW: ("flow_meas_lpm", "flow_pred_lpm", "flow_whitebox_lpm", "cm_flow_valid"),
}
# The output message that carries them (configuration key under outputs:).
QUANTITY_OUTPUT: dict[str, str] = {MOTOR_SPEED: "cm_speed", FLOW: "cm_flow"}

# The CM output messages (configuration key -> the DBC signals cmcan fills in).
OUTPUT_SIGNALS: dict[str, tuple[str, ...]] = {
    "cm_ratio": (
        "cm_ratio_raw_pct",
        "cm_ratio_filt_pct",
        "extra_leakage_lpm",
        "cm_raw_valid",
        "cm_filt_valid",
        "cm_gate",
        "cm_alive_counter",
    ),
    "cm_speed": (*QUANTITY_SIGNALS[MOTOR_SPEED], "cm_alive_counter"),
    "cm_flow": (*QUANTITY_SIGNALS[FLOW], "cm_alive_counter"),
    "warning": ("warning_level", "warning_reason", "time_below_threshold_s", "warning_count"),
    # the on-board baseline's state and progress, where the configuration enables it
    "cm_baseline": ("baseline_state", "baseline_learned_h", "baseline_coverage_pct", "baseline_distance_lpm"),
    # the prognosis, where the configuration enables it
    "cm_prognosis": (
        "prognosis_state",
        "prognosis_direction",
        "prognosis_to_warning_h",
        "prognosis_to_eol_p10_h",
        "prognosis_to_eol_p50_h",
        "prognosis_to_eol_p90_h",
    ),
}
