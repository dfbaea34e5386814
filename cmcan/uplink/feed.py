"""The daemon's hook into the uplink: each tick the monitor evaluates, queue what should leave the machine.

``UplinkFeed`` is one of the monitor's tick listeners (:class:`cmcan.monitor.tick.TickListener`). At
each tick it folds the tick into the summary of its period and turns the warning transitions the
tick recorded (``monitor.totals.history``) into entries, handed to the writer's queue with the
counters of the monitor running now (the daemon's reload swaps the monitor and keeps its listeners).
It never blocks and never raises: a failure is counted and logged with a rate limit.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from cmcan.monitor.baseline import MODE_NAMES, Mode
from cmcan.monitor.prognosis import DIRECTION_CODES, STATE_CODES
from cmcan.monitor.tick import Tick, TickColumns
from cmcan.service.ratelog import RateLimitedLog
from cmcan.uplink.config import UplinkSettings
from cmcan.uplink.records import (
    Cumulative,
    SummaryBuilder,
    TickSample,
    baseline_entry,
    claim_entry,
    clear_entry,
    new_history,
    num,
    transition_entry,
)
from cmcan.uplink.writer import OutboxWriter

log = logging.getLogger("cmcan.uplink.feed")


class UplinkFeed:
    def __init__(self, monitor: Any, writer: OutboxWriter, summary_every_s: float) -> None:
        self.writer = writer
        self.errors = 0
        self.ratelog = RateLimitedLog(logger=log)
        # the monitor running now and the daemon's counters (the daemon attaches its own)
        self.source: Callable[[], tuple[Any, dict[str, int]]] = lambda: (monitor, {})
        history = monitor.totals.history
        self._last_seen = history[-1] if history else None  # transitions before this start are old news
        clears = monitor.totals.dtc_clears
        self._last_clear = clears[-1] if clears else None  # so are DM3/DM11 clears
        self._last_claim: Any = None  # the J1939 claim's events: all of them are news (it starts with the daemon)
        self._baseline_state: str | None = None  # the baseline state of the last tick (None: none yet)
        self.summaries = SummaryBuilder(
            summary_every_s, self._cumulative(monitor, {}), quantity=monitor.params.output_role
        )

    @classmethod
    def open(cls, settings: UplinkSettings, monitor: Any) -> UplinkFeed:
        o = settings.outbox
        writer = OutboxWriter(str(o.path), o.max_bytes, o.max_age_s, o.queue_size).start()
        log.info("uplink outbox %s (summaries every %g s of frame time)", o.path, settings.summary_every_s)
        return cls(monitor, writer, settings.summary_every_s)

    def attach(self, source: Callable[[], tuple[Any, dict[str, int]]]) -> None:
        """Where the counters come from: the monitor running now and the daemon's own counters."""
        self.source = source

    def tick(self, tick: Tick) -> None:
        """Queue new transitions and fold the tick into its period's summary."""
        try:
            monitor, stats = self.source()
            sample = _sample(tick)
            entries = self.summaries.add(sample, self._cumulative(monitor, stats))
            new = new_history(monitor.totals.history, self._last_seen)
            if new:
                self._last_seen = new[-1]
                tot = monitor.totals
                for h in new:
                    leak = sample.extra_leak_lpm if h["t_s"] == sample.t_s else None
                    entries.append(transition_entry(h, tot.warning_count, tot.fault_count, leak))
            entries += self._node_entries(monitor)
            b = sample.baseline
            if b is not None and b["state"] != self._baseline_state:
                if self._baseline_state is not None:  # a change, not the daemon's first tick
                    entries.append(baseline_entry(sample.t_s, self._baseline_state, b))
                self._baseline_state = b["state"]
            for e in entries:
                self.writer.submit(e)
        except Exception:  # the uplink must never take the daemon down
            self.errors += 1
            self.ratelog(logging.ERROR, "uplink-feed", "uplink: cannot build an outbox entry", exc_info=True)

    def _node_entries(self, monitor: Any) -> list[Any]:
        """DM3/DM11 clears and address-claim changes since the last tick, as events."""
        out = []
        new = new_history(monitor.totals.dtc_clears, self._last_clear)
        if new:
            self._last_clear = new[-1]
            out += [clear_entry(c) for c in new]
        node = getattr(monitor, "node", None)
        claim = node.claim if node is not None else None
        if claim is not None:
            new = new_history(claim.events, self._last_claim)
            if new:
                self._last_claim = new[-1]
                out += [claim_entry(e, claim.name_value) for e in new]
        return out

    def ticks(self, chunk: TickColumns) -> None:
        for i in range(len(chunk)):
            self.tick(chunk.tick(i))

    def close(self) -> None:
        """At shutdown: the current period's summary so far, then write out the queue."""
        try:
            monitor, stats = self.source()
            for e in self.summaries.close(self._cumulative(monitor, stats)):
                self.writer.submit(e)
        except Exception:
            log.exception("uplink: cannot write the last summary")
        self.writer.close()

    def _cumulative(self, monitor: Any, stats: dict[str, int]) -> Cumulative:
        tot = monitor.totals
        counters = dict(monitor.counters)
        counters.update(stats)
        counters.update(self.writer.stats.as_counters())
        counters["uplink_feed_errors"] = self.errors
        return Cumulative(dict(tot.time_in_level_s), tot.evaluated_s, tot.warning_count, tot.fault_count, counters)


# Enum member -> lower-case name, one table per enum: Enum.name is slow on a 10 Hz path, and IntEnum
# members of different enums with the same value are equal (Gate.NO_INPUT == Level.LOW == 1).
_GATES: dict[Any, str] = {}
_LEVELS: dict[Any, str] = {}
_REASONS: dict[Any, str] = {}


def _name(table: dict[Any, str], member: Any) -> str:
    name = table.get(member)
    if name is None:
        name = table[member] = member.name.lower()
    return name


def _sample(tick: Any) -> TickSample:
    gate = _name(_GATES, tick.gate)
    return TickSample(
        t_s=tick.t_s,
        gate=gate,
        level=_name(_LEVELS, tick.level),
        reason=_name(_REASONS, tick.reason),
        ratio_raw_pct=tick.ratio_raw_pct if gate in ("evaluating", "extrapolated") else None,
        ratio_filt_pct=tick.ratio_filt_pct if tick.filt_valid else None,
        extra_leak_lpm=tick.extra_leak_lpm if tick.filt_valid else None,
        measured=tick.measured,
        predicted=tick.predicted,
        whitebox=tick.whitebox,
        baseline=_baseline(tick),
        prognosis=_prognosis(tick),
    )


_PROGNOSIS_STATES = {v: k for k, v in STATE_CODES.items()}
_PROGNOSIS_DIRECTIONS = {v: k for k, v in DIRECTION_CODES.items()}


def _prognosis(tick: Any) -> dict[str, Any] | None:
    """The tick's prognosis for JSON: hours rounded, None without an estimate, "never" past any."""
    if not tick.prognosis_state:
        return None

    def hours(v: float) -> float | str | None:
        return "never" if math.isinf(v) else num(v, 2)

    return {
        "state": _PROGNOSIS_STATES.get(tick.prognosis_state, str(tick.prognosis_state)),
        "direction": _PROGNOSIS_DIRECTIONS.get(tick.prognosis_direction) or None,
        "to_warning_h": hours(tick.prognosis_to_warning_h),
        "to_eol_h": [hours(getattr(tick, f"prognosis_to_eol_{q}_h")) for q in ("p10", "p50", "p90")],
    }


def _baseline(tick: Any) -> dict[str, Any] | None:
    if not tick.baseline_state:
        return None
    return {
        "state": MODE_NAMES[Mode(tick.baseline_state)],
        "learned_h": num(tick.baseline_learned_h, 4),
        "coverage_pct": num(tick.baseline_coverage_pct, 2),
        "distance_lpm": num(tick.baseline_distance_lpm, 4),
    }
