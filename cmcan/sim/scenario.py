"""Scenario files: the YAML that describes one simulated run, validated field by field."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from cmcan.oil import Oil, oil_from_grade
from cmcan.schema import Bool, Num, Obj, OneOf, SchemaError, Seq, Str, load_yaml
from cmcan.sim.physics import DriveParams, ExtraLosses, UnitLosses
from cmcan.sim.sensors import SensorError

INF = math.inf


def _term(coeff_key: str, hi: float) -> Obj:
    return Obj({"enabled": Bool(default=True), coeff_key: Num(0.0, hi, default=None)}, default={})


def _unit_losses() -> Obj:
    return Obj(
        {
            "laminar": _term("cs", 1e-6),
            "turbulent": _term("ct", 1e-2),
            "compressibility": _term("factor", 10.0),
        },
        default={},
    )


_DRIVE = Obj(
    {
        "pump_disp_max_cc": Num(1, 1000, "cm3/rev", default=None),
        "motor_disp_max_cc": Num(1, 1000, "cm3/rev", default=None),
        "motor_disp_setting": Num(0.05, 1.0, "(fraction of max)", default=None),
        "charge_pressure_bar": Num(0, 60, "bar", default=None),
        "relief_dp_bar": Num(50, 650, "bar", default=None),
        "relief_gain_lpm_per_bar": Num(0.001, 1000, "l/min/bar", default=None),
        "bulk_modulus_bar": Num(1000, 30000, "bar", default=None),
        "line_volume_l": Num(0.01, 100, "l", default=None),
        "motor_inertia_kgm2": Num(0.001, 1000, "kg m2", default=None),
        "motor_friction_nm": Num(0, 500, "Nm", default=None),
        "motor_viscous_nm_per_krpm": Num(0, 500, "Nm/krpm", default=None),
        "heat_capacity_kj_per_k": Num(1, 10000, "kJ/K", default=None),
        "cooler_w_per_k": Num(1, 100000, "W/K", default=None),
        "hm_loss_fraction": Num(0, 0.5, default=None),
    },
    default={},
)

# Loss terms beyond the units' own laws, in l/min at 300 bar and 50 C (the gap library's physical effects).
_EXTRA_LOSSES = Obj(
    {
        "laminar_lpm": Num(0, 1000, "l/min at 300 bar, 50 C", default=0.0),
        "pressure_lpm": Num(0, 1000, "l/min at 300 bar", default=0.0),
        "turbulent_lpm": Num(0, 1000, "l/min at 300 bar", default=0.0),
        "compress_factor": Num(0, 10, "(share of n V dp / K)", default=0.0),
        "filling_lpm": Num(0, 1000, "l/min at 3000 rpm", default=0.0),
    },
    default={},
)


def _fluid_rule(f: dict[str, Any]) -> tuple[str, str] | None:
    if f["grade"] is not None:
        for key in ("nu40_cst", "nu100_cst"):
            if f[key] is not None:
                return key, "give either grade or nu40_cst and nu100_cst, not both"
        try:
            oil_from_grade(f["grade"])
        except ValueError as exc:
            return "grade", str(exc)
        return None
    if (f["nu40_cst"] is None) != (f["nu100_cst"] is None):
        return ("nu100_cst" if f["nu100_cst"] is None else "nu40_cst"), "nu40_cst and nu100_cst go together"
    if f["nu40_cst"] is not None and f["nu100_cst"] >= f["nu40_cst"]:
        return "nu100_cst", f"must be lower than nu40_cst ({f['nu40_cst']} cSt), got {f['nu100_cst']}"
    return None


# The hydraulic oil: an ISO grade (mineral HLP oil) or its two reference viscosities; default VG 46.
_FLUID = Obj(
    {
        "grade": Str(default=None),
        "nu40_cst": Num(2, 1000, "cSt at 40 C", default=None),
        "nu100_cst": Num(1, 100, "cSt at 100 C", default=None),
        "density15_kg_m3": Num(700, 1100, "kg/m3 at 15 C", default=None),
    },
    default={},
    rule=_fluid_rule,
)

_SENSOR_ERROR = Obj(
    {
        "offset": Num(-1e4, 1e4, "(the channel's unit)", default=0.0),
        "gain_pct": Num(-50, 50, "%", default=0.0),
        "lag_s": Num(0, 10, "s", default=0.0),
    },
    default={},
)
SENSOR_CHANNELS = (
    "pump_speed_rpm",
    "pump_disp_cc",
    "high_pressure_bar",
    "low_pressure_bar",
    "temp_c",
    "motor_speed_rpm",
)

_PHASE_TABLE_POINT = Obj(
    {
        "t_s": Num(0, INF, "s"),
        "pump_speed_rpm": Num(0, 3600, "rpm"),
        "pump_disp_pct": Num(0, 100, "%"),
        "dp_bar": Num(0, 600, "bar"),
    }
)


def _table_rule(d: dict[str, Any]) -> tuple[str, str] | None:
    ts = [p["t_s"] for p in d["points"]]
    if any(b <= a for a, b in itertools.pairwise(ts)):
        return "points", "t_s must increase strictly from point to point"
    return None


def _sweep_rule(d: dict[str, Any]) -> tuple[str, str] | None:
    for key in ("pump_speed_rpm", "pump_disp_pct", "dp_bar", "hold_s"):
        lo, hi = d[key]
        if hi < lo:
            return key, f"expected [low, high] with low <= high, got {d[key]}"
    return None


_MIXED = Obj(
    {
        "ramp_s": Num(0.05, 10, "s", default=0.8),
        "speed_scale": Num(0.5, 1.5, default=1.0),
        "load_scale": Num(0.2, 1.2, default=1.0),
    }
)
_PLAIN_DUTIES = OneOf(
    "kind",
    {
        "constant": Obj(
            {
                "pump_speed_rpm": Num(0, 3600, "rpm"),
                "pump_disp_pct": Num(0, 100, "%"),
                "dp_bar": Num(0, 600, "bar"),
            }
        ),
        "wheel_loader": _MIXED,
        "excavator": _MIXED,
        "sweep": Obj(
            {
                "pump_speed_rpm": Seq(Num(0, 3600, "rpm"), min_len=2, max_len=2),
                "pump_disp_pct": Seq(Num(0, 100, "%"), min_len=2, max_len=2),
                "dp_bar": Seq(Num(0, 600, "bar"), min_len=2, max_len=2),
                "hold_s": Seq(Num(0.5, 3600, "s"), min_len=2, max_len=2, default=[4.0, 12.0]),
                "edge_share": Num(0, 1, default=0.0),
                "ramp_s": Num(0.05, 10, "s", default=0.8),
            },
            rule=_sweep_rule,
        ),
        "table": Obj(
            {
                "points": Seq(_PHASE_TABLE_POINT, min_len=1),
                "interpolation": Str(default="linear", choices=("linear", "step")),
                "repeat": Bool(default=False),
            },
            rule=_table_rule,
        ),
    },
)
# A machine moved to other work in mid-life (light to heavy, one site to another): one duty until
# ``at_h`` operating hours, another after.
_DUTY = OneOf(
    "kind",
    {
        **_PLAIN_DUTIES.variants,
        "change": Obj({"at_h": Num(0, INF, "h"), "before": _PLAIN_DUTIES, "after": _PLAIN_DUTIES}),
    },
)

_OIL = OneOf(
    "model",
    {
        "heat_balance": Obj(
            {
                "ambient_c": Num(-40, 60, "C", default=25.0),
                "ambient_swing_c": Num(0, 30, "C", default=0.0),
                "ambient_period_h": Num(0.1, 1000, "h", default=24.0),
                "initial_c": Num(-30, 120, "C", default=None),
            }
        ),
        "prescribed": Obj(
            {
                "temp_c": Num(-30, 120, "C"),
                "swing_c": Num(0, 50, "C", default=0.0),
                "period_h": Num(0.01, 1000, "h", default=24.0),
            }
        ),
        "profile": Obj(
            {"points": Seq(Seq(Num(-1e9, 1e9), min_len=2, max_len=2), min_len=2), "repeat": Bool(default=False)}
        ),
    },
)

_REF = {"ref_dp_bar": Num(10, 600, "bar", default=480.0), "ref_temp_c": Num(0, 120, "C", default=60.0)}
_COMPONENT = Str(choices=("pump", "motor"))


def _wear_rule(e: dict[str, Any]) -> tuple[str, str] | None:
    if e["fail_h"] <= e["start_h"]:
        return "fail_h", f"must be later than start_h ({e['start_h']} h), got {e['fail_h']}"
    c = e["rate_change_h"]
    if c is not None and not e["start_h"] < c < e["fail_h"]:
        return "rate_change_h", f"must lie between start_h ({e['start_h']} h) and fail_h ({e['fail_h']} h), got {c}"
    return None


def _mis_rule(e: dict[str, Any]) -> tuple[str, str] | None:
    if e["mode"] == "drift" and (e["end_h"] is None or e["end_h"] <= e["start_h"]):
        return "end_h", f"a drift needs end_h later than start_h ({e['start_h']} h)"
    if e["fail_h"] is not None and e["fail_h"] < e["start_h"]:
        return "fail_h", f"must not be earlier than start_h ({e['start_h']} h)"
    return None


_EVENT = OneOf(
    "type",
    {
        "leakage": Obj(
            {
                "component": Str(default="loop", choices=("loop", "pump", "motor")),
                "start_h": Num(0, INF, "h"),
                "extra_lpm": Num(0, 200, "l/min"),
                "ref_dp_bar": Num(10, 600, "bar", default=480.0),
                "ramp_h": Num(0, INF, "h", default=0.0),
            }
        ),
        "wear": Obj(
            {
                "component": _COMPONENT,
                "start_h": Num(0, INF, "h"),
                "fail_h": Num(0, INF, "h"),
                "fail_extra_lpm": Num(0.1, 200, "l/min", default=40.0),
                "shape": Num(1, 8, default=3.0),
                # laminar: a worn gap, Q ~ dp / viscosity; orifice: a crack or a torn seal, Q ~ sqrt(dp)
                "law": Str(default="laminar", choices=("laminar", "orifice")),
                # power: x = F s^k; steps: the same curve reached in ``steps`` jumps (damage in stages)
                "growth": Str(default="power", choices=("power", "steps")),
                "steps": Num(2, 20, integer=True, default=4),
                # the wear's pace times ``rate_factor`` from ``rate_change_h`` on (heavier or lighter
                # work); fail_h stays the hour of failure
                "rate_change_h": Num(0, INF, "h", default=None),
                "rate_factor": Num(0.1, 10, default=1.0),
                **_REF,
            },
            rule=_wear_rule,
        ),
        "misposition": Obj(
            {
                "mode": Str(choices=("step", "drift")),
                "start_h": Num(0, INF, "h"),
                "end_h": Num(0, INF, "h", default=None),
                "pct": Num(-50, 50, "% of motor displacement"),
                "fail_h": Num(0, INF, "h", default=None),
            },
            rule=_mis_rule,
        ),
        "failure": Obj(
            {
                "component": _COMPONENT,
                "at_h": Num(0, INF, "h"),
                "extra_lpm": Num(1, 500, "l/min", default=120.0),
                **_REF,
            }
        ),
        "replace": Obj({"component": _COMPONENT, "at_h": Num(0, INF, "h")}),
    },
)

_SENSORS = Obj(
    {
        "noise": Obj(
            {
                "pump_speed_rpm": Num(0, 100, "rpm", default=1.5),
                "pump_disp_cc": Num(0, 10, "cm3/rev", default=0.15),
                "high_pressure_bar": Num(0, 50, "bar", default=1.5),
                "low_pressure_bar": Num(0, 50, "bar", default=0.3),
                "temp_c": Num(0, 10, "C", default=0.1),
                "motor_speed_rpm": Num(0, 100, "rpm", default=3.0),
            },
            default={},
        ),
        "jitter_ms": Num(0, 5, "ms", default=0.0),
        # Miscalibrated or slow transducers: reading = (1 + gain_pct/100) * lagged(true) + offset.
        "errors": Obj(dict.fromkeys(SENSOR_CHANNELS, _SENSOR_ERROR), default={}),
    },
    default={},
)


def _sampling_rule(s: dict[str, Any]) -> tuple[str, str] | None:
    if s["mode"] == "bursts" and s["burst_s"] > s["every_min"] * 60:
        return "burst_s", f"must not exceed the burst interval ({s['every_min']} min)"
    return None


_LOSSES = Obj({"pump": _unit_losses(), "motor": _unit_losses(), "extra": _EXTRA_LOSSES}, default={})
# A drive file: the machine alone (its sizes, loss terms and oil), as the gap diagnosis takes it.
_DRIVE_FILE = Obj({"drive": _DRIVE, "losses": _LOSSES, "fluid": _FLUID})

_SCENARIO = Obj(
    {
        "name": Str(),
        "description": Str(default=""),
        "seed": Num(0, 2**32 - 1, integer=True),
        "duration_h": Num(1e-4, 20000, "h"),
        "sample_rate_hz": Num(10, 1000, "Hz", default=100.0),
        "start_epoch_s": Num(0, 4e9, "s", default=1767225600.0),
        "sampling": Obj(
            {
                "mode": Str(default="continuous", choices=("continuous", "bursts")),
                "burst_s": Num(0.5, 3600, "s", default=10.0),
                "every_min": Num(0.1, 1440, "min", default=10.0),
            },
            default={},
            rule=_sampling_rule,
        ),
        "drive": _DRIVE,
        "losses": _LOSSES,
        "fluid": _FLUID,
        "oil": _OIL,
        "duty": _DUTY,
        "events": Seq(_EVENT, default=[]),
        "sensors": _SENSORS,
    }
)


@dataclass(frozen=True)
class Sampling:
    """Continuous, or bursts of ``burst_s`` seconds every ``every_min`` minutes of operation."""

    mode: str
    burst_s: float
    every_min: float

    @property
    def bursts(self) -> bool:
        return self.mode == "bursts"


@dataclass(frozen=True)
class Sensors:
    """Each channel's noise (its section as validated), timestamp jitter, and the errors of
    miscalibrated or slow transducers (only those that are not zero)."""

    noise: Mapping[str, Any]
    jitter_ms: float
    errors: Mapping[str, SensorError]


@dataclass(frozen=True)
class Scenario:
    """A validated scenario, section by section. ``duty``, ``oil`` and ``events`` are the validated
    sections the duty cycle, the oil's temperature and the degradation models read
    (:mod:`cmcan.sim.duty`, :func:`cmcan.sim.run.oil_temperatures`, :mod:`cmcan.sim.degradation`)."""

    name: str
    source: str
    seed: int
    duration_h: float
    sample_rate_hz: float
    start_epoch_s: float
    sampling: Sampling
    duty: Mapping[str, Any]
    oil: Mapping[str, Any]
    events: tuple[Mapping[str, Any], ...]
    sensors: Sensors
    params: DriveParams
    document: Mapping[str, Any]  # the whole validated document: overrides start from it

    def with_overrides(self, **top: Any) -> Scenario:
        """A copy with top-level fields replaced (e.g. ``seed=``, ``duration_h=``), validated again.

        Shortening a run drops the events that would start after its new end."""
        doc = {**self.document, **top}
        if "duration_h" in top and "events" not in top:
            doc["events"] = [e for e in self.events if e.get("start_h", e.get("at_h", 0.0)) <= top["duration_h"]]
        return from_dict(doc, source=self.source)


def _params_from(raw: dict[str, Any]) -> DriveParams:
    p = DriveParams()
    overrides = {k: v for k, v in raw["drive"].items() if v is not None}
    p = replace(p, **overrides)
    units = {}
    for unit in ("pump", "motor"):
        base: UnitLosses = getattr(p, unit)
        spec = raw["losses"][unit]
        units[unit] = UnitLosses(
            laminar_cs=_coeff(spec["laminar"], "cs", base.laminar_cs),
            turbulent_ct=_coeff(spec["turbulent"], "ct", base.turbulent_ct),
            compress_factor=_coeff(spec["compressibility"], "factor", base.compress_factor),
        )
    return replace(p, **units, extra=ExtraLosses(**raw["losses"]["extra"]), oil=fluid_from(raw["fluid"]))


def fluid_from(f: dict[str, Any]) -> Oil:
    """The oil a validated ``fluid`` section names (VG 46 when it names none)."""
    oil = oil_from_grade(f["grade"]) if f["grade"] is not None else Oil()
    if f["nu40_cst"] is not None:
        oil = replace(oil, nu40_cst=f["nu40_cst"], nu100_cst=f["nu100_cst"])
    if f["density15_kg_m3"] is not None:
        oil = replace(oil, density15_kg_m3=f["density15_kg_m3"])
    return oil


def _sensor_errors(raw: dict[str, Any]) -> dict[str, SensorError]:
    """The sensor errors a validated scenario states, by channel (only those that are not zero)."""
    errs = {k: SensorError(**v) for k, v in raw["sensors"]["errors"].items()}
    return {k: e for k, e in errs.items() if e.any}


def _coeff(term: dict[str, Any], key: str, default: float) -> float:
    if not term["enabled"]:
        return 0.0
    return default if term[key] is None else float(term[key])


def _check_events(raw: dict[str, Any], source: str) -> None:
    for i, ev in enumerate(raw["events"]):
        t0 = ev.get("start_h", ev.get("at_h"))
        if t0 is not None and t0 > raw["duration_h"]:
            raise SchemaError(
                source, f"events[{i}]", f"starts at {t0} h, after the end of the run ({raw['duration_h']} h)"
            )


def from_dict(data: Any, source: str = "<scenario>") -> Scenario:
    raw = _SCENARIO.check(data, source, "")
    _check_events(raw, source)
    smp, sen = raw["sampling"], raw["sensors"]
    return Scenario(
        name=raw["name"],
        source=source,
        seed=int(raw["seed"]),
        duration_h=float(raw["duration_h"]),
        sample_rate_hz=float(raw["sample_rate_hz"]),
        start_epoch_s=float(raw["start_epoch_s"]),
        sampling=Sampling(smp["mode"], float(smp["burst_s"]), float(smp["every_min"])),
        duty=raw["duty"],
        oil=raw["oil"],
        events=tuple(raw["events"]),
        sensors=Sensors(sen["noise"], float(sen["jitter_ms"]), _sensor_errors(raw)),
        params=_params_from(raw),
        document=raw,
    )


def load(path: str | Path) -> Scenario:
    return from_dict(load_yaml(path), source=str(path))


def shipped_dir() -> Path:
    return Path(__file__).resolve().parent / "scenarios"


def shipped(name: str) -> Path:
    """Path of a scenario shipped with cmcan (``name`` with or without ``.yaml``)."""
    stem = name[:-5] if name.endswith(".yaml") else name
    path = shipped_dir() / f"{stem}.yaml"
    if not path.exists():
        names = ", ".join(sorted(p.stem for p in shipped_dir().glob("*.yaml")))
        raise FileNotFoundError(f"no shipped scenario {name!r}; shipped: {names}")
    return path


def resolve(name_or_path: str | Path) -> Path:
    """A scenario given as a path, or by the name of a shipped one."""
    p = Path(name_or_path)
    if p.exists() or (p.suffix in (".yaml", ".yml") and p.parent != Path(".")):
        return p
    try:
        return shipped(str(name_or_path))
    except FileNotFoundError:
        return p


def drive_from_dict(data: Any, source: str = "<drive>") -> DriveParams:
    """A machine from the ``drive``, ``losses`` and ``fluid`` sections (each optional; the rest is the
    reference drive)."""
    if data is None:
        data = {}
    return _params_from(_DRIVE_FILE.check(data, source, ""))


def load_drive(path: str | Path) -> DriveParams:
    return drive_from_dict(load_yaml(path), source=str(path))


def drive_differences(
    p: DriveParams, motor_disp_cc: float | None, pump_disp_max_cc: float, oil: Oil, rtol: float = 1e-3
) -> list[str]:
    """What a scenario's simulated drive ``p`` has other than a machine's configuration (its V_M,
    largest pump displacement and oil): frames written through that configuration would then be
    another machine's, and its model would read them as worn or mispositioned. Empty when they agree."""
    out = []

    def differs(a: float, b: float) -> bool:
        return not math.isclose(a, b, rel_tol=rtol)

    if motor_disp_cc is not None and differs(p.motor_disp_cc, motor_disp_cc):
        out.append(
            f"motor displacement V_M {p.motor_disp_cc:g} cm3/rev (drive.motor_disp_max_cc x motor_disp_setting) "
            f"against the configuration's drive.motor_disp_cc {motor_disp_cc:g}"
        )
    if differs(p.pump_disp_max_cc, pump_disp_max_cc):
        out.append(
            f"pump displacement {p.pump_disp_max_cc:g} cm3/rev (drive.pump_disp_max_cc) against the "
            f"configuration's drive.pump_disp_max_cc {pump_disp_max_cc:g}"
        )
    if differs(p.oil.nu40_cst, oil.nu40_cst) or differs(p.oil.nu100_cst, oil.nu100_cst):
        out.append(
            f"oil of {p.oil.nu40_cst:g}/{p.oil.nu100_cst:g} cSt at 40/100 C (fluid) against the configuration's "
            f"oil of {oil.nu40_cst:g}/{oil.nu100_cst:g} cSt"
        )
    return out
