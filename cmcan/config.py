"""The daemon's configuration: YAML validated field by field, paths resolved, DBC names checked."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cantools.database.can import Database

from cmcan.dbc import DbcError, load_dbc
from cmcan.monitor.gating import GateLimits
from cmcan.schema import Num, Obj, SchemaError, Str, load_yaml
from cmcan.signals import SignalRef
from cmcan.uplink.config import UPLINK  # the uplink: section (issue 15)

ROLES = (
    "pump_speed_rpm",
    "pump_disp_cc",
    "high_pressure_bar",
    "low_pressure_bar",
    "dp_bar",
    "temp_c",
    "motor_speed_rpm",
    "motor_direction",
)
_STD_ROLES = ("pump_speed_rpm", "pump_disp_cc", "dp_bar", "temp_c", "motor_speed_rpm")

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
        "signals": Obj({r: _SIGNAL for r in ROLES}, rule=_signals_rule),
        "evaluation": Obj({"rate_hz": Num(0.5, 100, "Hz", default=10.0)}, default={}),
        "max_signal_age_s": Obj({"default": Num(0.01, 60, "s", default=0.5)}, default={}, extra=Num(0.01, 60, "s")),
        "gating": Obj(
            {
                "window_s": Num(0.1, 60, "s", default=1.0),
                "min_samples": Num(1, 10000, default=5, integer=True),
                "min_pump_speed_rpm": Num(0, 10000, "rpm", default=700.0),
                "min_pump_disp_cc": Num(0, 2000, "cm3/rev", default=20.0),
                "min_motor_speed_rpm": Num(0, 20000, "rpm", default=300.0),
                "max_std": Obj({r: Num(0, 1e4, default=None) for r in _STD_ROLES}, default={}),
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
class Config:
    source: str
    raw: dict[str, Any]
    dbc_path: Path
    model_path: Path
    signals: dict[str, SignalRef]

    @property
    def motor_disp_cc(self) -> float:
        return float(self.raw["drive"]["motor_disp_cc"])

    @property
    def gate_limits(self) -> GateLimits:
        g = self.raw["gating"]
        base = GateLimits()
        max_std = {**base.max_std, **{k: v for k, v in g["max_std"].items() if v is not None}}
        return GateLimits(
            window_s=g["window_s"],
            min_samples=g["min_samples"],
            min_pump_speed_rpm=g["min_pump_speed_rpm"],
            min_pump_disp_cc=g["min_pump_disp_cc"],
            min_motor_speed_rpm=g["min_motor_speed_rpm"],
            max_std=max_std,
        )

    def max_age_s(self, role: str) -> float:
        ages = self.raw["max_signal_age_s"]
        return float(ages.get(role, ages["default"]))

    @property
    def mapping(self) -> dict[str, tuple[str, str]]:
        return {r: (s.message, s.signal) for r, s in self.signals.items()}

    def dbc(self) -> Database:
        return load_dbc(self.dbc_path)


def default_config_path() -> Path:
    here = Path(__file__).resolve().parent
    for candidate in (here / "_data" / "config" / "cmcan.yaml", here.parent / "config" / "cmcan.yaml"):
        if candidate.exists():
            return candidate
    raise FileNotFoundError("the shipped config/cmcan.yaml was not found next to the cmcan package")


def from_dict(data: Any, source: str, base_dir: Path) -> Config:
    raw = _CONFIG.check(data, source, "")
    dbc_path = (base_dir / raw["dbc"]).resolve() if not Path(raw["dbc"]).is_absolute() else Path(raw["dbc"])
    if raw["model"] == "default":
        from cmcan.model.runtime import default_model_path

        model_path = default_model_path()
    else:
        model_path = Path(raw["model"]) if Path(raw["model"]).is_absolute() else (base_dir / raw["model"]).resolve()
    signals = {r: SignalRef(**v) for r, v in raw["signals"].items() if v is not None}
    return Config(source, raw, dbc_path, model_path, signals)


def load(path: str | Path | None = None) -> Config:
    p = Path(path) if path is not None else default_config_path()
    return from_dict(load_yaml(p), str(p), p.resolve().parent)


def check_against_dbc(cfg: Config, db: Database) -> None:
    """Every mapped message and signal exists in the DBC; outputs are there and are not inputs."""
    names = {m.name: m for m in db.messages}
    for role, ref in cfg.signals.items():
        msg = names.get(ref.message)
        if msg is None:
            raise SchemaError(
                cfg.source,
                f"signals.{role}.message",
                f"no message {ref.message!r} in {cfg.dbc_path}; it has {', '.join(sorted(names))}",
            )
        if ref.signal not in {s.name for s in msg.signals}:
            raise SchemaError(
                cfg.source,
                f"signals.{role}.signal",
                f"message {ref.message} in {cfg.dbc_path} has no signal {ref.signal!r}; "
                f"it has {', '.join(s.name for s in msg.signals)}",
            )
    inputs = {ref.message for ref in cfg.signals.values()}
    for key, out in cfg.raw["outputs"].items():
        if out["message"] not in names:
            raise SchemaError(cfg.source, f"outputs.{key}.message", f"no message {out['message']!r} in {cfg.dbc_path}")
        if out["message"] in inputs:
            raise SchemaError(cfg.source, f"outputs.{key}.message", f"{out['message']} is also an input message")


__all__ = ["Config", "DbcError", "SignalRef", "check_against_dbc", "default_config_path", "load"]
