"""What the monitor keeps across restarts: warning history, counts, time in each level, the filter."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from cmcan.errors import CmcanError, Kind
from cmcan.j1939.dm1 import OC_MAX

HISTORY_MAX = 1000
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

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, **asdict(self)}

    @classmethod
    def from_dict(cls, d: Any) -> Totals:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise StateError(f"not a {FORMAT} document")
        t = cls()
        try:
            t.warning_count = int(d["warning_count"])
            t.fault_count = int(d["fault_count"])
            t.evaluated_s = float(d["evaluated_s"])
            t.time_in_level_s = {k: float(d["time_in_level_s"][k]) for k in ("ok", "low", "high", "fault")}
            t.history = [dict(h) for h in d["history"]][-HISTORY_MAX:]
            t.condition = str(d["condition"])
            if t.condition not in ("ok", "low", "high"):
                raise StateError(f"condition {t.condition!r} is not one of ok, low, high")
            t.filter_ratios = [float(x) for x in d["filter_ratios"]]
            t.filter_leaks = [float(x) for x in d["filter_leaks"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise StateError(f"field {exc} missing or of the wrong type") from None
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
        return t


def _dtc_key(key: Any) -> None:
    """A DTC key is "SPN:FMI" with SPN 0..524287 and FMI 0..31."""
    parts = key.split(":") if isinstance(key, str) else []
    ok = len(parts) == 2 and all(x.isdigit() for x in parts) and int(parts[0]) < 1 << 19 and int(parts[1]) < 32
    if not ok:
        raise StateError(f"DTC key {key!r} is not SPN:FMI (SPN 0..524287, FMI 0..31)")
