"""Degradation events over operating hours: leakage, wear, misposition, sudden failure, replacement.

Each event is a pure function of operating hours. A replacement of a component ends the effects of
every earlier event on that component (a new unit is healthy); a bypass leakage on the loop is not
a component and is not reset by a replacement.

Leakage amounts are stated as l/min at a reference operating point, the way a test rig reports them:
- wear grows the laminar gap flow: Q = x(t) * (dp / dp_ref) * (mu_ref / mu), x(t) = F * s^k with
  s the fraction of the way from wear onset to failure (slow, then accelerating); or (``law:
  orifice``, a crack or a torn seal) an orifice, Q = x(t) * sqrt(dp / dp_ref); x(t) may come in
  ``steps`` (staged damage), and its pace change at ``rate_change_h`` (other work from then on);
- an artificial leakage is an orifice: Q = x * sqrt(dp / dp_ref).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.oil import Oil
from cmcan.sim.physics import BAR, LPM

# After loss of function the unit leaks this many times its wear leakage at failure.
LOSS_OF_FUNCTION_FACTOR = 3.0


@dataclass(frozen=True)
class Degradation:
    """Per-sample degradation state, as conductances for the integrator plus the ground truth."""

    wear_g_pump: NDArray[np.float64]
    wear_g_motor: NDArray[np.float64]
    bypass_h: NDArray[np.float64]
    misposition_pct: NDArray[np.float64]
    failed: NDArray[np.bool_]

    @property
    def motor_disp_factor(self) -> NDArray[np.float64]:
        return 1.0 + self.misposition_pct / 100.0


def _component_of(event: dict[str, Any]) -> str:
    if event["type"] == "misposition":
        return "motor"
    return str(event.get("component", "loop"))


def _active_window(event: dict[str, Any], events: list[dict[str, Any]]) -> tuple[float, float]:
    """[start, end) in hours during which an event acts: until the next replacement of its component."""
    start = float(event.get("start_h", event.get("at_h", 0.0)))
    comp = _component_of(event)
    ends = [
        float(e["at_h"])
        for e in events
        if e["type"] == "replace" and e["component"] == comp and float(e["at_h"]) > start
    ]
    return start, min(ends, default=np.inf)


def evaluate(events: list[dict[str, Any]], t_h: NDArray[np.float64], oil: Oil) -> Degradation:
    n = len(t_h)
    g = {"pump": np.zeros(n), "motor": np.zeros(n), "loop": np.zeros(n)}
    bypass = np.zeros(n)
    mis = np.zeros(n)
    failed = np.zeros(n, dtype=bool)
    for ev in events:
        kind = ev["type"]
        if kind == "replace":
            continue
        start, end = _active_window(ev, events)
        act = (t_h >= start) & (t_h < end)
        if not act.any():
            continue
        th = t_h[act]
        if kind == "leakage":
            bypass[act] += ev["extra_lpm"] * LPM / np.sqrt(ev["ref_dp_bar"] * BAR) * _ramp(th, start, ev["ramp_h"])
        elif kind == "wear":
            x_lpm = wear_lpm(ev, th)
            broken = th >= ev["fail_h"]
            x_lpm = np.where(broken, ev["fail_extra_lpm"] * LOSS_OF_FUNCTION_FACTOR, x_lpm)
            if ev.get("law", "laminar") == "orifice":  # a crack, a torn seal: sqrt(dp), hardly any viscosity
                bypass[act] += x_lpm * LPM / np.sqrt(ev["ref_dp_bar"] * BAR)
            else:
                g[ev["component"]][act] += _laminar_g(x_lpm, ev["ref_dp_bar"], ev["ref_temp_c"], oil)
            failed[np.flatnonzero(act)[broken]] = True
        elif kind == "failure":
            g[ev["component"]][act] += _laminar_g(ev["extra_lpm"], ev["ref_dp_bar"], ev["ref_temp_c"], oil)
            failed[act] = True
        elif kind == "misposition":
            mis[act] += misposition_pct(ev, th)
            if ev["fail_h"] is not None:
                failed[np.flatnonzero(act)[th >= ev["fail_h"]]] = True
        else:
            raise ValueError(f"unknown event type {kind!r}")
    # A leak on the loop itself (not inside a unit) acts like pump-side leakage on the flow balance.
    return Degradation(g["pump"] + g["loop"], g["motor"], bypass, mis, failed)


def misposition_pct(ev: dict[str, Any], th: NDArray[np.float64]) -> NDArray[np.float64]:
    """A misposition's error of the motor's displacement (%) at operating hours ``th`` from its
    ``start_h`` on: all at once (``mode: step``) or ramped until ``end_h``."""
    if ev["mode"] == "step":
        return np.full(np.shape(th), float(ev["pct"]))
    start = float(ev["start_h"])
    return ev["pct"] * np.clip((th - start) / (ev["end_h"] - start), 0.0, 1.0)


def wear_progress(ev: dict[str, Any], th: NDArray[np.float64]) -> NDArray[np.float64]:
    """The share of the way from a wear's onset to its failure at operating hours ``th`` (0 to 1):
    even in time, or from ``rate_change_h`` on ``rate_factor`` times faster (failure stays at fail_h)."""
    start, fail = float(ev["start_h"]), float(ev["fail_h"])
    c, f = ev.get("rate_change_h"), float(ev.get("rate_factor", 1.0))
    if c is None or f == 1.0:
        return np.clip((th - start) / (fail - start), 0.0, 1.0)
    pace = 1.0 / ((c - start) + f * (fail - c))
    done = np.where(th < c, (th - start) * pace, (c - start) * pace + f * (th - c) * pace)
    return np.clip(done, 0.0, 1.0)


def wear_lpm(ev: dict[str, Any], th: NDArray[np.float64]) -> NDArray[np.float64]:
    """A wear's extra leakage at its reference point (l/min) before failure: F s^k, or that curve in
    ``steps`` jumps (each stage of damage reached at once)."""
    level = wear_progress(ev, th) ** ev["shape"]
    if ev.get("growth", "power") == "steps":
        n = int(ev.get("steps", 4))
        level = np.floor(level * n) / n
    return ev["fail_extra_lpm"] * level


def _ramp(th: NDArray[np.float64], start: float, ramp_h: float) -> NDArray[np.float64]:
    if ramp_h <= 0:
        return np.ones_like(th)
    return np.clip((th - start) / ramp_h, 0.0, 1.0)


def _laminar_g(x_lpm: Any, ref_dp_bar: float, ref_temp_c: float, oil: Oil) -> Any:
    mu_ref = float(oil.dynamic_viscosity_pa_s(ref_temp_c))
    return np.asarray(x_lpm, dtype=float) * LPM * mu_ref / (ref_dp_bar * BAR)


def scheduled_failures(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Failures the scenario schedules: (component, hour, kind), for lead-time reports."""
    out = []
    for ev in events:
        if ev["type"] == "wear":
            out.append(
                {
                    "component": ev["component"],
                    "fail_h": float(ev["fail_h"]),
                    "kind": "wear",
                    "onset_h": float(ev["start_h"]),
                }
            )
        elif ev["type"] == "failure":
            out.append(
                {
                    "component": ev["component"],
                    "fail_h": float(ev["at_h"]),
                    "kind": "sudden",
                    "onset_h": float(ev["at_h"]),
                }
            )
        elif ev["type"] == "misposition" and ev["fail_h"] is not None:
            out.append(
                {
                    "component": "motor",
                    "fail_h": float(ev["fail_h"]),
                    "kind": "misposition",
                    "onset_h": float(ev["start_h"]),
                }
            )
    return sorted(out, key=lambda f: f["fail_h"])
