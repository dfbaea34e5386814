"""``cmcan fleet report``: one self-contained HTML page over the data set (no script, no link out).

The page opens with the service plan, the one ranking of the fleet: :mod:`cmcan.fleet.plan`'s rows
as ``cmcan fleet plan`` prints them (warning now, imminent, trend by p10 then p50, cannot judge,
learning, no trend, no prognosis), each with its hours and dates to the warning and to end of life,
the machine's utilisation, flags, and a small chart with numbered axes of its estimates over its
operating hours (the p50 in its p10-p90 band); what end of life means for whom follows the table.
The fleet overview draws every machine's ratio and gives each machine's ratio statistics, in the
plan's order. Each machine then gets its CM ratio over its operating hours with the thresholds that
judged each stretch (the learning band while the on-board baseline learned, the configured ones
otherwise), its warnings, and under it the prognosis's band where it had estimates (the figures are
PNG inlined as base64); the quarantine list closes the page; a data set whose every log was
quarantined still gets its page, with that list. A machine's operating hours are its logged hours:
its logs in time order, each one's duration added (``machine_logs.offset_h``).
"""

from __future__ import annotations

import base64
import html
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cmcan import __version__
from cmcan.errors import CmcanError, Kind
from cmcan.fitcheck import DOES_NOT_FIT, FIT_BAND_PCT
from cmcan.fleet import plan as service
from cmcan.fleet.dataset import writing
from cmcan.fleet.query import read, require_duckdb
from cmcan.monitor.baseline import Mode
from cmcan.monitor.prognosis import IMMINENT, STATE_CODES, TREND
from cmcan.monitor.tick import PROGNOSIS_HOURS

ATTENTION = {4: "configuration or model does not fit", 3: "warning now", 2: "had warnings", 1: "faults", 0: "ok"}
MAX_POINTS_PER_MACHINE = 1500
SPARK_POINTS = 120  # estimates per sparkline: one per bin of a machine's span of estimates
# the end-of-life hours among the prognosis's columns, in the order p10, p50, p90
P10_H, P50_H, P90_H = (c for c in PROGNOSIS_HOURS if "_to_eol_" in c)


@dataclass
class MachineRow:
    machine: str
    logs: int
    hours: float
    evaluated_h: float
    warnings_low: int
    warnings_high: int
    faults: int
    first_day: Any
    last_day: Any
    level_now: str
    ratio_now: float | None
    trend_pct_per_100h: float | None
    first_warning_h: float | None
    low_pct: float
    high_pct: float
    fit: str = "unknown"
    fit_median_pct: float | None = None
    fit_log: str | None = None
    learning_low_pct: float | None = None  # the learning band where the machine's baseline learned
    learning_high_pct: float | None = None

    @property
    def misfit(self) -> bool:
        return self.fit == DOES_NOT_FIT

    @property
    def attention(self) -> int:
        if self.misfit:
            return 4
        if self.level_now in ("low", "high"):
            return 3
        if self.warnings_low + self.warnings_high > 0:
            return 2
        if self.faults > 0 or self.level_now == "fault":
            return 1
        return 0

    @property
    def state(self) -> str:
        if self.misfit:
            return "misfit"
        if self.level_now in ("low", "high", "fault"):
            return self.level_now
        if self.warnings_low + self.warnings_high > 0:
            return "low" if self.warnings_low >= self.warnings_high else "high"
        return "fault" if self.faults else "ok"


def _f(x: Any) -> float | None:
    if x is None:
        return None
    x = float(x)
    return None if math.isnan(x) else x


_TIMELINE = f"""
    SELECT t.machine, ml.offset_h + t.log_time_h AS op_h, t.cm_ratio_raw_pct AS raw, t.cm_ratio_filt_pct AS filt,
           coalesce(t.baseline_state, 0) = {int(Mode.LEARNING)} AS learning
    FROM timeline t JOIN machine_logs ml ON t.machine = ml.machine AND t.log_hash = ml.log_hash
    WHERE t.evaluated > 0"""


def machines(con: Any, trend_h: float) -> list[MachineRow]:
    rows = con.execute(
        f"""
        WITH tl AS ({_TIMELINE}),
        span AS (SELECT machine, max(op_h) AS end_h FROM tl GROUP BY machine),
        trend AS (
            SELECT tl.machine, regr_slope(raw, op_h) * 100 AS trend,
                   arg_max(filt, op_h) FILTER (WHERE filt IS NOT NULL AND NOT isnan(filt)) AS recent
            FROM tl JOIN span USING (machine) WHERE op_h >= end_h - ? GROUP BY tl.machine),
        warn AS (
            SELECT e.machine, min(ml.offset_h + e.log_time_h) AS first_h
            FROM events e JOIN machine_logs ml ON e.machine = ml.machine AND e.log_hash = ml.log_hash
            WHERE e.to_level IN ('low', 'high') GROUP BY e.machine),
        agg AS (
            SELECT machine, count(*) AS logs, sum(duration_h) AS hours, sum(evaluated_h) AS evaluated_h,
                   sum(warnings_low) AS wl, sum(warnings_high) AS wh, sum(faults) AS faults,
                   min(day) AS first_day, max(day) AS last_day,
                   arg_max(final_level, first_time_s) AS level_now,
                   max(threshold_low_pct) AS low_pct, min(threshold_high_pct) AS high_pct,
                   min(learning_low_pct) AS learn_low, max(learning_high_pct) AS learn_high
            FROM machine_logs GROUP BY machine)
        SELECT agg.machine, logs, hours, evaluated_h, wl, wh, faults, first_day, last_day, level_now,
               trend.recent, trend.trend, warn.first_h, low_pct, high_pct, mf.fit, mf.fit_median_pct, mf.fit_log,
               learn_low, learn_high
        FROM agg LEFT JOIN trend USING (machine) LEFT JOIN warn USING (machine) LEFT JOIN machines mf USING (machine)
        """,
        [trend_h],
    ).fetchall()
    out = [
        MachineRow(
            r[0],
            int(r[1]),
            float(r[2]),
            float(r[3]),
            int(r[4]),
            int(r[5]),
            int(r[6]),
            r[7],
            r[8],
            r[9],
            _f(r[10]),
            _f(r[11]),
            _f(r[12]),
            float(r[13]),
            float(r[14]),
            r[15] or "unknown",
            _f(r[16]),
            r[17],
            _f(r[18]),
            _f(r[19]),
        )
        for r in rows
    ]
    return sorted(out, key=lambda m: m.machine)


def series(con: Any, width_h: float) -> dict[str, tuple[list[float], list[float], list[float], list[bool]]]:
    """Per machine: operating hour, raw and filtered ratio (means over bins of ``width_h``) and
    whether its baseline was learning in the bin (the learning band judged it)."""
    rows = con.execute(
        f"""
        WITH tl AS ({_TIMELINE})
        SELECT machine, avg(op_h), avg(raw), avg(filt), bool_or(learning) FROM tl
        GROUP BY machine, floor(op_h / ?) ORDER BY machine, 2""",
        [width_h],
    ).fetchall()
    out: dict[str, tuple[list[float], list[float], list[float], list[bool]]] = {}
    for m, h, raw, filt, learning in rows:
        s = out.setdefault(m, ([], [], [], []))
        s[0].append(h)
        s[1].append(raw if raw is not None else math.nan)
        s[2].append(filt if filt is not None else math.nan)
        s[3].append(bool(learning))
    return out


def events(con: Any) -> dict[str, list[tuple[float, str]]]:
    rows = con.execute(
        """SELECT e.machine, ml.offset_h + e.log_time_h, e.to_level
           FROM events e JOIN machine_logs ml ON e.machine = ml.machine AND e.log_hash = ml.log_hash
           WHERE e.to_level <> 'ok' ORDER BY 1, 2"""
    ).fetchall()
    out: dict[str, list[tuple[float, str]]] = {}
    for m, h, level in rows:
        out.setdefault(m, []).append((float(h), level))
    return out


_PROGNOSIS_TIMELINE = f"""
    SELECT t.machine, ml.offset_h + t.log_time_h AS op_h, coalesce(t.prognosis_state, 0) AS state,
           t.{P10_H} AS p10, t.{P50_H} AS p50, t.{P90_H} AS p90
    FROM timeline t JOIN machine_logs ml ON t.machine = ml.machine AND t.log_hash = ml.log_hash
    WHERE t.evaluated > 0"""
# a row with an estimate: a trend and a p50 (NaN: no estimate; inf: never gets there, kept)
_ESTIMATE = f"state IN ({STATE_CODES[TREND]}, {STATE_CODES[IMMINENT]}) AND p50 IS NOT NULL AND NOT isnan(p50)"


def service_series(con: Any) -> dict[str, tuple[list[float], list[float], list[float], list[float]]]:
    """Per machine with estimates: operating hour, p10, p50, p90 of the latest estimate in each of
    ``SPARK_POINTS`` bins over its span of estimates."""
    rows = con.execute(
        f"""
        WITH tl AS ({_PROGNOSIS_TIMELINE}),
        est AS (SELECT * FROM tl WHERE {_ESTIMATE}),
        span AS (SELECT machine, min(op_h) AS h0, greatest(max(op_h) - min(op_h), 1e-6) AS width_h
                 FROM est GROUP BY machine)
        SELECT machine, arg_max([op_h, p10, p50, p90], op_h) AS e FROM est JOIN span USING (machine)
        GROUP BY machine, floor((op_h - h0) / width_h * {SPARK_POINTS})
        ORDER BY machine, e[1]"""
    ).fetchall()
    out: dict[str, tuple[list[float], list[float], list[float], list[float]]] = {}
    for m, values in rows:
        s = out.setdefault(m, ([], [], [], []))
        for column, v in zip(s, values, strict=True):
            column.append(math.nan if v is None else float(v))
    return out


CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:24px;color:#222;max-width:1200px}
h1{font-size:22px;margin-bottom:4px} h2{font-size:18px;margin-top:32px;border-bottom:1px solid #ddd}
h3{font-size:15px;margin:20px 0 4px}
.meta{color:#666;font-size:13px} .cards{display:flex;gap:12px;flex-wrap:wrap;margin:16px 0}
.card{border:1px solid #ddd;border-radius:6px;padding:8px 14px;min-width:110px}
.card b{display:block;font-size:20px} .card span{font-size:12px;color:#666}
table{border-collapse:collapse;font-size:13px;margin:8px 0}
th,td{border-bottom:1px solid #eee;padding:4px 8px;text-align:right} th{background:#f6f6f6}
td.l,th.l{text-align:left} tr.a3 td{background:#fff1e0} tr.a2 td{background:#fffbe8} tr.a1 td{background:#fdeeee}
.tag{border-radius:3px;padding:1px 6px;font-size:12px;color:#fff}
.t-ok{background:#4a9a4a}.t-low{background:#e08a00}.t-high{background:#8a4fbf}.t-fault{background:#c83a3a}
.t-misfit{background:#555} tr.a4 td{background:#eeeeee}
p.misfit{background:#f3f3f3;border-left:4px solid #555;padding:6px 10px}
img{max-width:100%;height:auto;border:1px solid #eee}
.t-trend{background:#e08a00}.t-imminent{background:#c83a3a}.t-none{background:#4a9a4a}
tr.imminent td{background:#fdeeee} td.spark{padding:1px 8px} td.spark img{border:0;display:block}
"""


def _tag(level: str) -> str:
    text = "does not fit" if level == "misfit" else level
    return f'<span class="tag t-{html.escape(level)}">{html.escape(text)}</span>'


def _misfit_note(m: MachineRow) -> str:
    lo, hi = FIT_BAND_PCT
    return (
        f"<p class='misfit'><b>Configuration or model does not fit this machine.</b> Its CM ratio sat at a median of "
        f"{_num(m.fit_median_pct, '{:.1f}')} % from its first hour ({html.escape(m.fit_log or '')}), outside "
        f"{lo:g}-{hi:g} %: a drive of another size (V_M), another model, or a drive already worn when monitoring "
        "began. Its warnings say nothing about wear until the configuration and model are right; it is not ranked "
        "with the worn drives.</p>"
    )


def _num(x: float | None, fmt: str = "{:.2f}") -> str:
    return "&ndash;" if x is None else fmt.format(x)


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


# a row's colour: the plan's groups that need someone now, then those that need a look
GROUP_CLASS = {"warning_now": "a3", "imminent": "a3", "trend": "a2", "cannot_judge": "a4"}


def _date_span(dates: list[str | None]) -> str:
    return " / ".join(html.escape(d) if d else "&ndash;" for d in dates)


def plan_section(rows: list[service.Row], spark: dict[str, bytes]) -> list[str]:
    """The service plan's HTML parts: :mod:`cmcan.fleet.plan`'s rows, one ranking (``spark``: the
    small chart of each machine with estimates)."""
    parts = ["<h2 id='service'>Service plan</h2>"]
    if not rows:
        return [*parts, "<p>No machine has an evaluated row in this data set.</p>"]
    parts.append(
        "<p class='meta'>The same plan as <code>cmcan fleet plan</code>: warning now, imminent, trend (by the "
        "p10, then the p50 of the operating hours to end of life), cannot judge, learning, no trend, no "
        "prognosis; each machine at its latest evaluated row. Dates count the hours at the machine's own "
        f"utilisation (operating hours per calendar day over its last {service.UTILISATION_DAYS:g} days). "
        "The chart: the hours to end of life over the machine's operating hours, p50 in its p10-p90 band "
        "(the truth is not known in the field).</p>"
        "<table id='ranking'><tr><th>#</th><th class='l'>machine</th><th class='l'>group</th>"
        "<th class='l'>level</th><th class='l'>baseline</th><th class='l'>prognosis</th>"
        "<th>to warning (h)</th><th>to end of life p10 / p50 / p90 (h)</th><th class='l'>due p10 / p50 / p90</th>"
        "<th>h/day</th><th class='l'>last heard</th><th class='l'>flags</th><th class='l'>estimates</th></tr>"
    )
    for r in rows:
        name = html.escape(r.machine)
        prognosis = html.escape(r.prognosis_state.replace("_", " ") + (f" ({r.direction})" if r.direction else ""))
        warn = service.hours_text(r.to_warning_h, "{:.0f}", "&ndash;")
        if r.warning_date and r.to_warning_h:
            warn += f"<br><span class='meta'>{html.escape(r.warning_date)}</span>"
        alt = f"{r.machine}: hours to end of life, p50 in its p10-p90 band, over operating hours"
        chart = _img(spark[r.machine], alt) if r.machine in spark else ""
        parts.append(
            f"<tr class='{GROUP_CLASS.get(r.group, 'a0')} g-{r.group}'><td>{r.rank}</td>"
            f"<td class='l'><a href='#m-{name}'>{name}</a></td><td class='l'>{service.group_text(r.group)}</td>"
            f"<td class='l'>{_tag(r.warning_level)}</td>"
            f"<td class='l'>{html.escape(r.baseline_state.replace('_', ' '))}</td>"
            f"<td class='l'>{prognosis}</td><td>{warn}</td>"
            f"<td>{' / '.join(service.hours_text(h, '{:.0f}', '&ndash;') for h in r.to_eol_h)}</td>"
            f"<td class='l'>{_date_span(r.due_date)}</td>"
            f"<td>{service.hours_text(r.utilisation_h_per_day, '{:.1f}', '&ndash;')}</td>"
            f"<td class='l'>{html.escape(r.last_heard[:10])} ({r.last_heard_days:.0f} d"
            f"{', uplink' if r.source == service.UPLINK else ''})</td>"
            f"<td class='l'>{html.escape(', '.join(f.replace('_', ' ') for f in r.flags)) or '&ndash;'}</td>"
            f"<td class='l spark'>{chart}</td></tr>"
        )
    parts.append("</table>")
    parts.append(f"<p id='plan-totals'>{html.escape(service.totals(rows))}.</p>")
    meaning = service.meanings(rows)
    if all(r.prognosis_state == service.NOT_CONFIGURED for r in rows):
        parts.append(
            "<p id='service-none'>No machine in this data set has a prognosis configured "
            "(<code>prognosis: enabled</code> in its configuration, docs/prognosis.md): no hours to end of life.</p>"
        )
    for text, names in meaning.items():
        parts.append(f"<p class='eol'>End of life for {html.escape(', '.join(names))}: {html.escape(text)}.</p>")
    return parts


def build(root: str | Path, trend_h: float = 50.0, max_machines: int = 50) -> str:
    """The report's HTML."""
    return read(root, lambda con: _build(con, root, trend_h, max_machines))


def _build(con: Any, root: str | Path, trend_h: float, max_machines: int) -> str:
    from cmcan.fleet.figures import plot_machine, plot_overview, plot_service_spark

    plan_rows = service.plan(service.facts(con, math.inf), time.time())
    rank = {r.machine: r.rank for r in plan_rows}
    ms = sorted(machines(con, trend_h), key=lambda m: (rank.get(m.machine, len(rank) + 1), m.machine))
    total_h = max((m.hours for m in ms), default=1.0)
    ser = series(con, max(total_h / MAX_POINTS_PER_MACHINE, 1.0 / 3600.0))
    evs = events(con)
    starts = {
        m: [
            float(h)
            for (h,) in con.execute(
                "SELECT offset_h FROM machine_logs WHERE machine = ? ORDER BY offset_h", [m]
            ).fetchall()
        ]
        for m in ser
    }
    quarantine = con.execute(
        "SELECT machine, log, stage, reason, quarantined_at FROM quarantine ORDER BY machine, log"
    ).fetchall()
    tot = con.execute(
        "SELECT count(*), coalesce(sum(duration_h), 0), coalesce(sum(evaluated_h), 0), "
        "coalesce(sum(count_frames_total), 0), string_agg(DISTINCT cmcan_version, ', ') FROM logs"
    ).fetchall()[0]
    low = min((m.low_pct for m in ms), default=98.0)
    high = max((m.high_pct for m in ms), default=102.0)

    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>cmcan fleet report: {html.escape(Path(root).name)}</title><style>{CSS}</style></head><body>",
        "<h1>Fleet condition report</h1>",
        f"<div class='meta'>data set {html.escape(os.path.abspath(root))} &middot; written by cmcan {__version__} "
        f"at {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} &middot; results from cmcan "
        f"{html.escape(tot[4] or '-')}</div>",
        "<div class='cards'>",
    ]
    need = sum(1 for r in plan_rows if r.group in GROUP_CLASS)
    misfits = sum(1 for m in ms if m.misfit)
    for value, label in (
        (len(ms), "machines"),
        (need, "need a look"),
        (misfits, "do not fit"),
        (tot[0], "logs"),
        (f"{tot[1]:.0f} h", "logged"),
        (f"{tot[2]:.1f} h", "evaluated"),
        (f"{tot[3] / 1e6:.1f} M", "frames"),
        (len(quarantine), "quarantined"),
    ):
        parts.append(f"<div class='card'><b>{value}</b><span>{label}</span></div>")
    parts.append("</div>")
    traces = service_series(con)  # the query layer gives older data sets these columns, null
    spark = {r.machine: plot_service_spark(*traces[r.machine]) for r in plan_rows if r.machine in traces}
    parts += plan_section(plan_rows, spark)
    if not ms:
        parts.append(
            "<p>No log is committed in this data set"
            + (": every log that was tried is in the quarantine list below.</p>" if quarantine else ".</p>")
        )
    parts.append("<h2 id='overview'>Fleet overview</h2>")
    lines = [(m.machine, *ser.get(m.machine, ([], [], [], []))[:3:2], m.state) for m in ms]
    if ms:
        parts.append(_img(plot_overview(lines, low, high), "filtered CM ratio of every machine"))
    parts.append(
        "<table id='statistics'><tr><th>#</th><th class='l'>machine</th><th class='l'>state</th><th class='l'>now</th>"
        f"<th>trend (%/100 h, last {trend_h:g} h)</th><th>filtered ratio now (%)</th><th>low</th><th>high</th>"
        "<th>faults</th><th>first warning (h)</th><th>logs</th><th>logged (h)</th><th>evaluated (h)</th>"
        "<th class='l'>days</th></tr>"
    )
    for m in ms:
        parts.append(
            f"<tr class='a{m.attention}'><td>{rank.get(m.machine, '&ndash;')}</td><td class='l'>"
            f"<a href='#m-{html.escape(m.machine)}'>{html.escape(m.machine)}</a></td>"
            f"<td class='l'>{ATTENTION[m.attention]}</td>"
            f"<td class='l'>{_tag(m.level_now)}</td><td>{_num(m.trend_pct_per_100h)}</td><td>{_num(m.ratio_now)}</td>"
            f"<td>{m.warnings_low}</td><td>{m.warnings_high}</td><td>{m.faults}</td>"
            f"<td>{_num(m.first_warning_h, '{:.1f}')}</td><td>{m.logs}</td><td>{m.hours:.1f}</td>"
            f"<td>{m.evaluated_h:.2f}</td><td class='l'>{m.first_day} &ndash; {m.last_day}</td></tr>"
        )
    parts.append("</table>")
    parts.append("<h2 id='machines'>Machines</h2>")
    for m in ms[:max_machines]:
        h, raw, filt, learning = ser.get(m.machine, ([], [], [], []))
        title = (
            f"{m.machine}: CM ratio over operating hours ({m.warnings_low} low, {m.warnings_high} high warnings, "
            f"{m.faults} faults)"
        )
        band = None
        if m.learning_low_pct is not None and m.learning_high_pct is not None:
            band = (learning, m.learning_low_pct, m.learning_high_pct)
        parts.append(f"<h3 id='m-{html.escape(m.machine)}'>{html.escape(m.machine)} {_tag(m.state)}</h3>")
        if m.misfit:
            parts.append(_misfit_note(m))
        png = plot_machine(
            h,
            raw,
            filt,
            m.low_pct,
            m.high_pct,
            evs.get(m.machine, []),
            starts.get(m.machine, []),
            title,
            learning=band,
            prognosis=traces.get(m.machine),
        )
        parts.append(_img(png, title))
    if len(ms) > max_machines:
        parts.append(f"<p class='meta'>{len(ms) - max_machines} more machines in the table above (not drawn).</p>")
    parts.append(f"<h2 id='quarantine'>Quarantine ({len(quarantine)})</h2>")
    if quarantine:
        parts.append(
            "<table><tr><th class='l'>machine</th><th class='l'>log</th><th class='l'>stage</th>"
            "<th class='l'>reason</th><th class='l'>when</th></tr>"
        )
        for q in quarantine:
            parts.append("<tr>" + "".join(f"<td class='l'>{html.escape(str(v))}</td>" for v in q) + "</tr>")
        parts.append("</table>")
    else:
        parts.append("<p>No log failed.</p>")
    parts.append("</body></html>\n")
    return "\n".join(parts)


def write_report(root: str | Path, out: Path, trend_h: float = 50.0, max_machines: int = 50) -> int:
    duckdb = require_duckdb()
    try:
        text = build(root, trend_h, max_machines)
    except duckdb.Error as exc:  # a data set file that DuckDB cannot read (corrupt, cut short)
        raise CmcanError(f"{root}: cannot read the data set: {str(exc).splitlines()[0]}", Kind.DATA) from None
    tmp = out.with_name(f".{out.name}.tmp")
    with writing("write the report", out):
        try:
            tmp.write_text(text, encoding="utf-8")
            os.replace(tmp, out)
        finally:
            tmp.unlink(missing_ok=True)
    return len(text)
