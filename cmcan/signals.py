"""Quantities cmcan exchanges, by role, and where the shipped DBC carries each of them.

The names double as the simulator's CSV column names, each with its unit. A machine with another DBC
maps the same roles onto its own messages and signals in its configuration.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SignalRef:
    """Where a role is on the bus: value_in_role_unit = physical_value * scale + offset."""

    message: str
    signal: str
    scale: float = 1.0
    offset: float = 0.0


# role -> (DBC message, DBC signal) in dbc/cmcan.dbc
DEFAULT_INPUTS: dict[str, tuple[str, str]] = {
    "pump_speed_rpm": ("PUMP_STATUS", "pump_speed_rpm"),
    "pump_disp_cc": ("PUMP_STATUS", "pump_disp_cc"),
    "high_pressure_bar": ("LOOP_PRESSURE", "high_pressure_bar"),
    "low_pressure_bar": ("LOOP_PRESSURE", "low_pressure_bar"),
    "temp_c": ("OIL_STATUS", "oil_temp_c"),
    "motor_speed_rpm": ("MOTOR_STATUS", "motor_speed_rpm"),
    "motor_direction": ("MOTOR_STATUS", "motor_direction"),
}

# Inputs of the model, in its input order.
MODEL_INPUTS: tuple[str, ...] = ("pump_speed_rpm", "pump_disp_cc", "dp_bar", "temp_c")
MODEL_UNITS: dict[str, str] = {"pump_speed_rpm": "rpm", "pump_disp_cc": "cm3/rev", "dp_bar": "bar", "temp_c": "degC"}

MOTOR_FORWARD = 1
MOTOR_STOPPED = 0
