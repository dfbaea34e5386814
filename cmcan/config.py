"""The configuration: YAML validated once, field by field, into typed sections; paths resolved.

Each section is a frozen dataclass; nothing else in cmcan reads the YAML. An override is
``dataclasses.replace`` of a section (``with_overrides`` for the command line's). The core's own
parameter types (gate limits, thresholds) are used as they are; checks that need the DBC or the
model live in :mod:`cmcan.assemble`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from cmcan.can.checksums import ALGORITHMS
from cmcan.can.j1939.dm1 import PROPRIETARY_SPNS
from cmcan.can.j1939.name import Name
from cmcan.can.j1939.requests import AnswerLimits
from cmcan.io.points import Condition, PointsError, PointSpec
from cmcan.monitor.baseline import BaselineSettings
from cmcan.monitor.gating import REFERENCE_PUMP_DISP_CC, REFERENCE_PUMP_SPEED_RPM, GateLimits, scaled
from cmcan.monitor.node import ClearTrust
from cmcan.monitor.prognosis import PrognosisParams
from cmcan.monitor.warnings import Thresholds
from cmcan.oil import Oil, oil_from_grade
from cmcan.roles import (
    FIXABLE,
    FLOW,
    GATEABLE,
    MAPPABLE,
    MODEL_INPUTS,
    MOTOR_SPEED,
    QUANTITIES,
    QUANTITY_OUTPUT,
    SignalRef,
)
from cmcan.schema import Bool, Either, Num, Obj, SchemaError, Seq, Str, load_yaml, reference, section, values_of
from cmcan.uplink.config import UPLINK, UplinkSettings

_SIGNAL = Obj(
    {"message": Str(), "signal": Str(), "scale": Num(-1e6, 1e6, default=1.0), "offset": Num(-1e9, 1e9, default=0.0)},
    default=None,
)


def _signals_rule(c: dict[str, Any]) -> tuple[str, str] | None:
    """Every model input and the output quantity come from a signal, or (pump speed and
    displacement) from a constant in drive.fixed; never from both."""
    s, drive = c["signals"], c["drive"]
    fixed = {r for r, v in drive["fixed"].items() if v is not None}
    for role in ("pump_speed_rpm", "pump_disp_cc", "temp_c", drive["quantity"]):
        if role in fixed:
            if s.get(role) is not None:
                return f"signals.{role}", f"also given as a constant in drive.fixed.{role}; keep one"
        elif s.get(role) is None:
            alt = " (or give its constant value in drive.fixed)" if role in FIXABLE else ""
            return f"signals.{role}", f"missing; every machine must map this role to a DBC message and signal{alt}"
    has_dp = s.get("dp_bar") is not None
    has_hl = s.get("high_pressure_bar") is not None and s.get("low_pressure_bar") is not None
    if not (has_dp or has_hl):
        return "signals.dp_bar", "map either dp_bar, or both high_pressure_bar and low_pressure_bar"
    if has_dp and (s.get("high_pressure_bar") is not None or s.get("low_pressure_bar") is not None):
        return "signals.dp_bar", "map dp_bar or high/low pressure, not both"
    return None


def _drive_rule(d: dict[str, Any]) -> tuple[str, str] | None:
    if d["quantity"] == MOTOR_SPEED and d["motor_disp_cc"] is None:
        return "motor_disp_cc", "missing; a motor-speed machine needs V_M, its motor displacement in cm3/rev"
    if d["quantity"] == FLOW and d["motor_disp_cc"] is not None:
        return "motor_disp_cc", "only for quantity motor_speed_rpm: a flow machine's output needs no V_M"
    return None


def _oil_rule(o: dict[str, Any]) -> tuple[str, str] | None:
    if (o["nu40_cst"] is None) != (o["nu100_cst"] is None):
        return "nu100_cst" if o["nu100_cst"] is None else "nu40_cst", "give both nu40_cst and nu100_cst, or neither"
    if o["nu40_cst"] is not None and o["nu100_cst"] >= o["nu40_cst"]:
        return "nu100_cst", f"must be below nu40_cst ({o['nu40_cst']:g} cSt): oil thins as it warms"
    if o["nu40_cst"] is None:
        try:
            oil_from_grade(o["grade"])
        except ValueError as exc:
            return "grade", str(exc)
    return None


def _gating_rule(c: dict[str, Any]) -> tuple[str, str] | None:
    if c["drive"]["quantity"] != MOTOR_SPEED and c["gating"]["min_motor_speed_rpm"] is not None:
        return "gating.min_motor_speed_rpm", "only for quantity motor_speed_rpm; use min_flow_lpm"
    if c["gating"]["min_motor_speed_rpm"] is not None and c["gating"]["min_flow_lpm"] is not None:
        return "gating.min_flow_lpm", "give min_motor_speed_rpm or min_flow_lpm, not both"
    return None


def _config_rule(c: dict[str, Any]) -> tuple[str, str] | None:
    return _signals_rule(c) or _gating_rule(c)


def _baseline_rule(b: dict[str, Any]) -> tuple[str, str] | None:
    if not b["learning_low_pct"] < 100.0 < b["learning_high_pct"]:
        return "learning_low_pct", "the learning band must hold 100 %"
    return None


def _prognosis_rule(p: dict[str, Any]) -> tuple[str, str] | None:
    kind, value = p["end_of_life"]["kind"], p["end_of_life"]["value"]
    if kind == "ratio_pct" and not 50.0 <= value < 100.0:
        return "end_of_life", f"a ratio end of life must lie in [50, 100) %, got {value:g}"
    return None


# The prognosis: operating hours to the warning and to end of life (cmcan.monitor.prognosis;
# docs/prognosis.md). Its settings are declared once, in PrognosisParams.
_PROGNOSIS_HEAD = {"enabled": (Bool(default=False), "estimate the operating hours to the warning and to end of life")}
_PROGNOSIS = section(PrognosisParams, {k: spec for k, (spec, _) in _PROGNOSIS_HEAD.items()}, _prognosis_rule)


# The machine's own baseline, learned on board (cmcan.monitor.baseline; docs/commissioning.md). Its
# settings are declared once, in BaselineSettings.
_BASELINE_HEAD = {"enabled": (Bool(default=False), "learn the machine's own baseline on board")}
_BASELINE = section(BaselineSettings, {k: spec for k, (spec, _) in _BASELINE_HEAD.items()}, _baseline_rule)


def _threshold_rule(t: dict[str, Any]) -> tuple[str, str] | None:
    if t["low_pct"] >= t["high_pct"]:
        return "low_pct", f"must be below high_pct ({t['high_pct']}), got {t['low_pct']}"
    if t["hysteresis_pct"] * 2 >= t["high_pct"] - t["low_pct"]:
        return "hysteresis_pct", "must be less than half the band between low_pct and high_pct"
    return None


def _output(default_msg: str, period: int) -> Obj:
    return Obj(
        {"message": Str(default=default_msg), "period_ms": Num(10, 60000, "ms", default=period, integer=True)},
        default={},
    )


_CONFIG = Obj(
    {
        "bus": Obj(
            {
                "interface": Str(default="socketcan"),
                "channel": Str(default="can0"),
                "bitrate": Num(10_000, 1_000_000, "bit/s", default=250_000, integer=True),
                "receive_buffer_bytes": Num(0, 1 << 28, "bytes", default=8 << 20, integer=True),
            },
            default={},
        ),
        "dbc": Str(),
        "model": Str(default="default"),
        "drive": Obj(
            {
                "quantity": Str(default=MOTOR_SPEED, choices=QUANTITIES),
                "motor_disp_cc": Num(1, 2000, "cm3/rev", default=None),
                "pump_speed_nominal_rpm": Num(1, 20000, "rpm", default=REFERENCE_PUMP_SPEED_RPM),
                "pump_disp_max_cc": Num(0.01, 5000, "cm3/rev", default=REFERENCE_PUMP_DISP_CC),
                "fixed": Obj(
                    {
                        "pump_speed_rpm": Num(0, 20000, "rpm", default=None),
                        "pump_disp_cc": Num(-5000, 5000, "cm3/rev", default=None),
                    },
                    default={},
                ),
            },
            rule=_drive_rule,
        ),
        "oil": Obj(
            {
                "grade": Str(default="VG46"),
                "nu40_cst": Num(1, 5000, "cSt", default=None),
                "nu100_cst": Num(0.5, 500, "cSt", default=None),
            },
            default={},
            rule=_oil_rule,
        ),
        "signals": Obj({r: _SIGNAL for r in MAPPABLE}),
        "points": Obj(
            {
                "columns": Obj({r: Str(default=None) for r in (*MODEL_INPUTS, *QUANTITIES)}, default={}),
                "constants": Obj({r: Num(-1e9, 1e9, default=None) for r in MODEL_INPUTS}, default={}),
                "where": Seq(Str(), default=[]),
            },
            default={},
        ),
        "evaluation": Obj({"rate_hz": Num(0.5, 100, "Hz", default=10.0)}, default={}),
        "max_signal_age_s": Obj(
            {
                "default": Num(0.01, 3600, "s", default=0.5),
                **{r: Num(0.01, 3600, "s", default=None) for r in GATEABLE},
            },
            default={},
        ),
        "gating": Obj(
            {
                "window_s": Num(0.1, 3600, "s", default=1.0),
                "min_samples": Num(1, 10000, default=5, integer=True),
                # Absolute minimums; unset, the reference drive's scaled to drive: (gating.scaled).
                "min_pump_speed_rpm": Num(0, 20000, "rpm", default=None),
                "min_pump_disp_cc": Num(0, 5000, "cm3/rev", default=None),
                "min_motor_speed_rpm": Num(0, 20000, "rpm", default=None),
                "min_flow_lpm": Num(0, 100000, "l/min", default=None),
                "max_std": Obj({r: Num(0, 1e4, default=None) for r in GATEABLE}, default={}),
                "envelope_margin_pct": Num(-50, 100, "%", default=0.0),
            },
            default={},
        ),
        "filter": Obj(
            {
                "samples": Num(1, 1_000_000, default=300, integer=True),
                "min_samples": Num(1, 1_000_000, default=50, integer=True),
            },
            default={},
            rule=lambda f: (
                ("min_samples", f"must not exceed samples ({f['samples']})")
                if f["min_samples"] > f["samples"]
                else None
            ),
        ),
        "thresholds": Obj(
            {
                "low_pct": Num(50, 100, "%", default=98.0),
                "high_pct": Num(100, 200, "%", default=102.0),
                "hysteresis_pct": Num(0, 10, "%", default=0.5),
                "debounce_s": Num(0, 86400, "s", default=60.0),
                "fault_after_s": Num(0.1, 3600, "s", default=5.0),
            },
            default={},
            rule=_threshold_rule,
        ),
        "outputs": Obj(
            {
                "cm_ratio": _output("CM_RATIO", 100),
                "cm_speed": _output("CM_SPEED", 100),
                "cm_flow": _output("CM_FLOW", 100),
                "warning": _output("CM_WARNING", 1000),
                "cm_baseline": _output("CM_BASELINE", 1000),
                "cm_prognosis": _output("CM_PROGNOSIS", 1000),
            },
            default={},
        ),
        "state": Obj(
            {"directory": Str(default="/var/lib/cmcan"), "save_every_s": Num(1, 86400, "s", default=60.0)}, default={}
        ),
        "uplink": UPLINK,  # validated by cmcan.uplink.config, disabled by default
        "baseline": _BASELINE,
        "prognosis": _PROGNOSIS,
    },
    rule=_config_rule,
)


# -- machine buses: channels, frame formats, per-message matching and health, J1939 ---------------------

_ADDRESS = Num(0, 253, integer=True)  # J1939 unicast source addresses (254 null, 255 global)
_SOURCES = Either((Str(choices=("any",)), Seq(_ADDRESS, min_len=1)), default=None)
_SPN = Num(PROPRIETARY_SPNS.start, PROPRIETARY_SPNS.stop - 1, integer=True)


def _j1939_rule(j: dict[str, Any]) -> tuple[str, str] | None:
    if j["enabled"] and j["source_address"] is None:
        return "source_address", "missing; a J1939 node sends from its own source address (0..253)"
    if j["dm1"]["enabled"] and not j["enabled"]:
        return "dm1.enabled", "DM1 is a J1939 message: set j1939.enabled: true as well"
    if j["dm1"]["spn"] == j["dm1"]["input_spn"]:
        return "dm1.input_spn", "must differ from dm1.spn (the inputs' faults are another DTC than the condition)"
    if j["source_address"] is not None and j["source_address"] in j["clears"]["trusted_addresses"]:
        return "clears.trusted_addresses", f"includes cmcan's own address {j['source_address']}: never trusted"
    return _name_rule(j)


def _name_rule(j: dict[str, Any]) -> tuple[str, str] | None:
    """An arbitrary address capable NAME needs the addresses it may move to, and only it has them."""
    capable = j["name"] is not None and j["name"]["arbitrary_address_capable"]
    if j["addresses"] and j["name"] is None:
        return "addresses", "the addresses an arbitrary address capable node moves to: give j1939.name as well"
    if capable and not [a for a in j["addresses"] if a != j["source_address"]]:
        return "addresses", (
            "missing; an arbitrary address capable NAME moves to one of these when it loses its address "
            "(e.g. [0x8D, 0x8E, 0x8F]), or set name.arbitrary_address_capable: false"
        )
    if j["addresses"] and not capable:
        return (
            "name.arbitrary_address_capable",
            "is false: a node that is not arbitrary address capable never moves; drop j1939.addresses or set it true",
        )
    if len(set(j["addresses"])) != len(j["addresses"]):
        return "addresses", "lists an address twice"
    return None


_NAME = Obj(
    {
        "identity_number": Num(0, (1 << 21) - 1, integer=True),
        "manufacturer_code": Num(0, (1 << 11) - 1, integer=True),
        "function": Num(0, 255, integer=True),
        "industry_group": Num(0, 7, integer=True, default=0),
        "arbitrary_address_capable": Bool(default=False),
        "ecu_instance": Num(0, 7, integer=True, default=0),
        "function_instance": Num(0, 31, integer=True, default=0),
        "vehicle_system": Num(0, 127, integer=True, default=0),
        "vehicle_system_instance": Num(0, 15, integer=True, default=0),
    },
    default=None,
)


_BUS_SECTIONS = {
    "frames": Obj(
        {"extended_ids": Bool(default=False), "fd": Bool(default=False)},
        default={},
    ),
    "channels": Obj(
        {
            "extra": Seq(
                Obj(
                    {
                        "channel": Str(),
                        "bitrate": Num(10_000, 1_000_000, "bit/s", default=None, integer=True),
                        "fd": Bool(default=False),
                    }
                ),
                default=[],
            ),
            "outputs": Str(default=None),
            "from_log": Obj({}, extra=Str(), default={}),
        },
        default={},
    ),
    "messages": Obj(
        {},
        extra=Obj(
            {
                "channel": Str(default=None),
                "source_addresses": _SOURCES,
                # its cycle time when the DBC has none (or to correct it): fits windows and timeouts
                "cycle_ms": Num(1, 3_600_000, "ms", default=None),
                # PDU1 messages: the destination addresses accepted (default: any; 255 is global)
                "destinations": Either(
                    (Str(choices=("any",)), Seq(Num(0, 255, integer=True), min_len=1)), default="any"
                ),
                "counter": Str(default=None),
                "checksum_signal": Str(default=None),
                "checksum": Str(choices=(*ALGORITHMS, "none"), default=None),
            }
        ),
        default={},
    ),
    "input_health": Obj(
        {
            "timeout_cycles": Num(1, 1000, "cycles", default=10.0),
            "max_counter_step": Num(1, 1000, integer=True, default=2),
            "checksum": Str(choices=(*ALGORITHMS, "none"), default=None),
        },
        default={},
    ),
    "j1939": Obj(
        {
            "enabled": Bool(default=False),
            "source_address": Num(0, 253, integer=True, default=None),
            "source_addresses": Either((Str(choices=("any",)), Seq(_ADDRESS, min_len=1)), default="any"),
            "bam_packet_gap_ms": Num(50, 200, "ms", default=100.0),
            "dm1": Obj(
                {
                    "enabled": Bool(default=False),
                    "spn": Num(PROPRIETARY_SPNS.start, PROPRIETARY_SPNS.stop - 1, integer=True, default=520192),
                    "input_spn": Num(PROPRIETARY_SPNS.start, PROPRIETARY_SPNS.stop - 1, integer=True, default=520193),
                    "low_severe_pct": Num(50, 100, "%", default=96.0),
                    "high_severe_pct": Num(100, 200, "%", default=104.0),
                    "period_ms": Num(100, 60000, "ms", default=1000, integer=True),
                },
                default={},
            ),
            # J1939-81: with a NAME cmcan claims source_address before it sends anything else
            "name": _NAME,
            "addresses": Seq(Num(0, 253, integer=True), default=[]),
            "request_interval_ms": Num(50, 10000, "ms", default=300.0),
            # J1939-73 DM3/DM11: who may clear (declared once, in ClearTrust)
            "clears": section(ClearTrust),
            # all requesters together: a global rate and a bound on answers waiting (declared once, in AnswerLimits)
            "answers": section(AnswerLimits),
        },
        default={},
        rule=_j1939_rule,
    ),
}
_CONFIG = replace(_CONFIG, fields={**_CONFIG.fields, **_BUS_SECTIONS})  # the rules stay


@dataclass(frozen=True)
class BusConfig:
    interface: str  # a python-can interface: socketcan, virtual, pcan, ...
    channel: str
    bitrate: int
    receive_buffer_bytes: int


@dataclass(frozen=True)
class DriveConfig:
    quantity: str  # what the model predicts: motor_speed_rpm (closed circuit) or flow_lpm (open circuit)
    motor_disp_cc: float | None  # V_M at the motor's fixed displacement setting; None for flow
    pump_speed_nominal_rpm: float  # sizes the gates (gating.scaled)
    pump_disp_max_cc: float
    fixed: dict[str, float] = field(default_factory=dict)  # model inputs held constant, no sensor

    @property
    def lpm_per_unit(self) -> float:
        """Flow in l/min per unit of the quantity: V_M / 1000 for motor speed, 1 for flow."""
        if self.quantity == MOTOR_SPEED:
            assert self.motor_disp_cc is not None
            return self.motor_disp_cc / 1000.0
        return 1.0

    @property
    def nominal_flow_lpm(self) -> float:
        return self.pump_speed_nominal_rpm * self.pump_disp_max_cc / 1000.0


@dataclass(frozen=True)
class EvaluationConfig:
    rate_hz: float


@dataclass(frozen=True)
class SignalAges:
    """Largest age of a role's newest sample before it counts as stale."""

    default_s: float
    per_role_s: dict[str, float] = field(default_factory=dict)

    def of(self, role: str) -> float:
        return self.per_role_s.get(role, self.default_s)


@dataclass(frozen=True)
class GatingConfig:
    limits: GateLimits
    envelope_margin_pct: float  # widen (+) or narrow (-) the model's training envelope by this share of its span


@dataclass(frozen=True)
class BaselineConfig:
    """The ``baseline`` section: on or off, and its settings (declared once, in
    :class:`~cmcan.monitor.baseline.BaselineSettings`)."""

    enabled: bool = False
    settings: BaselineSettings = field(default_factory=BaselineSettings)

    @classmethod
    def on(cls, **settings: Any) -> BaselineConfig:
        """The baseline enabled with these settings, the rest their defaults."""
        return cls(True, BaselineSettings(**settings))


@dataclass(frozen=True)
class PrognosisConfig:
    """The ``prognosis`` section: on or off, and its settings as the core takes them (declared once,
    in :class:`~cmcan.monitor.prognosis.PrognosisParams`; the warning thresholds and the oil are
    given at assembly from their own sections)."""

    enabled: bool = False
    params: PrognosisParams = field(default_factory=PrognosisParams)

    @classmethod
    def on(cls, **settings: Any) -> PrognosisConfig:
        """The prognosis enabled with these settings (by field name), the rest their defaults."""
        return cls(True, PrognosisParams(**settings))


@dataclass(frozen=True)
class FilterConfig:
    samples: int
    min_samples: int


@dataclass(frozen=True)
class OutputMessageConfig:
    message: str
    period_ms: int


@dataclass(frozen=True)
class OutputsConfig:
    cm_ratio: OutputMessageConfig
    cm_speed: OutputMessageConfig
    warning: OutputMessageConfig
    cm_flow: OutputMessageConfig = OutputMessageConfig("CM_FLOW", 100)
    cm_baseline: OutputMessageConfig = OutputMessageConfig("CM_BASELINE", 1000)
    cm_prognosis: OutputMessageConfig = OutputMessageConfig("CM_PROGNOSIS", 1000)

    def items(
        self, quantity: str = MOTOR_SPEED, baseline: bool = False, prognosis: bool = False
    ) -> list[tuple[str, OutputMessageConfig]]:
        """The messages a machine of this output quantity sends (CM_SPEED or CM_FLOW in the middle),
        then CM_BASELINE and CM_PROGNOSIS where the on-board baseline and the prognosis are enabled."""
        key = QUANTITY_OUTPUT[quantity]
        out = [("cm_ratio", self.cm_ratio), (key, getattr(self, key)), ("warning", self.warning)]
        out += [("cm_baseline", self.cm_baseline)] if baseline else []
        return out + ([("cm_prognosis", self.cm_prognosis)] if prognosis else [])


@dataclass(frozen=True)
class StateConfig:
    directory: Path
    save_every_s: float
    origin: str = ""  # who named the directory, for messages: "" the file's state.directory, or "--state-dir"


@dataclass(frozen=True)
class ChannelConfig:
    """One bus cmcan opens: its channel name, bitrate (None: as bus.bitrate) and whether it is CAN FD."""

    name: str
    bitrate: int | None = None
    fd: bool = False


@dataclass(frozen=True)
class FramesConfig:
    extended_ids: bool = False  # 29-bit identifiers in the mapping and the outputs
    fd: bool = False  # bus.channel is a CAN FD bus


@dataclass(frozen=True)
class ChannelsConfig:
    extra: tuple[ChannelConfig, ...] = ()  # buses besides bus.channel, on bus.interface
    outputs: str | None = None  # where cmcan sends (None: bus.channel)
    from_log: dict[str, str] = field(default_factory=dict)  # a log's channel names -> configured channels


@dataclass(frozen=True)
class MessageConfig:
    """Per input message: its channel, J1939 source addresses, and how its health is checked."""

    channel: str | None = None  # None: bus.channel
    source_addresses: tuple[int, ...] | None = None  # None: j1939.source_addresses
    source_addresses_set: bool = False  # given here (not the default)
    counter: str | None = None  # a signal name, "none", or None: found by name in the DBC
    checksum_signal: str | None = None  # None: found by name in the DBC
    checksum: str | None = None  # an algorithm, "none", or None: input_health.checksum
    destinations: tuple[int, ...] | None = None  # PDU1: the destinations accepted; None: any
    cycle_ms: float | None = None  # None: the DBC's GenMsgCycleTime


@dataclass(frozen=True)
class HealthConfig:
    timeout_cycles: float = 10.0  # a message missing this many DBC cycle times is stale
    max_counter_step: int = 2  # an alive counter advancing by more has jumped
    checksum: str | None = None  # the algorithm of checksum signals found in the DBC


@dataclass(frozen=True)
class Dm1Config:
    enabled: bool = False
    spn: int = 520192
    input_spn: int = 520193
    low_severe_pct: float = 96.0
    high_severe_pct: float = 104.0
    period_ms: int = 1000


@dataclass(frozen=True)
class J1939Config:
    enabled: bool = False
    source_address: int | None = None  # cmcan's own
    source_addresses: tuple[int, ...] | None = None  # senders accepted by default; None: any
    bam_packet_gap_ms: float = 100.0
    dm1: Dm1Config = field(default_factory=Dm1Config)
    name: Name | None = None  # J1939-81 NAME: cmcan claims its address (None: a fixed address, no claim)
    addresses: tuple[int, ...] = ()  # an arbitrary address capable NAME's addresses to move to, in order
    request_interval_ms: float = 300.0  # one answer per requester and PGN per this much frame time
    clears: ClearTrust = field(default_factory=ClearTrust)  # who may clear DTCs (DM3/DM11): nobody by default
    answers: AnswerLimits = field(default_factory=AnswerLimits)  # answers to requests, all requesters together


@dataclass(frozen=True)
class Config:
    source: str  # the file it came from, for messages
    bus: BusConfig
    dbc_path: Path
    model_path: Path | None  # None: the model shipped with cmcan
    drive: DriveConfig
    oil: Oil  # the oil's viscosity law, for the model's laminar leakage term
    signals: dict[str, SignalRef]  # role -> where it is on the bus
    evaluation: EvaluationConfig
    max_signal_age: SignalAges
    gating: GatingConfig
    filter: FilterConfig
    thresholds: Thresholds
    outputs: OutputsConfig
    state: StateConfig
    uplink: UplinkSettings  # the telematics uplink (disabled by default); its outbox in the state directory
    # How an operating-point table's columns map onto roles (cmcan train/score --points).
    points: PointSpec = field(default_factory=PointSpec)
    frames: FramesConfig = field(default_factory=FramesConfig)
    channels: ChannelsConfig = field(default_factory=ChannelsConfig)
    messages: dict[str, MessageConfig] = field(default_factory=dict)
    input_health: HealthConfig = field(default_factory=HealthConfig)
    j1939: J1939Config = field(default_factory=J1939Config)
    baseline: BaselineConfig = field(default_factory=BaselineConfig)
    prognosis: PrognosisConfig = field(default_factory=PrognosisConfig)

    def output_items(self) -> list[tuple[str, OutputMessageConfig]]:
        """The output messages this machine sends (:meth:`OutputsConfig.items`)."""
        return self.outputs.items(self.quantity, self.baseline.enabled, self.prognosis.enabled)

    @property
    def channel_list(self) -> tuple[ChannelConfig, ...]:
        """Every bus cmcan opens, bus.channel first."""
        return (ChannelConfig(self.bus.channel, self.bus.bitrate, self.frames.fd), *self.channels.extra)

    @property
    def output_channel(self) -> str:
        return self.channels.outputs or self.bus.channel

    def message(self, name: str) -> MessageConfig:
        return self.messages.get(name, MessageConfig())

    def message_channel(self, name: str) -> str:
        return self.message(name).channel or self.bus.channel

    @property
    def motor_disp_cc(self) -> float | None:
        return self.drive.motor_disp_cc

    @property
    def quantity(self) -> str:
        return self.drive.quantity

    @property
    def lpm_per_unit(self) -> float:
        return self.drive.lpm_per_unit

    @property
    def gate_limits(self) -> GateLimits:
        return self.gating.limits

    @property
    def rate_hz(self) -> float:
        return self.evaluation.rate_hz

    def max_age_s(self, role: str) -> float:
        return self.max_signal_age.of(role)


def default_config_path() -> Path:
    here = Path(__file__).resolve().parent
    for candidate in (here / "_data" / "config" / "cmcan.yaml", here.parent / "config" / "cmcan.yaml"):
        if candidate.exists():
            return candidate
    raise FileNotFoundError("the shipped config/cmcan.yaml was not found next to the cmcan package")


def _path(base_dir: Path, p: str) -> Path:
    return Path(p) if Path(p).is_absolute() else (base_dir / p).resolve()


def _gate_limits(raw: dict[str, Any], drive: DriveConfig) -> GateLimits:
    """The reference drive's gates scaled to this machine, then the values the file sets."""
    g = raw["gating"]
    base = scaled(drive.quantity, drive.lpm_per_unit, drive.pump_speed_nominal_rpm, drive.pump_disp_max_cc)
    over: dict[str, Any] = {"window_s": g["window_s"], "min_samples": g["min_samples"]}
    if g["min_pump_speed_rpm"] is not None:
        over["min_pump_speed_rpm"] = g["min_pump_speed_rpm"]
    if g["min_pump_disp_cc"] is not None:
        over["min_pump_disp_cc"] = g["min_pump_disp_cc"]
    if g["min_motor_speed_rpm"] is not None:
        over["min_output"] = g["min_motor_speed_rpm"]
    if g["min_flow_lpm"] is not None:
        over["min_output"] = g["min_flow_lpm"] / drive.lpm_per_unit
    over["max_std"] = {**base.max_std, **{k: v for k, v in g["max_std"].items() if v is not None}}
    return replace(base, **over)


def _oil(o: dict[str, Any]) -> Oil:
    if o["nu40_cst"] is not None:
        return Oil(nu40_cst=float(o["nu40_cst"]), nu100_cst=float(o["nu100_cst"]))
    return oil_from_grade(o["grade"])


def _points(raw: dict[str, Any], drive: DriveConfig, source: str) -> PointSpec:
    """The points section as a spec; roles it does not name are read from a column of the role's
    name, the drive's fixed inputs are constants."""
    pts = raw["points"]
    consts = {**drive.fixed, **{r: float(v) for r, v in pts["constants"].items() if v is not None}}
    named = {r: c for r, c in pts["columns"].items() if c is not None}
    both = sorted(set(named) & set(consts))
    if both:
        raise SchemaError(source, f"points.columns.{both[0]}", "also a constant (points.constants or drive.fixed)")
    roles = (*MODEL_INPUTS, drive.quantity)
    cols = {r: named.get(r, r) for r in roles if r not in consts}
    try:
        where = tuple(Condition.parse(w, f"points.where[{i}]") for i, w in enumerate(pts["where"]))
    except PointsError as exc:
        raise SchemaError(source, "", str(exc)) from None
    return PointSpec(cols, consts, where, f"{source} (points:)")


def from_dict(data: Any, source: str, base_dir: Path) -> Config:
    """Validate a parsed YAML document and build the typed configuration (SchemaError names the field)."""
    raw = _CONFIG.check(data, source, "")
    d = raw["drive"]
    drive = DriveConfig(
        quantity=d["quantity"],
        motor_disp_cc=None if d["motor_disp_cc"] is None else float(d["motor_disp_cc"]),
        pump_speed_nominal_rpm=float(d["pump_speed_nominal_rpm"]),
        pump_disp_max_cc=float(d["pump_disp_max_cc"]),
        fixed={r: float(v) for r, v in d["fixed"].items() if v is not None},
    )
    ages = raw["max_signal_age_s"]
    th = raw["thresholds"]
    out = raw["outputs"]
    eol_high = raw["prognosis"]["end_of_life"]["high_pct"]
    if raw["prognosis"]["enabled"] and not th["low_pct"] < 100.0 < th["high_pct"]:
        field_ = "thresholds.low_pct" if th["low_pct"] >= 100.0 else "thresholds.high_pct"
        raise SchemaError(source, field_, "the prognosis needs a band around 100 % (low_pct < 100 < high_pct)")
    eol = raw["prognosis"]["end_of_life"]
    if raw["prognosis"]["enabled"] and eol["kind"] == "ratio_pct" and not eol["value"] < th["low_pct"]:
        raise SchemaError(
            source,
            "prognosis.end_of_life.value",
            f"a ratio end of life must lie below thresholds.low_pct ({th['low_pct']:g} %): the warning comes first",
        )
    if raw["prognosis"]["enabled"] and not eol_high > th["high_pct"]:
        raise SchemaError(
            source, "prognosis.end_of_life.high_pct", f"must lie above thresholds.high_pct ({th['high_pct']:g})"
        )
    # relative to the configuration file like every path in it (not to the working directory, which is
    # / under systemd); the uplink's outbox is relative to this directory
    state_dir = _path(base_dir, raw["state"]["directory"])
    cfg = Config(
        source=source,
        bus=BusConfig(**raw["bus"]),
        dbc_path=_path(base_dir, raw["dbc"]),
        model_path=None if raw["model"] == "default" else _path(base_dir, raw["model"]),
        drive=drive,
        oil=_oil(raw["oil"]),
        signals={r: SignalRef(**v) for r, v in raw["signals"].items() if v is not None},
        evaluation=EvaluationConfig(rate_hz=float(raw["evaluation"]["rate_hz"])),
        max_signal_age=SignalAges(ages["default"], {r: v for r, v in ages.items() if r != "default" and v is not None}),
        gating=GatingConfig(_gate_limits(raw, drive), raw["gating"]["envelope_margin_pct"]),
        filter=FilterConfig(**raw["filter"]),
        thresholds=Thresholds(
            th["low_pct"], th["high_pct"], th["hysteresis_pct"], th["debounce_s"], th["fault_after_s"]
        ),
        outputs=OutputsConfig(**{k: OutputMessageConfig(**v) for k, v in out.items()}),
        state=StateConfig(state_dir, float(raw["state"]["save_every_s"])),
        uplink=UplinkSettings.from_raw(raw["uplink"], state_dir, base_dir, source),
        points=_points(raw, drive, source),
        baseline=_baseline(raw["baseline"]),
        prognosis=_prognosis(raw["prognosis"], th),
    )
    return _with_bus_sections(cfg, raw, source)


def _prognosis(p: dict[str, Any], th: dict[str, Any]) -> PrognosisConfig:
    """The section as the core takes it, on the warning thresholds (checked against it above); a
    section switched off keeps the defaults (its settings checked, not used)."""
    if not p["enabled"]:
        return PrognosisConfig()
    settings = values_of(PrognosisParams, p)
    return PrognosisConfig(True, PrognosisParams(low_pct=th["low_pct"], high_pct=th["high_pct"], **settings))


def _baseline(b: dict[str, Any]) -> BaselineConfig:
    values = values_of(BaselineSettings, b)
    values["edges"] = {r: tuple(float(v) for v in e) for r, e in values["edges"].items() if e is not None}
    return BaselineConfig(b["enabled"], BaselineSettings(**values))


def _sources(v: Any) -> tuple[int, ...] | None:
    return None if v is None or v == "any" else tuple(int(x) for x in v)


def _with_bus_sections(cfg: Config, raw: dict[str, Any], source: str) -> Config:
    """The machine's bus sections (channels, frame formats, messages, health, J1939), checked across."""
    ch = raw["channels"]
    names = [cfg.bus.channel]
    extra = []
    for i, e in enumerate(ch["extra"]):
        if e["channel"] in names:
            raise SchemaError(source, f"channels.extra[{i}].channel", f"{e['channel']!r} is already a channel")
        names.append(e["channel"])
        extra.append(ChannelConfig(e["channel"], e["bitrate"], e["fd"]))
    known = f"configured channels: {', '.join(names)}"
    if ch["outputs"] is not None and ch["outputs"] not in names:
        raise SchemaError(source, "channels.outputs", f"{ch['outputs']!r} is not a configured channel ({known})")
    for log_name, target in ch["from_log"].items():
        if target not in names:
            raise SchemaError(
                source, f"channels.from_log.{log_name}", f"{target!r} is not a configured channel ({known})"
            )
    messages = {}
    for name, m in raw["messages"].items():
        if m["channel"] is not None and m["channel"] not in names:
            raise SchemaError(
                source, f"messages.{name}.channel", f"{m['channel']!r} is not a configured channel ({known})"
            )
        messages[name] = MessageConfig(
            m["channel"],
            _sources(m["source_addresses"]),
            m["source_addresses"] is not None,
            m["counter"],
            m["checksum_signal"],
            m["checksum"],
            _sources(m["destinations"]),
            None if m["cycle_ms"] is None else float(m["cycle_ms"]),
        )
    inputs = {v["message"] for v in raw["signals"].values() if v is not None}
    for name in messages:
        if name not in inputs:
            raise SchemaError(
                source, f"messages.{name}", f"not an input message of signals: (they are {', '.join(sorted(inputs))})"
            )
    h = raw["input_health"]
    j = raw["j1939"]
    if j["enabled"] and not raw["frames"]["extended_ids"]:
        raise SchemaError(source, "frames.extended_ids", "J1939 needs 29-bit identifiers: set it to true")
    d = j["dm1"]
    th = cfg.thresholds
    if d["enabled"] and d["low_severe_pct"] >= th.low_pct:
        raise SchemaError(
            source,
            "j1939.dm1.low_severe_pct",
            f"must be below thresholds.low_pct ({th.low_pct:g}), got {d['low_severe_pct']:g}",
        )
    if d["enabled"] and d["high_severe_pct"] <= th.high_pct:
        raise SchemaError(
            source,
            "j1939.dm1.high_severe_pct",
            f"must be above thresholds.high_pct ({th.high_pct:g}), got {d['high_severe_pct']:g}",
        )
    own = j["source_address"]
    for name, m in messages.items():
        if own is not None and m.source_addresses is not None and own in m.source_addresses:
            raise SchemaError(source, f"messages.{name}.source_addresses", f"includes cmcan's own address {own}")
    default_sources = _sources(j["source_addresses"])
    if j["name"] is not None and not j["enabled"]:
        raise SchemaError(source, "j1939.name", "a NAME is claimed on a J1939 bus: set j1939.enabled: true as well")
    if own is not None and default_sources is not None and own in default_sources:
        raise SchemaError(source, "j1939.source_addresses", f"includes cmcan's own address {own}")
    return replace(
        cfg,
        frames=FramesConfig(**raw["frames"]),
        channels=ChannelsConfig(tuple(extra), ch["outputs"], dict(ch["from_log"])),
        messages=messages,
        input_health=HealthConfig(float(h["timeout_cycles"]), h["max_counter_step"], h["checksum"]),
        j1939=J1939Config(
            j["enabled"],
            own,
            default_sources,
            float(j["bam_packet_gap_ms"]),
            Dm1Config(**d),
            Name(**j["name"]) if j["name"] is not None else None,
            tuple(j["addresses"]),
            float(j["request_interval_ms"]),
            ClearTrust(**values_of(ClearTrust, j["clears"])),
            AnswerLimits(**values_of(AnswerLimits, j["answers"])),
        ),
    )


def load(path: str | Path | None = None) -> Config:
    """The configuration at ``path`` (the shipped one by default); SchemaError names file and field."""
    p = Path(path) if path is not None else default_config_path()
    return from_dict(load_yaml(p), str(p), p.resolve().parent)


def rename_channels(cfg: Config, names: Mapping[str, str]) -> Config:
    """The configuration with channels renamed (``old: new``) wherever it names them."""

    def ren(name: str | None) -> str | None:
        return names.get(name, name) if name is not None else None

    return replace(
        cfg,
        bus=replace(cfg.bus, channel=names.get(cfg.bus.channel, cfg.bus.channel)),
        channels=replace(
            cfg.channels,
            extra=tuple(replace(c, name=names.get(c.name, c.name)) for c in cfg.channels.extra),
            outputs=ren(cfg.channels.outputs),
            from_log={k: names.get(v, v) for k, v in cfg.channels.from_log.items()},
        ),
        messages={k: replace(m, channel=ren(m.channel)) for k, m in cfg.messages.items()},
    )


def with_overrides(
    cfg: Config, interface: str | None = None, channel: str | None = None, state_dir: str | None = None
) -> Config:
    """The command line's overrides of bus and state directory. A new bus.channel takes the old one's
    place wherever the configuration names it (messages, outputs, log channel names); the uplink's
    outbox moves with the state directory when it lives there. A relative ``state_dir`` is relative
    to the working directory, as a command line's paths are (the file's are relative to the file)."""
    if channel and channel != cfg.bus.channel:
        cfg = rename_channels(cfg, {cfg.bus.channel: channel})
    bus = replace(cfg.bus, **({"interface": interface} if interface else {}))
    if not state_dir:
        return replace(cfg, bus=bus)
    state = replace(cfg.state, directory=Path(state_dir), origin="--state-dir")
    uplink = cfg.uplink
    if uplink.outbox.path.is_relative_to(cfg.state.directory):  # the outbox lives in the state directory
        outbox = replace(uplink.outbox, path=Path(state_dir) / uplink.outbox.path.relative_to(cfg.state.directory))
        uplink = replace(uplink, outbox=outbox)
    return replace(cfg, bus=bus, state=state, uplink=uplink)


__all__ = [
    "Config",
    "SchemaError",
    "SignalRef",
    "default_config_path",
    "from_dict",
    "load",
    "rename_channels",
    "with_overrides",
]


def reference_rows() -> list[str]:
    """The configuration reference of the sections whose settings are declared once (Markdown rows
    for docs/configuration.md)."""
    return [
        *reference(BaselineSettings, "baseline", _BASELINE_HEAD),
        "",
        *reference(PrognosisParams, "prognosis", _PROGNOSIS_HEAD),
        "",
        *reference(ClearTrust, "j1939.clears"),
        "",
        *reference(AnswerLimits, "j1939.answers"),
    ]
