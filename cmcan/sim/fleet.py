"""A simulated fleet: machines of a few types (drive sizes), each with its own duty, oil and fate.

Pure planning: from (machines, hours, seed) to one scenario per machine (validated by
:mod:`cmcan.sim.scenario`), the training scenario of each machine type, and the ground truth. The
files (logs, configurations, models, the sidecar) are written by :mod:`cmcan.fleet.simfleet`.

The fleet is a time-lapse like the run-to-failure scenario: each machine is sampled in bursts
(``burst_s`` every ``every_min`` minutes of operation), so hundreds of operating hours fit in a few
hundred thousand frames; a burst's timestamps carry its true operating time.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np

from cmcan.sim import scenario as scn


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


def _degradation(kind: str, t: MachineType, hours: float, rng: np.random.Generator) -> list[dict[str, Any]]:
    """One fault developing over the machine's hours, failing in the last third of them."""
    fail_h = round(float(hours * rng.uniform(0.70, 0.92)), 2)
    span = float(min(fail_h * 0.8, hours * rng.uniform(0.30, 0.45)))
    start_h = round(fail_h - span, 2)
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


def plan_fleet(spec: FleetSpec) -> list[MachinePlan]:
    """Machines ``m001``, ``m002``, ...: types in turn, duty, oil climate and start date drawn from the
    seed; the first ``round(share * N)`` of a shuffled order degrade (kinds in turn), the rest stay
    healthy."""
    spec.check()
    rng = np.random.default_rng(spec.seed)
    n = spec.machines
    types = list(TYPES.values())
    degrading = set(rng.permutation(n)[: round(spec.degrading_share * n)].tolist())
    plans = []
    k_deg = 0
    for i in range(n):
        mt = types[i % len(types)]
        name = f"m{i + 1:03d}"
        duty = DUTIES[int(rng.integers(len(DUTIES)))]
        oil_c = round(float(rng.uniform(45.0, 70.0)), 1)
        swing_c = round(float(rng.uniform(5.0, 20.0)), 1)
        start = spec.start_epoch_s + 86400.0 * int(rng.integers(0, 30))
        events: list[dict[str, Any]] = []
        kind = None
        if i in degrading:
            kind = DEGRADATIONS[k_deg % len(DEGRADATIONS)]
            k_deg += 1
            events = _degradation(kind, mt, spec.hours, rng)
        raw = {
            "name": f"fleet_{name}",
            "description": f"fleet machine {name}: {mt.name} drive, {duty}, "
            + (f"{kind} failing at {events[0]['fail_h']} h" if events else "healthy"),
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
            "events": events,
            "failures": failures,
        }
        plans.append(MachinePlan(name, mt, s, bool(events), truth))
    return plans


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
