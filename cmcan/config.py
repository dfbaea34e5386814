"""The configuration: YAML validated once, field by field, into typed sections; paths resolved.

Each section is a frozen dataclass; nothing else in cmcan reads the YAML. An override is
``dataclasses.replace`` of a section (``with_overrides`` for the command line's). The core's own
parameter types (gate limits, thresholds) are used as they are; checks that need the DBC or the
model live in :mod:`cmcan.assemble`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from cmcan.monitor.gating import GateLimits
from cmcan.monitor.warnings import Thresholds
from cmcan.roles import GATED, MAPPABLE, SignalRef
from cmcan.schema import Num, Obj, SchemaError, Str, load_yaml
from cmcan.uplink.config import UPLINK, UplinkSettings

_SIGNAL = Obj(
    {"message": Str(), "signal": Str(), "scale": Num(-1e6, 1e6, default=1.0), "offset": Num(-1e9, 1e9, default=0.0)},
    default=None,
)


def _signals_rule(s: dict[str, Any]) -> tuple[str, str] | None:
    for role in ("pump_speed_rpm", "pump_disp_cc", "temp_c", "motor_speed_rpm"):
        if s.get(role) is None:
            return role, "missing; every machine must map this role to a DBC message and signal"
    has_dp = s.get("dp_bar") is not None
    has_hl = s.get("high_pressure_bar") is not None and s.get("low_pressure_bar") is not None
    if not (has_dp or has_hl):
        return "dp_bar", "map either dp_bar, or both high_pressure_bar and low_pressure_bar"
    if has_dp and (s.get("high_pressure_bar") is not None or s.get("low_pressure_bar") is not None):
        return "dp_bar", "map dp_bar or high/low pressure, not both"
    return None


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
        "drive": Obj({"motor_disp_cc": Num(1, 2000, "cm3/rev")}),
        "signals": Obj({r: _SIGNAL for r in MAPPABLE}, rule=_signals_rule),
        "evaluation": Obj({"rate_hz": Num(0.5, 100, "Hz", default=10.0)}, default={}),
        "max_signal_age_s": Obj(
            {"default": Num(0.01, 60, "s", default=0.5), **{r: Num(0.01, 60, "s", default=None) for r in GATED}},
            default={},
        ),
        "gating": Obj(
            {
                "window_s": Num(0.1, 60, "s", default=1.0),
                "min_samples": Num(1, 10000, default=5, integer=True),
                "min_pump_speed_rpm": Num(0, 10000, "rpm", default=700.0),
                "min_pump_disp_cc": Num(0, 2000, "cm3/rev", default=20.0),
                "min_motor_speed_rpm": Num(0, 20000, "rpm", default=300.0),
                "max_std": Obj({r: Num(0, 1e4, default=None) for r in GATED}, default={}),
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
                "warning": _output("CM_WARNING", 1000),
            },
            default={},
        ),
        "state": Obj(
            {"directory": Str(default="/var/lib/cmcan"), "save_every_s": Num(1, 86400, "s", default=60.0)}, default={}
        ),
        "uplink": UPLINK,  # issue 15: validated by cmcan.uplink.config, disabled by default
    }
)


@dataclass(frozen=True)
class BusConfig:
    interface: str  # a python-can interface: socketcan, virtual, pcan, ...
    channel: str
    bitrate: int
    receive_buffer_bytes: int


@dataclass(frozen=True)
class DriveConfig:
    motor_disp_cc: float  # V_M at the motor's fixed displacement setting


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

    def items(self) -> list[tuple[str, OutputMessageConfig]]:
        return [("cm_ratio", self.cm_ratio), ("cm_speed", self.cm_speed), ("warning", self.warning)]


@dataclass(frozen=True)
class StateConfig:
    directory: Path
    save_every_s: float


@dataclass(frozen=True)
class Config:
    source: str  # the file it came from, for messages
    bus: BusConfig
    dbc_path: Path
    model_path: Path | None  # None: the model shipped with cmcan
    drive: DriveConfig
    signals: dict[str, SignalRef]  # role -> where it is on the bus
    evaluation: EvaluationConfig
    max_signal_age: SignalAges
    gating: GatingConfig
    filter: FilterConfig
    thresholds: Thresholds
    outputs: OutputsConfig
    state: StateConfig
    uplink: UplinkSettings  # the telematics uplink (disabled by default); its outbox in the state directory

    @property
    def motor_disp_cc(self) -> float:
        return self.drive.motor_disp_cc

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


def from_dict(data: Any, source: str, base_dir: Path) -> Config:
    """Validate a parsed YAML document and build the typed configuration (SchemaError names the field)."""
    raw = _CONFIG.check(data, source, "")
    g = raw["gating"]
    base = GateLimits()
    limits = GateLimits(
        window_s=g["window_s"],
        min_samples=g["min_samples"],
        min_pump_speed_rpm=g["min_pump_speed_rpm"],
        min_pump_disp_cc=g["min_pump_disp_cc"],
        min_motor_speed_rpm=g["min_motor_speed_rpm"],
        max_std={**base.max_std, **{k: v for k, v in g["max_std"].items() if v is not None}},
    )
    ages = raw["max_signal_age_s"]
    th = raw["thresholds"]
    out = raw["outputs"]
    return Config(
        source=source,
        bus=BusConfig(**raw["bus"]),
        dbc_path=_path(base_dir, raw["dbc"]),
        model_path=None if raw["model"] == "default" else _path(base_dir, raw["model"]),
        drive=DriveConfig(motor_disp_cc=float(raw["drive"]["motor_disp_cc"])),
        signals={r: SignalRef(**v) for r, v in raw["signals"].items() if v is not None},
        evaluation=EvaluationConfig(rate_hz=float(raw["evaluation"]["rate_hz"])),
        max_signal_age=SignalAges(ages["default"], {r: v for r, v in ages.items() if r != "default" and v is not None}),
        gating=GatingConfig(limits, g["envelope_margin_pct"]),
        filter=FilterConfig(**raw["filter"]),
        thresholds=Thresholds(
            th["low_pct"], th["high_pct"], th["hysteresis_pct"], th["debounce_s"], th["fault_after_s"]
        ),
        outputs=OutputsConfig(**{k: OutputMessageConfig(**v) for k, v in out.items()}),
        state=StateConfig(Path(raw["state"]["directory"]), float(raw["state"]["save_every_s"])),
        uplink=UplinkSettings.from_raw(raw["uplink"], raw["state"]["directory"], base_dir, source),
    )


def load(path: str | Path | None = None) -> Config:
    """The configuration at ``path`` (the shipped one by default); SchemaError names file and field."""
    p = Path(path) if path is not None else default_config_path()
    return from_dict(load_yaml(p), str(p), p.resolve().parent)


def with_overrides(
    cfg: Config, interface: str | None = None, channel: str | None = None, state_dir: str | None = None
) -> Config:
    """The command line's overrides of bus and state directory."""
    bus = replace(cfg.bus, **{k: v for k, v in (("interface", interface), ("channel", channel)) if v})
    if not state_dir:
        return replace(cfg, bus=bus)
    state = replace(cfg.state, directory=Path(state_dir))
    uplink = cfg.uplink
    if uplink.outbox.path.parent == cfg.state.directory:  # the outbox lives in the state directory
        outbox = replace(uplink.outbox, path=Path(state_dir) / uplink.outbox.path.name)
        uplink = replace(uplink, outbox=outbox)
    return replace(cfg, bus=bus, state=state, uplink=uplink)


__all__ = ["Config", "SchemaError", "SignalRef", "default_config_path", "from_dict", "load", "with_overrides"]
