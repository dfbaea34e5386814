"""What the monitor keeps across restarts: warning history, counts, time in each level, the filter."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can.j1939.dm1 import OC_MAX
from cmcan.errors import CmcanError, Kind
from cmcan.monitor.tick import LEVEL_NAMES
from cmcan.monitor.warnings import Level, Reason, Transition, add_repeat

HISTORY_MAX = 1000
CLEARS_MAX = 100
FORMAT = "cmcan-state/1"


class StateError(CmcanError, ValueError):
    """A state document cannot be read back; ``str()`` says which field is wrong."""

    kind = Kind.DATA


@dataclass
class Totals:
    warning_count: int = 0  # low and high warnings raised since commissioning
    fault_count: int = 0
    evaluated_s: float = 0.0  # steady operating time the ratio was evaluated over
    time_in_level_s: dict[str, float] = field(
        default_factory=lambda: {"ok": 0.0, "low": 0.0, "high": 0.0, "fault": 0.0}
    )
    history: list[dict[str, Any]] = field(default_factory=list)  # newest last, at most HISTORY_MAX
    condition: str = "ok"  # ratio condition underneath any fault, restored on restart
    filter_ratios: list[float] = field(default_factory=list)
    filter_leaks: list[float] = field(default_factory=list)
    # J1939 DM1: occurrence count per DTC ("SPN:FMI") and the DTCs active at the last save
    dtc_occurrences: dict[str, int] = field(default_factory=dict)
    dtc_active: list[str] = field(default_factory=list)
    # J1939-73 DM3 and DM11: each clear, with who asked (address, NAME where known) and when
    dtc_clears: list[dict[str, Any]] = field(default_factory=list)  # newest last, at most CLEARS_MAX
    # the on-board baseline (cmcan.monitor.baseline's document, checked there), None where not configured
    baseline: dict[str, Any] | None = None
    # the prognosis's history (cmcan.monitor.prognosis's document, checked there), None where not configured
    prognosis: dict[str, Any] | None = None

    def record(self, tr: Transition, run_shift_s: float) -> None:
        """A level change, with its time on the run's continuous time base (``Monitor.run_shift_s``)."""
        self.history.append(
            {
                "t_s": tr.t_s,
                "from": LEVEL_NAMES[tr.level_from],
                "to": LEVEL_NAMES[tr.level_to],
                "reason": tr.reason.name.lower(),
                "ratio_filt_pct": tr.ratio_pct,
                "t_run_s": tr.t_s + run_shift_s,
            }
        )
        del self.history[:-HISTORY_MAX]

    def record_clear(
        self, kind: str, t_s: float, t_run_s: float, by_address: int, by_name: int | None, cleared: list[str]
    ) -> None:
        """A DM3 or DM11 carried out at ``t_s``: what it cleared and who asked."""
        self.dtc_clears.append(
            {
                "t_s": t_s,
                "t_run_s": t_run_s,
                "kind": kind,
                "by_address": by_address,
                "by_name": None if by_name is None else f"0x{by_name:016X}",
                "cleared": list(cleared),
            }
        )
        del self.dtc_clears[:-CLEARS_MAX]

    def tick(self, level: Level, evaluated: bool, period_s: float) -> None:
        """One tick's time: in its level, and evaluated or not."""
        if evaluated:
            self.evaluated_s += period_s
        self.time_in_level_s[LEVEL_NAMES[level]] += period_s

    def ticks(self, levels: NDArray[np.int8], n_evaluated: int, period_s: float) -> None:
        """:meth:`tick` for a stretch of ticks: the same float additions, in the same order."""
        for lv in Level:
            cnt = int(np.count_nonzero(levels == lv))
            if cnt:
                name = LEVEL_NAMES[lv]
                self.time_in_level_s[name] = add_repeat(self.time_in_level_s[name], period_s, cnt)
        self.evaluated_s = add_repeat(self.evaluated_s, period_s, n_evaluated)

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, **asdict(self)}

    @classmethod
    def from_dict(cls, d: Any) -> Totals:
        """Read a saved document back, every field checked: a counter that is not a non-negative
        integer, a time that is not a finite non-negative number, a ratio that is not finite would be
        carried on (and written back) for ever; ``StateError`` names the field instead."""
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise StateError(f"not a {FORMAT} document")
        missing = [k for k in _FIELDS if k not in d]
        if missing:
            raise StateError(f"field {missing[0]!r} missing")
        t = cls()
        t.warning_count = _count(d["warning_count"], "warning_count")
        t.fault_count = _count(d["fault_count"], "fault_count")
        t.evaluated_s = _duration(d["evaluated_s"], "evaluated_s")
        tl = d["time_in_level_s"]
        if not isinstance(tl, dict) or set(tl) != set(LEVELS):
            raise StateError(f"field 'time_in_level_s': expected a mapping of {', '.join(LEVELS)}, got {tl!r:.80}")
        t.time_in_level_s = {k: _duration(tl[k], f"time_in_level_s.{k}") for k in LEVELS}
        if not isinstance(d["history"], list):
            raise StateError(f"field 'history': expected a list, got {d['history']!r:.80}")
        t.history = [_transition(h, f"history[{i}]") for i, h in enumerate(d["history"])][-HISTORY_MAX:]
        t.condition = d["condition"]
        if t.condition not in ("ok", "low", "high"):
            raise StateError(f"field 'condition': {t.condition!r:.40} is not one of ok, low, high")
        t.filter_ratios = _finite_list(d["filter_ratios"], "filter_ratios")
        t.filter_leaks = _finite_list(d["filter_leaks"], "filter_leaks")
        if len(t.filter_ratios) != len(t.filter_leaks):
            raise StateError("filter_ratios and filter_leaks differ in length")
        # absent in state files written before J1939 diagnostics: start with no counts
        occ = d.get("dtc_occurrences", {})
        active = d.get("dtc_active", [])
        if not isinstance(occ, dict) or not isinstance(active, list):
            raise StateError("dtc_occurrences must be a mapping and dtc_active a list")
        for key, n in occ.items():
            _dtc_key(key)
            if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= OC_MAX:
                raise StateError(f"dtc_occurrences[{key!r}]: expected an occurrence count 0..{OC_MAX}, got {n!r}")
        for key in active:
            _dtc_key(key)
        t.dtc_occurrences = {str(k): int(v) for k, v in occ.items()}
        t.dtc_active = [str(k) for k in active]
        t.dtc_clears = _clears(d.get("dtc_clears", []))  # absent before J1939 clears were kept
        bl = d.get("baseline")  # absent before the on-board baseline
        if bl is not None and not isinstance(bl, dict):
            raise StateError(f"field 'baseline': expected a mapping or null, got {bl!r:.80}")
        t.baseline = bl
        pg = d.get("prognosis")  # absent before the prognosis
        if pg is not None and not isinstance(pg, dict):
            raise StateError(f"field 'prognosis': expected a mapping or null, got {pg!r:.80}")
        t.prognosis = pg
        return t


def _clears(v: Any) -> list[dict[str, Any]]:
    """The DM3/DM11 records as :meth:`Totals.record_clear` writes them."""
    if not isinstance(v, list):
        raise StateError(f"field 'dtc_clears': expected a list, got {v!r:.60}")
    out = []
    for i, c in enumerate(v[-CLEARS_MAX:]):
        ok = (
            isinstance(c, dict)
            and c.get("kind") in ("dm3", "dm11")
            and _is_number(c.get("t_s"))
            and _is_number(c.get("t_run_s"))
            and isinstance(c.get("by_address"), int)
            and not isinstance(c.get("by_address"), bool)
            and 0 <= c["by_address"] <= 255
            and (c.get("by_name") is None or isinstance(c.get("by_name"), str))
            and isinstance(c.get("cleared"), list)
        )
        if not ok:
            raise StateError(f"field 'dtc_clears[{i}]': not a DM3/DM11 record: {c!r:.80}")
        for key in c["cleared"]:
            _dtc_key(key)
        out.append(dict(c))
    return out


def _dtc_key(key: Any) -> None:
    """A DTC key is "SPN:FMI" with SPN 0..524287 and FMI 0..31."""
    parts = key.split(":") if isinstance(key, str) else []
    ok = len(parts) == 2 and all(x.isdigit() for x in parts) and int(parts[0]) < 1 << 19 and int(parts[1]) < 32
    if not ok:
        raise StateError(f"DTC key {key!r} is not SPN:FMI (SPN 0..524287, FMI 0..31)")


_FIELDS = ("warning_count", "fault_count", "evaluated_s", "time_in_level_s", "history", "condition")
_FIELDS += ("filter_ratios", "filter_leaks")
LEVELS = tuple(LEVEL_NAMES[lv] for lv in Level)  # ok, low, high, fault
_REASONS = tuple(r.name.lower() for r in Reason)  # as the core records them


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _count(v: Any, name: str) -> int:
    if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
        raise StateError(f"field {name!r}: expected a non-negative integer, got {v!r:.40}")
    return v


def _duration(v: Any, name: str) -> float:
    if not (_is_number(v) and v >= 0):
        raise StateError(f"field {name!r}: expected a finite non-negative number of seconds, got {v!r:.40}")
    return float(v)


def _finite_list(v: Any, name: str) -> list[float]:
    if not isinstance(v, list):
        raise StateError(f"field {name!r}: expected a list of numbers, got {v!r:.40}")
    for i, x in enumerate(v):
        if not _is_number(x):
            raise StateError(f"field '{name}[{i}]': expected a finite number, got {x!r:.40}")
    return [float(x) for x in v]


def _transition(h: Any, name: str) -> dict[str, Any]:
    """One warning-level change as the core records it (t_s, from, to, reason, ratio_filt_pct, and
    t_run_s since this version)."""
    if not isinstance(h, dict):
        raise StateError(f"field {name!r}: expected a level change, got {h!r:.60}")
    if not _is_number(h.get("t_s")):
        raise StateError(f"field '{name}.t_s': expected a finite time, got {h.get('t_s')!r:.40}")
    if "t_run_s" in h and not _is_number(h["t_run_s"]):  # absent in states of older versions
        raise StateError(f"field '{name}.t_run_s': expected a finite time, got {h['t_run_s']!r:.40}")
    for key in ("from", "to"):
        if h.get(key) not in LEVELS:
            raise StateError(f"field '{name}.{key}': expected one of {', '.join(LEVELS)}, got {h.get(key)!r:.40}")
    if h.get("reason") not in _REASONS:
        raise StateError(f"field '{name}.reason': expected one of {', '.join(_REASONS)}, got {h.get('reason')!r:.40}")
    r = h.get("ratio_filt_pct")
    if r is not None and not _is_number(r):
        raise StateError(f"field '{name}.ratio_filt_pct': expected a finite number or null, got {r!r:.40}")
    return dict(h)
