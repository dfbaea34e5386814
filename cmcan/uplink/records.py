"""What leaves the machine, as outbox entries: pure code over values, no I/O, no clock.

Three kinds go into the outbox, each published on its own topic:
- ``event``: a warning level transition (ok, low, high, fault) at its tick's frame time;
- ``summary``: one per period of frame time (aligned to multiples of the period in UTC): ratio,
  leakage estimate, time in each level, counters, and the operating statistics that show a gap
  between the model and this machine (the model's residual, the learned correction's share, how
  often each gate held the point back, e.g. outside the training envelope);
- ``dropped``: what the outbox or the daemon's queue had to drop, and why.
The uplink wraps each body in the envelope (schema, machine id, id, seq, time, late flag) when it
publishes (``envelope``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

SCHEMA_VERSION = 1
EVENT, SUMMARY, DROPPED = "event", "summary", "dropped"
KINDS = (EVENT, SUMMARY, DROPPED)
LEVELS = ("ok", "low", "high", "fault")
ENVELOPE_KEYS = ("schema", "kind", "machine_id", "id", "seq", "t", "t_s", "late")


@dataclass(frozen=True)
class Entry:
    """One outbox entry before it is stored: kind (its topic), frame time, and the body."""

    kind: str
    t_s: float
    body: dict[str, Any]

    def to_json(self) -> str:
        return dumps(self.body)


@dataclass(frozen=True)
class TickSample:
    """What a summary takes from one evaluation tick (the monitor's ``Tick``, as plain values)."""

    t_s: float
    gate: str
    level: str
    reason: str
    ratio_raw_pct: float | None  # None when the tick did not evaluate
    ratio_filt_pct: float | None  # None while the filter is not valid
    extra_leak_lpm: float | None
    # the output quantity (motor speed in rpm or flow in l/min): measured, predicted, white-box
    measured: float
    predicted: float
    whitebox: float
    # the on-board baseline where configured: state, learned_h, coverage_pct, distance_lpm
    baseline: dict[str, Any] | None = None
    # the prognosis where configured: state, direction, hours to the warning and to end of life (p10/p50/p90)
    prognosis: dict[str, Any] | None = None


@dataclass(frozen=True)
class Cumulative:
    """Running totals at a tick: persisted totals of the monitor, and the process's counters."""

    time_in_level_s: dict[str, float]
    evaluated_s: float
    warning_count: int
    fault_count: int
    counters: dict[str, int]


def dumps(obj: Any) -> str:
    """Compact JSON; a NaN or infinity is a bug upstream and raises instead of producing bad JSON."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


def iso_utc(t_s: float) -> str:
    return datetime.fromtimestamp(t_s, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def num(x: float | None, digits: int) -> float | None:
    return round(float(x), digits) if x is not None and math.isfinite(x) else None


# -- events ----------------------------------------------------------------------------------------


def transition_entry(
    h: dict[str, Any], warning_count: int, fault_count: int, extra_leak_lpm: float | None = None
) -> Entry:
    """A level transition as recorded in the monitor's history (t_s, from, to, reason, ratio)."""
    return Entry(
        EVENT,
        float(h["t_s"]),
        {
            "type": "level_change",
            "from": h["from"],
            "to": h["to"],
            "reason": h["reason"],
            "ratio_filt_pct": num(h.get("ratio_filt_pct"), 4),
            "extra_leak_lpm": num(extra_leak_lpm, 4),
            "warning_count": int(warning_count),
            "fault_count": int(fault_count),
        },
    )


def baseline_entry(t_s: float, before: str | None, baseline: dict[str, Any]) -> Entry:
    """The on-board baseline changed state (learning ended, a suspect machine, a reset)."""
    return Entry(EVENT, float(t_s), {"type": "baseline_change", "from": before, **baseline})


def clear_entry(c: dict[str, Any]) -> Entry:
    """A J1939-73 DM3 or DM11 the monitor carried out (``Totals.dtc_clears``): what, who asked, when."""
    return Entry(
        EVENT,
        float(c["t_s"]),
        {
            "type": "dtc_clear",
            "kind": c["kind"],
            "by_address": int(c["by_address"]),
            "by_name": c.get("by_name"),
            "cleared": list(c["cleared"]),
        },
    )


def claim_entry(e: Any, name: int) -> Entry:
    """A change of the J1939 address claim (:class:`cmcan.can.j1939.claim.Event`): claiming, claimed, lost."""
    return Entry(
        EVENT,
        float(e.t_s),
        {
            "type": "address_claim",
            "state": e.state,
            "address": e.address,
            "name": f"0x{name:016X}",
            "detail": e.detail,
            "by_name": None if e.by_name is None else f"0x{e.by_name:016X}",
        },
    )


def new_history(history: list[Any], last_seen: Any) -> list[Any]:
    """The entries appended to ``history`` after ``last_seen`` (found by identity, newest last; the
    list is trimmed at its front, so indices shift but the objects stay the same)."""
    out: list[dict[str, Any]] = []
    for h in reversed(history):
        if h is last_seen:
            break
        out.append(h)
    out.reverse()
    return out


# -- summaries -------------------------------------------------------------------------------------


@dataclass
class _Stat:
    n: int = 0
    total: float = 0.0
    total_sq: float = 0.0
    lo: float = math.inf
    hi: float = -math.inf

    def add(self, x: float) -> None:
        if not math.isfinite(x):
            return
        self.n += 1
        self.total += x
        self.total_sq += x * x
        self.lo = min(self.lo, x)
        self.hi = max(self.hi, x)

    def to_dict(self, digits: int) -> dict[str, Any]:
        if self.n == 0:
            return {"n": 0, "mean": None, "std": None, "min": None, "max": None}
        mean = self.total / self.n
        var = max(0.0, self.total_sq / self.n - mean * mean)
        return {
            "n": self.n,
            "mean": num(mean, digits),
            "std": num(math.sqrt(var), digits),
            "min": num(self.lo, digits),
            "max": num(self.hi, digits),
        }


@dataclass
class _Window:
    index: int
    start: Cumulative
    first_t_s: float
    last_t_s: float = 0.0
    ticks: int = 0
    gates: dict[str, int] = field(default_factory=dict)
    ratio: _Stat = field(default_factory=_Stat)
    correction: _Stat = field(default_factory=_Stat)
    speed: _Stat = field(default_factory=_Stat)
    last: TickSample | None = None
    ratio_filt: float | None = None
    leak: float | None = None


class SummaryBuilder:
    """Accumulates ticks into windows of ``every_s`` frame time; a tick in a later window closes the
    current one into a summary entry. Totals are taken as differences of ``Cumulative`` snapshots, so
    time in each level and counters are exact even where a tick was not sampled."""

    def __init__(self, every_s: float, baseline: Cumulative, quantity: str = "motor_speed_rpm") -> None:
        if not every_s > 0:
            raise ValueError("every_s must be positive")
        self.every_s = float(every_s)
        self.quantity = quantity  # the measured output's statistics go under its role's name
        self.cum = baseline  # the snapshot at the newest tick seen (or at start)
        self.window: _Window | None = None

    def add(self, tick: TickSample, cum: Cumulative) -> list[Entry]:
        out: list[Entry] = []
        if not math.isfinite(tick.t_s):
            self.cum = cum
            return out
        k = math.floor(tick.t_s / self.every_s)
        w = self.window
        if w is not None and k != w.index:
            out.append(self._close(w, "period"))
            w = None
        if w is None:
            w = self.window = _Window(k, self.cum, tick.t_s)
        w.ticks += 1
        w.last_t_s = tick.t_s
        w.gates[tick.gate] = w.gates.get(tick.gate, 0) + 1
        if tick.ratio_raw_pct is not None:
            w.ratio.add(tick.ratio_raw_pct)
            w.speed.add(tick.measured)
            if tick.whitebox > 0:
                w.correction.add((tick.predicted - tick.whitebox) / tick.whitebox * 100.0)
        if tick.ratio_filt_pct is not None:
            w.ratio_filt = tick.ratio_filt_pct
            w.leak = tick.extra_leak_lpm
        w.last = tick
        self.cum = cum
        return out

    def close(self, cum: Cumulative | None = None) -> list[Entry]:
        """The current window as a summary now (at shutdown), with the totals ``cum`` of this moment;
        nothing when no tick was seen."""
        if cum is not None:
            self.cum = cum
        if self.window is None:
            return []
        w, self.window = self.window, None
        return [self._close(w, "shutdown")]

    def _close(self, w: _Window, closed_by: str) -> Entry:
        a, b = w.start, self.cum
        assert w.last is not None
        start_s = w.index * self.every_s
        counters = {k: int(v - a.counters.get(k, 0)) for k, v in b.counters.items()}
        body = {
            "window": {
                "start": iso_utc(start_s),
                "start_s": start_s,
                "every_s": self.every_s,
                "first_tick_s": w.first_t_s,
                "last_tick_s": w.last_t_s,
                "ticks_sampled": w.ticks,
                "closed_by": closed_by,
            },
            "level": w.last.level,
            "reason": w.last.reason,
            "ratio_filt_pct": num(w.ratio_filt, 4),
            "extra_leak_lpm": num(w.leak, 4),
            "ratio_raw_pct": w.ratio.to_dict(4),
            "correction_pct": w.correction.to_dict(4),
            self.quantity: w.speed.to_dict(4),
            "gate_ticks": dict(sorted(w.gates.items())),
            "time_in_level_s": {
                lv: num(b.time_in_level_s.get(lv, 0.0) - a.time_in_level_s.get(lv, 0.0), 3) for lv in LEVELS
            },
            "time_in_level_total_s": {lv: num(b.time_in_level_s.get(lv, 0.0), 3) for lv in LEVELS},
            "evaluated_s": num(b.evaluated_s - a.evaluated_s, 3),
            "evaluated_total_h": num(b.evaluated_s / 3600.0, 6),
            "warnings_raised": b.warning_count - a.warning_count,
            "warning_count": b.warning_count,
            "faults_raised": b.fault_count - a.fault_count,
            "fault_count": b.fault_count,
            "counters": counters,
            "counters_total": dict(b.counters),
        }
        if w.last.baseline is not None:
            body["baseline"] = w.last.baseline
        if w.last.prognosis is not None:
            body["prognosis"] = w.last.prognosis
        return Entry(SUMMARY, w.last_t_s, body)


# -- what was dropped ------------------------------------------------------------------------------


@dataclass
class Dropped:
    """Entries dropped for one reason: 'size' or 'age' (the outbox's bounds), 'queue_full' (the
    daemon's queue), 'corrupt_outbox' (the file was corrupt: what it held, unknown in number, is kept
    aside on the gateway as ``kept_as``)."""

    reason: str
    entries: int = 0
    bytes: int = 0
    by_kind: dict[str, int] = field(default_factory=dict)
    first_t_s: float | None = None
    last_t_s: float | None = None
    first_seq: int | None = None
    last_seq: int | None = None
    kept_as: str | None = None  # 'corrupt_outbox': the file the unsent entries are kept in

    def add(self, kind: str, t_s: float, nbytes: int = 0, seq: int | None = None) -> None:
        self.entries += 1
        self.bytes += nbytes
        self.by_kind[kind] = self.by_kind.get(kind, 0) + 1
        if math.isfinite(t_s):
            self.first_t_s = t_s if self.first_t_s is None else min(self.first_t_s, t_s)
            self.last_t_s = t_s if self.last_t_s is None else max(self.last_t_s, t_s)
        if seq is not None:
            self.first_seq = seq if self.first_seq is None else min(self.first_seq, seq)
            self.last_seq = seq if self.last_seq is None else max(self.last_seq, seq)

    def body(self) -> dict[str, Any]:
        return {
            "reason": self.reason,
            "entries": self.entries,
            "bytes": self.bytes,
            "by_kind": dict(sorted(self.by_kind.items())),
            "first_t_s": self.first_t_s,
            "last_t_s": self.last_t_s,
            "first_seq": self.first_seq,
            "last_seq": self.last_seq,
            **({"kept_as": self.kept_as} if self.kept_as is not None else {}),
        }

    def to_json(self) -> str:
        return dumps(self.body())


# -- the envelope ----------------------------------------------------------------------------------


def envelope(machine_id: str, stream_id: str, seq: int, kind: str, t_s: float, late: bool, body_json: str) -> str:
    """The published payload: envelope fields first, then the stored body's fields. ``id`` is the same
    for every copy of an entry (a QoS 1 duplicate or a resend after a restart): consumers deduplicate
    by it; ``seq`` increases with every entry of this outbox, so order and gaps are visible."""
    head = dumps(
        {
            "schema": SCHEMA_VERSION,
            "kind": kind,
            "machine_id": machine_id,
            "id": f"{stream_id}-{seq}",
            "seq": seq,
            "t": iso_utc(t_s),
            "t_s": t_s,
            "late": late,
        }
    )
    if not (body_json.startswith("{") and body_json.endswith("}")):
        raise ValueError(f"entry {seq}: body is not a JSON object")
    return head if body_json == "{}" else head[:-1] + "," + body_json[1:]
