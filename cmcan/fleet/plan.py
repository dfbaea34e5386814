"""``cmcan fleet plan``: the service plan, one ranked row per machine.

What the data set says of each machine at the plan's time (:func:`facts`, one query) and the plan
made of it (:func:`plan`, pure): its warning level, its baseline's and its prognosis's state, the
operating hours to its warning and to its end of life (p10, p50, p90), a calendar date for each from
the machine's own utilisation, what end of life means for it, and flags. The ranking is one rule,
:data:`GROUPS` then the hours: a machine that warns now comes first whatever its prognosis says.

Hours are operating hours (the prognosis counts them, docs/prognosis.md); dates turn them into
calendar days with the machine's utilisation, its operating hours per calendar day over its last
:data:`UTILISATION_DAYS` days heard (at least one day). A machine that changes its duty moves its
dates by as much: the hours hold, the dates follow the utilisation.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from cmcan.fitcheck import DOES_NOT_FIT
from cmcan.monitor.baseline import MODE_NAMES, Mode
from cmcan.monitor.prognosis import DIRECTION_CODES, IMMINENT, NONE, STATE_CODES, TREND

# The ranking's groups, most urgent first: a warning now; the prognosis imminent; a trend; a machine
# whose ratio cannot be judged (its baseline suspect, its configuration or model not fitting, left out
# of its type model by fleet train, its sensors at fault); its baseline still learning; no trend; no
# prognosis configured.
GROUPS = ("warning_now", "imminent", "trend", "cannot_judge", "learning", "no_trend", "no_prognosis")
WARNING_LEVELS = ("low", "high")
UTILISATION_DAYS = 14.0  # the recent days the utilisation is taken over
STALE_DAYS = 7.0  # a machine not heard for longer is flagged: its row is that old
NOT_CONFIGURED = "not_configured"
LOGS, UPLINK = "logs", "uplink"  # the two sources of a machine's state
_STATE_NAMES = {code: name for name, code in STATE_CODES.items()}
_DIRECTION_NAMES = {code: name for name, code in DIRECTION_CODES.items() if name}
_BASELINE_NAMES = {int(m): name for m, name in MODE_NAMES.items()}


@dataclass(frozen=True)
class Facts:
    """A machine as the data set has it at the plan's time: its latest row's states and hours (NaN:
    none), its latest evaluated row's ratio, when it was last heard, its operating hours, those of its
    recent days."""

    machine: str
    last_heard_s: float
    operating_h: float
    level: str  # ok, low, high, fault at its latest row
    ratio_filt_pct: float = math.nan
    baseline_state: int = 0  # 0: no on-board baseline configured, else its Mode
    prognosis_state: int = 0  # 0: no prognosis configured, else STATE_CODES
    direction: int = 0
    to_warning_h: float = math.nan
    to_eol_h: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    recent_h: float = 0.0  # operating hours over its recent days
    recent_days: float = 1.0  # those days (at least one)
    fit: str = "unknown"
    end_of_life: str | None = None
    type_verdict: str | None = None  # why fleet train left it out of its type model (its latest log's)
    source: str = LOGS  # where its latest state came from: its logs, or its gateway's uplink


@dataclass(frozen=True)
class Row:
    machine: str
    rank: int
    group: str
    warning_level: str
    baseline_state: str
    prognosis_state: str
    direction: str | None
    to_warning_h: float | None
    to_eol_h: list[float | None]
    due_date: list[str | None]
    warning_date: str | None
    utilisation_h_per_day: float | None
    operating_h: float
    ratio_filt_pct: float | None
    last_heard: str
    last_heard_days: float
    end_of_life: str | None
    flags: list[str] = field(default_factory=list)
    source: str = LOGS
    type_verdict: str | None = None  # fleet train's words where it left the machine out (left_out_of_type)

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _hours(x: float) -> float | None:
    """An hour for the plan: None where there is none (NaN); inf (never gets there) stays."""
    return None if math.isnan(x) else float(x)


def _date(from_s: float, hours: float | None, per_day: float | None) -> str | None:
    if hours is None or per_day is None or per_day <= 0 or math.isinf(hours):
        return None
    t = from_s + hours / per_day * 86400.0
    try:
        return dt.datetime.fromtimestamp(t, dt.UTC).date().isoformat()
    except (OverflowError, OSError, ValueError):  # beyond the calendar's years: no date
        return None


def group_of(f: Facts) -> str:
    """The ranking's group of a machine (one rule: the first that holds)."""
    if f.level in WARNING_LEVELS:
        return "warning_now"
    state = _STATE_NAMES.get(f.prognosis_state)
    if state == IMMINENT:
        return "imminent"
    if state == TREND and not math.isnan(f.to_eol_h[1]):
        return "trend"
    if f.baseline_state == Mode.SUSPECT or f.fit == DOES_NOT_FIT or f.type_verdict or f.level == "fault":
        return "cannot_judge"
    if f.baseline_state == Mode.LEARNING:
        return "learning"
    if f.prognosis_state == 0:
        return "no_prognosis"
    return "no_trend"


def flags_of(f: Facts, now_s: float) -> list[str]:
    out = []
    if f.fit == DOES_NOT_FIT:
        out.append("does_not_fit")
    if f.baseline_state == Mode.SUSPECT:
        out.append("baseline_suspect")
    if f.type_verdict:
        out.append("left_out_of_type")
    if f.baseline_state == Mode.LEARNING:
        out.append("learning")
    if f.level == "fault":
        out.append("sensor_fault")
    if f.level in WARNING_LEVELS and _STATE_NAMES.get(f.prognosis_state) == NONE:
        out.append("warning_without_trend")  # the prognosis has no trend yet: the warning is the news
    if any(math.isinf(h) for h in f.to_eol_h):
        out.append("eol_not_reached")  # a quantile's curve never gets there (null in JSON, "never" in the table)
    if f.recent_h <= 0:
        out.append("no_utilisation")
    if (now_s - f.last_heard_s) / 86400.0 > STALE_DAYS:
        out.append("stale")
    return out


def plan(machines: Sequence[Facts], now_s: float) -> list[Row]:
    """The service plan at ``now_s`` (epoch s): the machines ranked by :data:`GROUPS`, then by p10
    and p50 to end of life (none last), then by name."""

    def key(f: Facts) -> tuple[int, float, float, str]:
        p10, p50 = (math.inf if math.isnan(x) else x for x in f.to_eol_h[:2])
        return GROUPS.index(group_of(f)), p10, p50, f.machine

    rows = []
    for rank, f in enumerate(sorted(machines, key=key), start=1):
        per_day = f.recent_h / max(f.recent_days, 1.0) if f.recent_h > 0 else None
        eol = [_hours(x) for x in f.to_eol_h]
        warns_now = f.level in WARNING_LEVELS
        to_warning = 0.0 if warns_now else _hours(f.to_warning_h)
        rows.append(
            Row(
                machine=f.machine,
                rank=rank,
                group=group_of(f),
                warning_level=f.level,
                baseline_state=_BASELINE_NAMES.get(f.baseline_state, NOT_CONFIGURED),
                prognosis_state=_STATE_NAMES.get(f.prognosis_state, NOT_CONFIGURED),
                direction=_DIRECTION_NAMES.get(f.direction),
                to_warning_h=to_warning,
                to_eol_h=eol,
                due_date=[_date(f.last_heard_s, h, per_day) for h in eol],
                warning_date=_date(f.last_heard_s, to_warning, per_day),
                utilisation_h_per_day=None if per_day is None else round(per_day, 3),
                operating_h=round(f.operating_h, 3),
                ratio_filt_pct=_hours(f.ratio_filt_pct),
                last_heard=dt.datetime.fromtimestamp(f.last_heard_s, dt.UTC).isoformat(timespec="seconds"),
                last_heard_days=round((now_s - f.last_heard_s) / 86400.0, 2),
                end_of_life=f.end_of_life,
                flags=flags_of(f, now_s),
                source=f.source,
                type_verdict=f.type_verdict,
            )
        )
    return rows


# -- what the data set says ------------------------------------------------------------------------

_ROWS = """
    SELECT t.machine, t.time_s, ml.offset_h + t.log_time_h AS op_h, t.evaluated, t.warning_level,
           t.cm_ratio_filt_pct AS filt, coalesce(t.baseline_state, 0) AS baseline_state,
           coalesce(t.prognosis_state, 0) AS prognosis_state, coalesce(t.prognosis_direction, 0) AS direction,
           t.prognosis_to_warning_h AS to_warning, t.prognosis_to_eol_p10_h AS p10,
           t.prognosis_to_eol_p50_h AS p50, t.prognosis_to_eol_p90_h AS p90
    FROM timeline t JOIN machine_logs ml ON t.machine = ml.machine AND t.log_hash = ml.log_hash
    WHERE t.time_s <= ?"""


def facts(con: Any, at_s: float) -> list[Facts]:
    """Every machine heard up to ``at_s`` (epoch s) as :class:`Facts`, from its logs and from its
    gateway's uplink: a machine known from both once, from the source heard last (:func:`merge`)."""
    return merge(log_facts(con, at_s), uplink_facts(con, at_s))


def merge(from_logs: Sequence[Facts], from_uplink: Sequence[Facts]) -> list[Facts]:
    """One :class:`Facts` per machine: the one heard last (the logs on a tie); a machine's uplink
    state keeps what only its logs know (the fit check, what end of life means, fleet train's verdict)."""
    out = {f.machine: f for f in from_logs}
    for u in from_uplink:
        f = out.get(u.machine)
        if f is None:
            out[u.machine] = u
        elif u.last_heard_s > f.last_heard_s:
            out[u.machine] = dataclasses.replace(u, fit=f.fit, end_of_life=f.end_of_life, type_verdict=f.type_verdict)
    return [out[m] for m in sorted(out)]


_BASELINE_CODES = {name: int(mode) for mode, name in MODE_NAMES.items()}


def uplink_facts(con: Any, at_s: float) -> list[Facts]:
    """Every machine with a summary up to ``at_s`` in the uplink's rows: its latest summary's states
    and hours, its level at its latest summary or level change (whichever is later), its operating
    hours as the monitor counts them (time in any level since commissioning)."""
    rows = con.execute(
        f"""
        WITH s AS (SELECT * FROM uplink_summaries WHERE time_s <= ?),
        lv AS (SELECT machine, time_s, level FROM s
               UNION ALL SELECT machine, time_s, to_level FROM uplink_events
               WHERE type = 'level_change' AND to_level IS NOT NULL AND time_s <= ?),
        heard AS (SELECT machine, max(time_s) AS last_s, arg_max(level, time_s) AS level FROM lv GROUP BY machine),
        latest AS (SELECT machine, arg_max({{'filt': ratio_filt_pct, 'base': baseline_state,
                          'state': prognosis_state, 'dir': prognosis_direction, 'warn': prognosis_to_warning_h,
                          'p10': prognosis_to_eol_p10_h, 'p50': prognosis_to_eol_p50_h,
                          'p90': prognosis_to_eol_p90_h, 'op': operating_total_h}}, time_s) AS v,
                          max(time_s) AS last_s
                   FROM s GROUP BY machine),
        recent AS (SELECT s.machine, max(s.operating_total_h) - min(s.operating_total_h) AS recent_h,
                          (max(s.time_s) - min(s.time_s)) / 86400.0 AS recent_days
                   FROM s JOIN latest USING (machine)
                   WHERE s.time_s >= latest.last_s - {UTILISATION_DAYS * 86400.0} GROUP BY s.machine)
        SELECT latest.machine, heard.last_s, heard.level, latest.v, recent.recent_h, recent.recent_days
        FROM latest JOIN heard USING (machine) LEFT JOIN recent USING (machine)
        ORDER BY latest.machine""",
        [at_s, at_s],
    ).fetchall()
    out = []
    for machine, last_s, level, v, recent_h, recent_days in rows:
        out.append(
            Facts(
                machine=machine,
                last_heard_s=float(last_s),
                operating_h=_num(v["op"]),
                level=str(level or "ok"),
                ratio_filt_pct=_num(v["filt"]),
                baseline_state=_BASELINE_CODES.get(v["base"], 0),
                prognosis_state=STATE_CODES.get(v["state"], 0),
                direction=DIRECTION_CODES.get(v["dir"] or "", 0),
                to_warning_h=_num(v["warn"]),
                to_eol_h=(_num(v["p10"]), _num(v["p50"]), _num(v["p90"])),
                recent_h=max(_num(recent_h), 0.0) if recent_h is not None else 0.0,
                recent_days=max(_num(recent_days), 1.0) if recent_days is not None else 1.0,
                source=UPLINK,
            )
        )
    return out


def log_facts(con: Any, at_s: float) -> list[Facts]:
    """Every machine heard up to ``at_s`` (epoch s) in its logs as :class:`Facts` (one query over the
    data set's views; the states, hours and level of its latest row, the ratio of its latest evaluated
    row: the prognosis estimates on its operating clock, at a row the gate passed or not)."""
    rows = con.execute(
        f"""
        WITH r AS ({_ROWS}),
        heard AS (SELECT machine, max(time_s) AS last_s, min(time_s) AS first_s, max(op_h) AS op_h,
                         arg_max(warning_level, time_s) AS level
                  FROM r GROUP BY machine),
        ev AS (SELECT machine, arg_max(filt, time_s) AS filt FROM r WHERE evaluated > 0 GROUP BY machine),
        st AS (SELECT machine, arg_max([baseline_state::DOUBLE, prognosis_state::DOUBLE, direction::DOUBLE,
                                        to_warning, p10, p50, p90], time_s) AS v
               FROM r GROUP BY machine),
        recent AS (SELECT r.machine, max(r.op_h) - min(r.op_h) AS recent_h,
                          (max(r.time_s) - min(r.time_s)) / 86400.0 AS recent_days
                   FROM r JOIN heard USING (machine)
                   WHERE r.time_s >= heard.last_s - {UTILISATION_DAYS * 86400.0} GROUP BY r.machine),
        eol AS (SELECT machine, arg_max(end_of_life, first_time_s) AS end_of_life,
                       arg_max(type_verdict, first_time_s) AS type_verdict
                FROM logs WHERE first_time_s <= ? GROUP BY machine)
        SELECT heard.machine, heard.last_s, heard.op_h, heard.level, ev.filt, st.v, recent.recent_h,
               recent.recent_days, mf.fit, eol.end_of_life, eol.type_verdict
        FROM heard LEFT JOIN ev USING (machine) LEFT JOIN st USING (machine) LEFT JOIN recent USING (machine)
             LEFT JOIN machines mf USING (machine) LEFT JOIN eol USING (machine)
        ORDER BY heard.machine""",
        [at_s, at_s],
    ).fetchall()
    out = []
    for machine, last_s, op_h, level, filt, v, recent_h, recent_days, fit, eol, verdict in rows:
        base, state, direction, to_warning, p10, p50, p90 = (
            (_num(x) for x in v) if v else (0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        )
        out.append(
            Facts(
                machine=machine,
                last_heard_s=float(last_s),
                operating_h=_num(op_h),
                level=str(level or "ok"),
                ratio_filt_pct=_num(filt),
                baseline_state=int(base),
                prognosis_state=int(state),
                direction=int(direction),
                to_warning_h=to_warning,
                to_eol_h=(p10, p50, p90),
                recent_h=max(_num(recent_h), 0.0) if recent_h is not None else 0.0,
                recent_days=max(_num(recent_days), 1.0) if recent_days is not None else 1.0,
                fit=fit or "unknown",
                end_of_life=eol,
                type_verdict=verdict,
            )
        )
    return out


def _num(x: Any) -> float:
    return math.nan if x is None else float(x)


def build(root: Any, at_s: float | None, now_s: float) -> list[Row]:
    """The plan over the data set at ``root`` as of ``at_s`` (None: everything in it), its ages
    counted to ``now_s`` (the plan's time: ``at_s`` where given)."""
    from cmcan.fleet.query import read

    tables = {"timeline", "uplink_summaries", "uplink_events"}
    return read(root, lambda con: plan(facts(con, math.inf if at_s is None else at_s), now_s), tables)


def group_text(group: str) -> str:
    """A group's name as the table and the report print it."""
    return group.replace("_", " ")


def hours_text(x: float | None, fmt: str = "{:.0f}", none: str = "-") -> str:
    """An hour of the plan as text: ``none`` where there is none, "never" where it never gets there."""
    if x is None:
        return none
    return "never" if math.isinf(x) else fmt.format(x)


def meanings(rows: Sequence[Row]) -> dict[str, list[str]]:
    """What end of life means, and for which machines (machines configured alike share a line)."""
    out: dict[str, list[str]] = {}
    for r in rows:
        if r.end_of_life:
            out.setdefault(r.end_of_life, []).append(r.machine)
    return out


def totals(rows: Sequence[Row]) -> str:
    """The machines per group in one line."""
    counts = {g: sum(1 for r in rows if r.group == g) for g in GROUPS}
    return f"{len(rows)} machines: " + ", ".join(f"{n} {group_text(g)}" for g, n in counts.items() if n)


def format_table(rows: Sequence[Row]) -> str:
    """The plan as a text table, its totals per group and what end of life means for whom."""
    head = ("#", "machine", "group", "level", "baseline", "prognosis", "to warn h", "EOL h p10/p50/p90",
            "due p10 / p50", "h/day", "last heard", "flags")  # fmt: skip
    body = [
        (
            str(r.rank),
            r.machine,
            r.group,  # one word a column: the table stays easy to cut and grep
            r.warning_level,
            r.baseline_state,
            r.prognosis_state + (f" ({r.direction})" if r.direction else ""),
            hours_text(r.to_warning_h),
            "/".join(hours_text(h) for h in r.to_eol_h),
            " / ".join(d or "-" for d in r.due_date[:2]),
            hours_text(r.utilisation_h_per_day, "{:.1f}"),
            f"{r.last_heard[:10]} ({r.last_heard_days:.0f} d{', uplink' if r.source == UPLINK else ''})",
            ",".join(r.flags) or "-",
        )
        for r in rows
    ]
    widths = [max(len(c) for c in col) for col in zip(head, *body, strict=True)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(line, widths, strict=True)).rstrip() for line in (head, *body)]
    lines.append("")
    lines.append(totals(rows))
    for text, names in meanings(rows).items():
        lines.append(f"end of life for {', '.join(names)}: {text}")
    return "\n".join(lines) + "\n"
