"""A simulated fleet: machines of a few types (drive sizes), each with its own duty, oil and fate.

Pure planning: from (machines, hours, seed) to one scenario per machine (validated by
:mod:`cmcan.sim.scenario`), the training scenario of each machine type, and the ground truth. The
files (logs, configurations, models, the sidecar) are written by :mod:`cmcan.fleet.simfleet`.

The fleet is a time-lapse like the run-to-failure scenario: each machine is sampled in bursts
(``burst_s`` every ``every_min`` minutes of operation), so hundreds of operating hours fit in a few
hundred thousand frames; a burst's timestamps carry its true operating time.

Unit-to-unit variation (issue 29), off by default: with a :class:`UnitSpread` every machine gets its
own displacements, healthy leakage and sensor errors within the spread's tolerances, drawn from a
stream of its own (``[seed, 29, ...]``), so switching it on changes nothing else the seed draws. Some
healthy machines can arrive already leaking (``arriving_leaks``). The configuration and model of a
type keep the nominal drive: the monitor does not know a machine's own draws, the truth sidecar does.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numpy as np

from cmcan.sim import scenario as scn
from cmcan.sim.physics import DriveParams
from cmcan.sim.sensors import SensorError


@dataclass(frozen=True)
class MachineType:
    """A drive size: pump and motor displacements, and what a machine of this size runs at."""

    name: str
    pump_disp_max_cc: float
    motor_disp_max_cc: float
    motor_disp_setting: float
    motor_inertia_kgm2: float
    heat_capacity_kj_per_k: float

    @property
    def motor_disp_cc(self) -> float:
        return self.motor_disp_max_cc * self.motor_disp_setting

    def drive(self) -> dict[str, float]:
        return {
            "pump_disp_max_cc": self.pump_disp_max_cc,
            "motor_disp_max_cc": self.motor_disp_max_cc,
            "motor_disp_setting": self.motor_disp_setting,
            "motor_inertia_kgm2": self.motor_inertia_kgm2,
            "heat_capacity_kj_per_k": self.heat_capacity_kj_per_k,
        }

    def rated_flow_lpm(self, pump_speed_rpm: float = 2000.0) -> float:
        return self.pump_disp_max_cc * pump_speed_rpm / 1000.0


# Three sizes of mobile drive; every type gets its own configuration (V_M) and its own model.
TYPES: dict[str, MachineType] = {
    t.name: t
    for t in (
        MachineType("compact", 45.0, 80.0, 0.40, 0.5, 120.0),
        MachineType("mid", 78.0, 110.0, 0.40, 1.0, 200.0),
        MachineType("large", 130.0, 160.0, 0.50, 2.0, 350.0),
    )
}
DUTIES = ("wheel_loader", "excavator")
# Wear leaks this share of the type's rated flow (at 2000 rpm) at its reference pressure when the unit
# loses function, as the shipped run-to-failure scenario does (40 l/min on the 78 cm3 pump).
FAIL_SHARE_OF_RATED = 0.25
TRAINING_HOURS = 0.6
TRAINING_T_TRN_H = 0.4

# Unit-to-unit variation draws from its own stream ([seed, SPREAD_STREAM, k]), never from the plan's.
SPREAD_STREAM = 29
# A lognormal leakage factor is cut at this many sigmas, so every draw lies within a stated bound.
LEAK_CLIP_SIGMAS = 3.0
# Arriving leaks are stated as an orifice's flow at this delta pressure (the leakage event's default).
ARRIVING_LEAK_REF_DP_BAR = 480.0
# Shares of a channel's accuracy given to its offset and to its gain: half each keeps the worst case
# (offset and gain of the same sign at full scale) within the datasheet's figure.
_OFFSET_SHARE = 0.5
_GAIN_SHARE = 0.5


@dataclass(frozen=True)
class UnitSpread:
    """Tolerances of one machine against its type: each a +- bound (a band, drawn uniformly inside it:
    a datasheet states the band, not where in it the units lie), the leakage factor lognormal.

    Defaults are typical datasheet figures for mobile axial piston units and their sensors:

    - displacement +-1 %: the geometric displacement of series units (piston bores, pitch circle,
      swash angle stops) scatters by about a percent around the catalogue's figure;
    - healthy leakage factor, lognormal sigma 0.2 (cut at 3 sigma: 0.55 .. 1.82): gap flow goes with
      the gap height cubed, so +-6 % on the few-micrometre gaps gives +-20 %; the volumetric efficiency
      of new units of one series scatters by a few tenths of a percent, tens of percent of their
      leakage (about 3 % of rated flow at 480 bar and 60 C for these drives). Pump and motor draw
      their own factor (separate units); a unit's laminar and turbulent terms share it (same gaps);
    - speed sensors +-0.2 % of reading (pulse pick-ups: the count is exact, the gate time and
      the controller's filter are not), no offset (standstill reads 0);
    - swash-plate angle sensor (pump displacement) +-1 % of full scale (Hall-effect angle sensors);
    - pressure transducers +-0.5 % of full scale (thin-film mobile transducers, 600 bar on both
      ports of a closed circuit: either side can be the high one);
    - oil temperature +-1 K (Pt1000 class B is +-0.6 K at 60 C, with the transmitter about 1 K).

    A channel's accuracy is split between its offset (half the band at full scale) and its gain (the
    other half), so offset and gain together stay within it. The figures are parameters: nothing
    depends on the defaults, and :meth:`scaled` widens or narrows them all at once.
    """

    pump_disp_pct: float = 1.0
    motor_disp_pct: float = 1.0
    leak_sigma: float = 0.2
    speed_gain_pct: float = 0.2
    disp_sensor_pct_fs: float = 1.0
    pressure_pct_fs: float = 0.5
    pressure_fs_bar: float = 600.0
    temp_offset_c: float = 1.0

    def scaled(self, k: float) -> UnitSpread:
        """Every tolerance times ``k`` (the transducers' full scale stays)."""
        return replace(self, **{f.name: getattr(self, f.name) * k for f in fields(self) if f.name != "pressure_fs_bar"})

    def check(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"unit spread: {f.name} must be a number >= 0, got {v!r}")
        for key in ("pump_disp_pct", "motor_disp_pct", "speed_gain_pct", "disp_sensor_pct_fs", "pressure_pct_fs"):
            if getattr(self, key) > 10.0:
                raise ValueError(f"unit spread: {key} must be at most 10 %, got {getattr(self, key)}")
        if self.leak_sigma > 1.0:
            raise ValueError(f"unit spread: leak_sigma must be at most 1, got {self.leak_sigma}")
        if not 10.0 <= self.pressure_fs_bar <= 1000.0:
            raise ValueError(f"unit spread: pressure_fs_bar must be between 10 and 1000, got {self.pressure_fs_bar}")
        if self.temp_offset_c > 10.0:
            raise ValueError(f"unit spread: temp_offset_c must be at most 10 C, got {self.temp_offset_c}")

    @property
    def leak_factor_bounds(self) -> tuple[float, float]:
        return math.exp(-LEAK_CLIP_SIGMAS * self.leak_sigma), math.exp(LEAK_CLIP_SIGMAS * self.leak_sigma)

    def sensor_bounds(self, t: MachineType) -> dict[str, tuple[float, float]]:
        """Each channel's (largest offset in the channel's unit, largest gain error in %)."""

        def split(pct_fs: float, fs: float) -> tuple[float, float]:
            return _OFFSET_SHARE * pct_fs / 100.0 * fs, _GAIN_SHARE * pct_fs

        return {
            "pump_speed_rpm": (0.0, self.speed_gain_pct),
            "pump_disp_cc": split(self.disp_sensor_pct_fs, t.pump_disp_max_cc),
            "high_pressure_bar": split(self.pressure_pct_fs, self.pressure_fs_bar),
            "low_pressure_bar": split(self.pressure_pct_fs, self.pressure_fs_bar),
            "temp_c": (self.temp_offset_c, 0.0),
            "motor_speed_rpm": (0.0, self.speed_gain_pct),
        }


@dataclass(frozen=True)
class Unit:
    """One machine's own draws: its true largest displacements, its healthy leakage as factors on the
    type's coefficients, its sensors' own offset and gain errors, and a leak it arrives with."""

    pump_disp_max_cc: float
    motor_disp_max_cc: float
    pump_leak_factor: float = 1.0
    motor_leak_factor: float = 1.0
    sensors: dict[str, SensorError] = field(default_factory=dict)
    arriving_leak_lpm: float = 0.0


def nominal_unit(t: MachineType) -> Unit:
    """A machine exactly as its type."""
    return Unit(t.pump_disp_max_cc, t.motor_disp_max_cc, sensors={k: SensorError() for k in scn.SENSOR_CHANNELS})


def _signed(x: float, bound: float, digits: int) -> float:
    return round(bound * x, digits) + 0.0  # + 0.0: no -0.0 in the sidecar


def draw_unit(t: MachineType, spread: UnitSpread, rng: np.random.Generator) -> Unit:
    """A machine of type ``t`` within ``spread``. Always the same number of draws, whatever the
    tolerances: a scaled spread moves the same machines the same way, only farther."""
    e_disp = rng.uniform(-1.0, 1.0, 2)
    z_leak = np.clip(rng.standard_normal(2), -LEAK_CLIP_SIGMAS, LEAK_CLIP_SIGMAS)
    u_sensor = rng.uniform(-1.0, 1.0, (len(scn.SENSOR_CHANNELS), 2))
    bounds = spread.sensor_bounds(t)
    sensors = {
        ch: SensorError(offset=_signed(u[0], bounds[ch][0], 4), gain_pct=_signed(u[1], bounds[ch][1], 4))
        for ch, u in zip(scn.SENSOR_CHANNELS, u_sensor.tolist(), strict=True)
    }
    return Unit(
        pump_disp_max_cc=round(t.pump_disp_max_cc * (1.0 + spread.pump_disp_pct / 100.0 * e_disp[0]), 4),
        motor_disp_max_cc=round(t.motor_disp_max_cc * (1.0 + spread.motor_disp_pct / 100.0 * e_disp[1]), 4),
        pump_leak_factor=round(math.exp(spread.leak_sigma * z_leak[0]), 4),
        motor_leak_factor=round(math.exp(spread.leak_sigma * z_leak[1]), 4),
        sensors=sensors,
    )


def apply_unit(raw: dict[str, Any], t: MachineType, unit: Unit) -> dict[str, Any]:
    """The scenario document ``raw`` of a type-``t`` machine made this unit (a new document)."""
    ref = DriveParams()
    drive = {**raw["drive"], "pump_disp_max_cc": unit.pump_disp_max_cc, "motor_disp_max_cc": unit.motor_disp_max_cc}
    losses = {
        name: {"laminar": {"cs": base.laminar_cs * k}, "turbulent": {"ct": base.turbulent_ct * k}}
        for name, base, k in (("pump", ref.pump, unit.pump_leak_factor), ("motor", ref.motor, unit.motor_leak_factor))
    }
    errors = {}
    for ch, e in unit.sensors.items():
        gain_pct = e.gain_pct
        if ch == "pump_disp_cc":
            # The angle sensor reads the swash angle, the controller scales it by the catalogue's
            # displacement: the pump's own deviation never reaches the bus.
            gain_pct = ((1.0 + gain_pct / 100.0) * t.pump_disp_max_cc / unit.pump_disp_max_cc - 1.0) * 100.0
        errors[ch] = {"offset": e.offset, "gain_pct": gain_pct}
    events = list(raw["events"])
    if unit.arriving_leak_lpm > 0:
        events.append(
            {
                "type": "leakage",
                "component": "loop",
                "start_h": 0.0,
                "extra_lpm": unit.arriving_leak_lpm,
                "ref_dp_bar": ARRIVING_LEAK_REF_DP_BAR,
            }
        )
    sensors = {**raw.get("sensors", {}), "errors": errors}
    return {**raw, "drive": drive, "losses": losses, "sensors": sensors, "events": events}


def unit_truth(t: MachineType, unit: Unit) -> dict[str, Any]:
    """The sidecar's ``unit`` entry: the machine's own draws, against the type's nominal figures."""
    return {
        "pump_disp_max_cc": unit.pump_disp_max_cc,
        "motor_disp_max_cc": unit.motor_disp_max_cc,
        "motor_disp_cc": round(unit.motor_disp_max_cc * t.motor_disp_setting, 4),  # the true V_M
        "leak_factor": {"pump": unit.pump_leak_factor, "motor": unit.motor_leak_factor},
        "sensors": {k: {"offset": e.offset, "gain_pct": e.gain_pct} for k, e in unit.sensors.items()},
        "arriving_leak_lpm": unit.arriving_leak_lpm,
        "arriving_leak_ref_dp_bar": ARRIVING_LEAK_REF_DP_BAR,
    }


@dataclass(frozen=True)
class FleetSpec:
    machines: int
    hours: float
    seed: int = 1
    degrading_share: float = 0.5
    burst_s: float = 10.0
    every_min: float = 20.0
    log_hours: float = 24.0
    start_epoch_s: float = 1767225600.0  # 2026-01-01 00:00 UTC
    # Machine types in turn (None: every type of TYPES); e.g. ("mid",) for a fleet of one type.
    types: tuple[str, ...] | None = None
    # Each machine's oil: a mean drawn in oil_temp_c, swinging +- a value drawn in oil_swing_c over 10 h.
    oil_temp_c: tuple[float, float] = (45.0, 70.0)
    oil_swing_c: tuple[float, float] = (5.0, 20.0)
    # Unit-to-unit variation (None: every machine an exact copy of its type).
    spread: UnitSpread | None = None
    # Healthy machines that arrive with a leak from hour 0, of a share of the type's rated flow (at
    # 2000 rpm) drawn in arriving_leak_pct, at 480 bar. Healthy leakage of these drives is about 3 %
    # of rated flow at 480 bar and 60 C, its spread (leak_sigma 0.2) about +-0.6 % (1 sigma): 4 to
    # 8 % stands well clear of it and well below a worn unit's loss of function (25 %). Not clear of a
    # unit's displacement tolerance in the mean ratio (+-2 % of the flow, where the leak shows as about
    # 0.7 x its share at the duty's pressures): fleet train tells them apart by the part that grows
    # with the pressure (docs/fleet.md, "What size of arriving leak is named").
    arriving_leaks: int = 0
    arriving_leak_pct: tuple[float, float] = (4.0, 8.0)
    # The faults degrading machines develop, in turn (of DEGRADATIONS), and the operating hour before
    # which none starts (a fleet whose machines first learn a baseline: the fault comes after it). A
    # later onset only shortens the fault's span: the draws, the failure hours, stay as they were.
    degradations: tuple[str, ...] = ("motor_wear", "pump_wear", "misposition")
    onset_min_h: float = 0.0

    @property
    def type_names(self) -> tuple[str, ...]:
        return tuple(TYPES) if self.types is None else tuple(self.types)

    @property
    def degrading_count(self) -> int:
        return round(self.degrading_share * self.machines)

    def check(self) -> None:
        if self.machines < 1:
            raise ValueError(f"machines must be at least 1, got {self.machines}")
        if not 4.0 <= self.hours <= 20000.0:
            raise ValueError(f"hours must be between 4 and 20000, got {self.hours}")
        if not 0.0 <= self.degrading_share <= 1.0:
            raise ValueError(f"degrading share must be between 0 and 1, got {self.degrading_share}")
        if self.log_hours <= 0:
            raise ValueError(f"log hours must be positive, got {self.log_hours}")
        if self.burst_s > self.every_min * 60.0:
            raise ValueError(f"a burst ({self.burst_s} s) must fit its interval ({self.every_min} min)")
        self._check_types()
        _check_range("oil temperature", self.oil_temp_c, -30.0, 120.0, "C")
        _check_range("oil swing", self.oil_swing_c, 0.0, 50.0, "C")
        coldest, hottest = self.oil_temp_c[0] - self.oil_swing_c[1], self.oil_temp_c[1] + self.oil_swing_c[1]
        if coldest < -30.0 or hottest > 120.0:
            raise ValueError(f"oil would swing from {coldest:g} to {hottest:g} C, outside -30 .. 120 C")
        if self.spread is not None:
            self.spread.check()
        healthy = self.machines - self.degrading_count
        if not (isinstance(self.arriving_leaks, int) and 0 <= self.arriving_leaks <= healthy):
            raise ValueError(
                f"arriving leaks must be between 0 and the {healthy} healthy machines, got {self.arriving_leaks}"
            )
        _check_range("arriving leak", self.arriving_leak_pct, 0.1, 50.0, "% of rated flow")
        unknown = [k for k in self.degradations if k not in DEGRADATIONS]
        if not self.degradations or unknown:
            raise ValueError(f"degradations must name at least one of {', '.join(DEGRADATIONS)}, got {unknown}")
        # failures fall in 0.70 .. 0.92 of the hours (_degradation): the onset must leave a span
        latest = FAIL_FROM_SHARE * self.hours - MIN_SPAN_H
        if not (math.isfinite(self.onset_min_h) and 0.0 <= self.onset_min_h <= latest):
            raise ValueError(
                f"onset_min_h must be between 0 and {latest:g} h ({FAIL_FROM_SHARE:g} of the hours less "
                f"{MIN_SPAN_H:g} h), got {self.onset_min_h}"
            )

    def _check_types(self) -> None:
        if self.types is None:
            return
        if not self.types:
            raise ValueError("types must name at least one machine type")
        unknown = [t for t in self.types if t not in TYPES]
        if unknown:
            raise ValueError(f"unknown machine type {unknown[0]!r}; types: {', '.join(TYPES)}")


def _check_range(what: str, lo_hi: tuple[float, float], lo: float, hi: float, unit: str) -> None:
    if len(lo_hi) != 2 or not lo <= lo_hi[0] <= lo_hi[1] <= hi:
        raise ValueError(f"{what} range must be (low, high) with {lo} <= low <= high <= {hi} {unit}, got {lo_hi}")


# Fields that came with unit-to-unit variation: the sidecar states them only when they are not at
# their defaults, so a fleet without them is written as before, byte for byte.
_NEW_SPEC_FIELDS = (
    "types",
    "oil_temp_c",
    "oil_swing_c",
    "spread",
    "arriving_leaks",
    "arriving_leak_pct",
    "degradations",
    "onset_min_h",
)


def spec_record(spec: FleetSpec) -> dict[str, Any]:
    """The spec as the sidecar states it."""
    default = {f.name: f.default for f in fields(FleetSpec) if f.name in _NEW_SPEC_FIELDS}
    return {k: v for k, v in asdict(spec).items() if k not in default or getattr(spec, k) != default[k]}


@dataclass(frozen=True)
class MachinePlan:
    machine: str
    type: MachineType
    scenario: scn.Scenario
    degrading: bool
    truth: dict[str, Any]  # the sidecar's entry for this machine

    @property
    def start_epoch_s(self) -> float:
        return self.scenario.start_epoch_s


def _degradation(
    kind: str, t: MachineType, hours: float, rng: np.random.Generator, onset_min_h: float = 0.0
) -> list[dict[str, Any]]:
    """One fault developing over the machine's hours, failing in the last third of them, starting no
    earlier than ``onset_min_h`` (the same draws whatever it is)."""
    fail_h = round(float(hours * rng.uniform(FAIL_FROM_SHARE, 0.92)), 2)
    span = float(min(fail_h * 0.8, hours * rng.uniform(0.30, 0.45)))
    start_h = max(round(fail_h - span, 2), onset_min_h)
    if kind == "misposition":  # the displacement control drifts (ratio goes up)
        return [
            {
                "type": "misposition",
                "mode": "drift",
                "start_h": start_h,
                "end_h": fail_h,
                "pct": -10.0,
                "fail_h": fail_h,
            }
        ]
    return [
        {
            "type": "wear",
            "component": kind.split("_")[0],
            "start_h": start_h,
            "fail_h": fail_h,
            "fail_extra_lpm": round(FAIL_SHARE_OF_RATED * t.rated_flow_lpm(), 1),
        }
    ]


DEGRADATIONS = ("motor_wear", "pump_wear", "misposition")
FAIL_FROM_SHARE = 0.70  # a degrading machine fails after this share of its hours
MIN_SPAN_H = 2.0  # onset_min_h leaves a fault at least this long to develop


def plan_fleet(spec: FleetSpec) -> list[MachinePlan]:
    """Machines ``m001``, ``m002``, ...: types in turn, duty, oil climate and start date drawn from the
    seed; the first ``round(share * N)`` of a shuffled order degrade (kinds in turn), the rest stay
    healthy."""
    spec.check()
    rng = np.random.default_rng(spec.seed)
    n = spec.machines
    types = [TYPES[t] for t in spec.type_names]
    degrading = set(rng.permutation(n)[: spec.degrading_count].tolist())
    units = plan_units(spec, [types[i % len(types)] for i in range(n)], degrading)
    plans = []
    k_deg = 0
    for i in range(n):
        mt = types[i % len(types)]
        unit = units[i]
        name = f"m{i + 1:03d}"
        duty = DUTIES[int(rng.integers(len(DUTIES)))]
        oil_c = round(float(rng.uniform(*spec.oil_temp_c)), 1)
        swing_c = round(float(rng.uniform(*spec.oil_swing_c)), 1)
        start = spec.start_epoch_s + 86400.0 * int(rng.integers(0, 30))
        events: list[dict[str, Any]] = []
        kind = None
        if i in degrading:
            kind = spec.degradations[k_deg % len(spec.degradations)]
            k_deg += 1
            events = _degradation(kind, mt, spec.hours, rng, spec.onset_min_h)
        leak = f", arriving with a {unit.arriving_leak_lpm:g} l/min leak" if unit and unit.arriving_leak_lpm else ""
        raw = {
            "name": f"fleet_{name}",
            "description": f"fleet machine {name}: {mt.name} drive, {duty}, "
            + (f"{kind} failing at {events[0]['fail_h']} h" if events else "healthy")
            + leak,
            "seed": int(rng.integers(2**31)),
            "duration_h": spec.hours,
            "start_epoch_s": start,
            "sampling": {"mode": "bursts", "burst_s": spec.burst_s, "every_min": spec.every_min},
            "drive": mt.drive(),
            "oil": {"model": "prescribed", "temp_c": oil_c, "swing_c": swing_c, "period_h": 10.0},
            "duty": {
                "kind": duty,
                "speed_scale": round(float(rng.uniform(0.9, 1.1)), 3),
                "load_scale": round(float(rng.uniform(0.8, 1.1)), 3),
            },
            "events": events,
        }
        if unit is not None:
            raw = apply_unit(raw, mt, unit)
        s = scn.from_dict(raw, source=f"<fleet {name}>")
        failures = [{**f, "fail_epoch_s": start + f["fail_h"] * 3600.0} for f in _failures(events)]
        truth = {
            "machine": name,
            "type": mt.name,
            "motor_disp_cc": mt.motor_disp_cc,
            "duty": duty,
            "oil_temp_c": oil_c,
            "oil_swing_c": swing_c,
            "start_epoch_s": start,
            "hours": spec.hours,
            "degrading": bool(events),
            "degradation": kind,
            # as simulated: every key its value, the defaults too (the wear's shape and law)
            "events": [dict(e) for e in s.events[: len(events)]],
            "failures": failures,
        }
        if unit is not None:
            truth["unit"] = unit_truth(mt, unit)
        plans.append(MachinePlan(name, mt, s, bool(events), truth))
    return plans


def plan_units(spec: FleetSpec, machine_types: list[MachineType], degrading: set[int]) -> list[Unit | None]:
    """Each machine's own draws (None for all when the spec asks for no variation and no leaks).

    Two streams of their own: one for the units' draws, one for which healthy machines arrive leaking
    and how much, so neither the plan's draws nor each other's move when one is switched on."""
    if spec.spread is None and spec.arriving_leaks == 0:
        return [None] * len(machine_types)
    rng_unit = np.random.default_rng([spec.seed, SPREAD_STREAM, 0])
    units = [draw_unit(t, spec.spread, rng_unit) if spec.spread else nominal_unit(t) for t in machine_types]
    rng_leak = np.random.default_rng([spec.seed, SPREAD_STREAM, 1])
    healthy = [i for i in range(len(machine_types)) if i not in degrading]
    leaking = sorted(rng_leak.choice(healthy, size=spec.arriving_leaks, replace=False).tolist()) if healthy else []
    for i in leaking:
        pct = float(rng_leak.uniform(*spec.arriving_leak_pct))
        units[i] = replace(units[i], arriving_leak_lpm=round(pct / 100.0 * machine_types[i].rated_flow_lpm(), 2))
    return units


def _failures(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out = []
    for ev in events:
        if ev["type"] == "wear":
            out.append({"component": ev["component"], "kind": "wear", "onset_h": ev["start_h"], "fail_h": ev["fail_h"]})
        elif ev["type"] == "misposition" and ev.get("fail_h") is not None:
            out.append({"component": "motor", "kind": "misposition", "onset_h": ev["start_h"], "fail_h": ev["fail_h"]})
    return out


def training_scenario(t: MachineType, seed: int) -> scn.Scenario:
    """A healthy test-rig sweep of the type's drive over the mobile envelope and oil 20-100 C: the
    type's model is trained on its first ``TRAINING_T_TRN_H`` hours."""
    raw = {
        "name": f"training_{t.name}",
        "description": f"healthy sweep of the {t.name} drive for its model",
        "seed": seed,
        "duration_h": TRAINING_HOURS,
        "drive": t.drive(),
        "oil": {
            "model": "profile",
            "points": [[0.0, 45], [0.1, 95], [0.2, 20], [0.3, 80], [0.4, 30], [0.5, 100], [0.6, 55]],
        },
        "duty": {
            "kind": "sweep",
            "pump_speed_rpm": [800, 2600],
            "pump_disp_pct": [5, 100],
            "dp_bar": [20, 520],
            "hold_s": [4, 10],
            "edge_share": 0.2,
        },
    }
    return scn.from_dict(raw, source=f"<training {t.name}>")


def log_spans(spec: FleetSpec) -> list[tuple[float, float]]:
    """Operating-hour spans [start, end) of a machine's logs: one log per ``log_hours`` of operation."""
    edges = [*np.arange(0.0, spec.hours, spec.log_hours).tolist(), spec.hours]
    return [(float(a), float(b)) for a, b in itertools.pairwise(edges) if b > a]
