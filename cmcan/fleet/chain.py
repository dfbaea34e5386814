"""A machine's logs as one life: the monitor's state carried from each log to the next in time order.

The daemon keeps its state across restarts (``cmcan.monitor.totals.Totals``: the filter's contents,
the ratio condition under a warning, warning and fault counts, time in each level, DM1 occurrence
counts) and restores it when it starts again. Replaying a machine's consecutive logs carries the
same state from one log's end to the next log's start, so the fleet says what the daemon would have
said: a wear episode across two logs is one warning, the filter does not start empty at each log.

The state is not carried (the log starts fresh, and its ``state_in`` says why) when:

- the log is the machine's first in the data set;
- more than :data:`MAX_CARRY_GAP_H` hours of log time lie between the previous log's last frame and
  this one's first: a week without a log is a machine that was parked, repaired or moved, or logs
  that are missing; the filter refills in a few minutes of steady operation, a stale condition
  from before a repair would mislead for much longer;
- the log starts more than :data:`OVERLAP_TOLERANCE_S` before the previous one ended (two loggers,
  a log named twice under different names): there is no one order to carry in;
- the previous log was replayed with another configuration, DBC or model (its filter and
  condition are in another model's terms).

The carried state leaves out the warning history (the events table has it). Pure: no files.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Any

MAX_CARRY_GAP_H = 168.0
OVERLAP_TOLERANCE_S = 1.0
FRESH_FIRST = "first log of the machine in this run"


@dataclass(frozen=True)
class Carry:
    """The state a log starts from: ``state`` a ``Totals.to_dict()`` (None: fresh), why, and which
    log it comes from."""

    state: dict[str, Any] | None = None
    note: str = FRESH_FIRST
    from_log_hash: str | None = None
    inputs: tuple[str, str, str] | None = None  # (config, DBC, model) hashes of the log it comes from

    @property
    def carried(self) -> bool:
        return self.state is not None

    @property
    def state_hash(self) -> str:
        """16 hex of the carried state (empty for a fresh start), part of the log's provenance."""
        if self.state is None:
            return ""
        return hashlib.sha256(json.dumps(self.state, sort_keys=True).encode()).hexdigest()[:16]

    def fresh_because(self, why: str) -> Carry:
        return Carry(None, f"fresh: {why}", None, None)


@dataclass(frozen=True)
class LogEnd:
    """What the next log of the machine needs from one that went through: its end."""

    log_hash: str
    log_name: str
    last_t: float
    state: dict[str, Any]
    inputs: tuple[str, str, str]


def next_carry(prev: LogEnd | None, first_t: float | None) -> Carry:
    """The state the next log (first frame at ``first_t``) starts from, after ``prev``."""
    if prev is None:
        return Carry(None, f"fresh: {FRESH_FIRST}")
    if first_t is None:
        return Carry(None, "fresh: the log's first frame is unknown")
    gap_s = first_t - prev.last_t
    if gap_s > MAX_CARRY_GAP_H * 3600.0:
        return Carry(
            None,
            f"fresh: {gap_s / 3600.0:.1f} h since {prev.log_name} ended (more than {MAX_CARRY_GAP_H:g} h: not carried)",
        )
    if gap_s < -OVERLAP_TOLERANCE_S:
        return Carry(None, f"fresh: starts {-gap_s:.1f} s before {prev.log_name} ended (overlapping logs)")
    return Carry(
        prev.state, f"carried from {prev.log_name} ({gap_s / 3600.0:.2f} h between them)", prev.log_hash, prev.inputs
    )


def without_history(state: dict[str, Any]) -> dict[str, Any]:
    """A saved ``Totals`` document without its warning history (the events table holds it)."""
    return {**state, "history": []}
