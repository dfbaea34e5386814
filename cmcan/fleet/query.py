"""SQL over the fleet data set with DuckDB: read-only views over the committed, checked files.

``timeline``, ``events``, ``logs`` and ``quarantine`` have the hive partition columns ``machine``
(text) and ``day`` (date) added, and files of differing columns unioned by name (a column added by a
later cmcan reads as NULL in older files). ``machine_logs`` adds each log's offset on its machine's
operating-hour axis (the logged hours of the machine's earlier logs), so
``operating_h = offset_h + log_time_h`` places a timeline row on the machine's life; ``machines``
has one row per machine with the fit verdict (:mod:`cmcan.fitcheck`) of its first judged log.

**What a statement can do.** The files are opened here, by pyarrow, from the list the commit
records give (no glob: a data set path with ``[1]`` in it is just a path), checked against those
records (page checksums, the records' own hashes, the data files' SHA-256 unless ``verify=False``),
and handed to DuckDB as Arrow data. The DuckDB connection is in memory, with external access
(files, network), extension installing and loading, Python replacement scans and spilling to disk
off, and its configuration locked before the statement runs; the statement must be one ``SELECT``
(or ``EXPLAIN``). ``COPY ... TO``, ``ATTACH``, ``read_text``, ``glob``, ``INSTALL`` and anything
else that reaches outside the views are refused (:class:`QueryRefused`, exit 77).
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from cmcan.errors import CmcanError, Kind
from cmcan.fleet import dataset as ds
from cmcan.fleet.uplinkrows import COLUMNS as UPLINK_COLUMNS
from cmcan.fleet.uplinkrows import UPLINK_QUARANTINE, UPLINK_TABLES

# Columns of a table that has no file yet, so queries (and the report) over an empty data set run.
_F, _I, _S, _B = "double", "int64", "string", "bool"
_PROV = {"log_hash": _S, "config_hash": _S, "dbc_hash": _S, "model_hash": _S, "cmcan_version": _S}
EMPTY: dict[str, dict[str, str]] = {
    "timeline": {
        "time_s": _F,
        "log_time_h": _F,
        "ticks": _I,
        "evaluated": _I,
        "gate": _S,
        "measured": _F,
        "predicted": _F,
        "whitebox": _F,
        "cm_ratio_raw_pct": _F,
        "cm_ratio_filt_pct": _F,
        "extra_leak_lpm": _F,
        "cm_filt_valid": _B,
        "warning_level": _S,
        "warning_reason": _S,
        "time_below_threshold_s": _F,
        "pump_speed_rpm": _F,
        "pump_disp_cc": _F,
        "dp_bar": _F,
        "temp_c": _F,
        "baseline_state": _I,
        "baseline_learned_h": _F,
        "baseline_coverage_pct": _F,
        "baseline_distance_lpm": _F,
        "prognosis_state": _I,
        "prognosis_direction": _I,
        "prognosis_to_warning_h": _F,
        "prognosis_to_eol_p10_h": _F,
        "prognosis_to_eol_p50_h": _F,
        "prognosis_to_eol_p90_h": _F,
        **_PROV,
    },
    "events": {
        "time_s": _F,
        "log_time_h": _F,
        "from_level": _S,
        "to_level": _S,
        "reason": _S,
        "cm_ratio_filt_pct": _F,
        **_PROV,
    },
    "logs": {
        "log": _S,
        "log_name": _S,
        "log_size_bytes": _I,
        "first_time_s": _F,
        "last_time_s": _F,
        "duration_h": _F,
        "ticks": _I,
        "evaluated": _I,
        "evaluated_h": _F,
        **{f"cm_ratio_p{q:02d}_pct": _F for q in (1, 5, 50, 95, 99)},
        "cm_ratio_mean_pct": _F,
        "cm_ratio_trend_pct_per_h": _F,
        "cm_ratio_filt_first_pct": _F,
        "cm_ratio_filt_last_pct": _F,
        "cm_ratio_filt_min_pct": _F,
        "cm_ratio_filt_max_pct": _F,
        "extra_leak_mean_lpm": _F,
        "extra_leak_last_lpm": _F,
        "extra_leak_trend_lpm_per_h": _F,
        "warnings_low": _I,
        "warnings_high": _I,
        "faults": _I,
        "first_warning_time_s": _F,
        "first_fault_time_s": _F,
        **{f"time_{k}_h": _F for k in ("ok", "low", "high", "fault")},
        "final_level": _S,
        "final_reason": _S,
        **{f"count_{k}": _I for k in ("frames_total", "accepted", "ticks", "evaluated")},
        "quantity": _S,
        "motor_disp_cc": _F,
        "oil_nu40_cst": _F,
        "oil_nu100_cst": _F,
        "threshold_low_pct": _F,
        "threshold_high_pct": _F,
        "learning_low_pct": _F,
        "learning_high_pct": _F,
        "eol_kind": _S,
        "eol_value": _F,
        "eol_high_pct": _F,
        "end_of_life": _S,
        "type_verdict": _S,
        "timeline_rate_hz": _F,
        "engine": _S,
        "replay_s": _F,
        "state_in": _S,
        "state_note": _S,
        "carried_from": _S,
        "state_out": _S,
        "cut_line": _I,
        "fit": _S,
        "fit_median_pct": _F,
        "fit_points": _I,
        ds.FILES: _S,
        **_PROV,
        ds.RECORD_HASH: _S,
    },
    "quarantine": {
        "log": _S,
        "config": _S,
        "model": _S,
        "stage": _S,
        "reason": _S,
        "options": _S,
        "quarantined_at": _S,
        **_PROV,
        ds.RECORD_HASH: _S,
    },
}
# The uplink's tables (``cmcan fleet ingest``), as its rows are written (one vocabulary).
EMPTY.update({t: dict(UPLINK_COLUMNS[t]) for t in (*UPLINK_TABLES, UPLINK_QUARANTINE)})
ALL_TABLES = (*ds.TABLES, *UPLINK_TABLES, UPLINK_QUARANTINE)
PROVENANCE_KEYS = ("log_hash", "config_hash", "dbc_hash", "model_hash")
# Which tables' files each view reads.
VIEW_TABLES = {
    "timeline": ("timeline", "logs"),
    "events": ("events", "logs"),
    "logs": ("logs",),
    "quarantine": ("quarantine",),
    "machine_logs": ("logs",),
    "machines": ("logs",),
    **{t: (t,) for t in (*UPLINK_TABLES, UPLINK_QUARANTINE)},
}
# DuckDB with nothing outside the views: set at connect, then locked.
LOCKDOWN = {
    "enable_external_access": False,
    "autoload_known_extensions": False,
    "autoinstall_known_extensions": False,
    "allow_community_extensions": False,
    "python_enable_replacements": False,
    "temp_directory": "",
}
ALLOWED_STATEMENTS = ("SELECT", "EXPLAIN")


class QueryRefused(CmcanError):
    """A statement that would reach outside the data set's views (write, read files, network)."""

    kind = Kind.NO_PERMISSION


def require_duckdb() -> Any:
    try:
        import duckdb
    except ImportError:
        raise CmcanError(
            "this needs the 'fleet' extra: pip install 'cmcan[fleet]' (duckdb is missing)", Kind.UNAVAILABLE
        ) from None
    return duckdb


# -- the data set's files, read and checked ---------------------------------------------------------


def _empty(table: str) -> Any:
    import pyarrow as pa

    fields = [] if table == UPLINK_QUARANTINE else [pa.field("machine", pa.string())]  # (its own column)
    if table not in (ds.QUARANTINE, UPLINK_QUARANTINE):
        fields.append(pa.field("day", pa.date32()))
    fields += [pa.field(k, pa.type_for_alias(t)) for k, t in EMPTY[table].items()]
    return pa.schema(fields).empty_table()


def _records(root: Path, table: str) -> tuple[list[dict[str, Any]], list[str]]:
    """Every one-row record of a table (summaries, quarantine rows) with ``machine`` and ``day``
    from its folders, and the problems of the damaged ones."""
    import datetime as dt

    rows, problems = [], []
    for machine in ds.machines_in(root, table):
        base = ds.partition(root, table, machine)
        pattern = "*.parquet" if table == ds.QUARANTINE else "day=*/*.parquet"
        for f in sorted(base.glob(pattern)):
            if f.name.startswith("."):
                continue
            try:
                row = ds.read_record(f)
            except ds.Damaged as exc:
                problems += exc.problems
                continue
            extra: dict[str, Any] = {"machine": machine}
            if table != ds.QUARANTINE:
                try:
                    extra["day"] = dt.date.fromisoformat(f.parent.name.split("=", 1)[1])
                except ValueError:
                    problems.append(f"{f}: not in a day=YYYY-MM-DD folder")
                    continue
            rows.append({**extra, **row})
    return rows, problems


def _records_table(table: str, rows: list[dict[str, Any]]) -> Any:
    """One Arrow table of records whose columns may differ (unioned by name)."""
    import pyarrow as pa

    if not rows:
        return _empty(table)
    names: dict[str, None] = {}
    for r in rows:
        names.update(dict.fromkeys(r))
    names.update(dict.fromkeys(k for k in EMPTY[table] if k not in names))  # null in older records
    arrays = {}
    for k in names:
        values = [r.get(k) for r in rows]
        known = "date32" if k == "day" else ("string" if k == "machine" else EMPTY[table].get(k))
        if known is not None:
            arrays[k] = pa.array(values, pa.type_for_alias(known))
        elif all(v is None for v in values):
            arrays[k] = pa.array(values, pa.string())
        else:
            arrays[k] = pa.array(values)
    return pa.table(arrays)


def _data_dataset(root: Path, table: str, files: list[Path], flat: list[Path] | None = None) -> Any:
    """The data files of a table as one pyarrow dataset (hive partitions, unioned columns, page
    checksums verified while it is read). ``flat``: files of the uplink's tables not folded into the
    partitions yet, whose rows carry their ``machine`` and ``day`` (``cmcan.fleet.uplinkstore``)."""
    import pyarrow as pa
    import pyarrow.dataset as pds
    import pyarrow.parquet as pq

    partitioned = table != UPLINK_QUARANTINE
    part = pds.partitioning(pa.schema([("machine", pa.string()), ("day", pa.date32())]), flavor="hive")
    flat = flat or []
    if not files and not flat:
        return _empty(table)
    schemas = []
    problems = []
    for f in [*files, *flat]:
        try:
            schemas.append(pq.read_schema(f))
        except (OSError, pa.ArrowException) as exc:
            problems.append(f"{f}: not readable ({str(exc).splitlines()[0][:120]})")
    if problems:
        raise ds.Damaged(problems)
    # the columns cmcan writes today are there in every data set (null in files written before them):
    # a data set from an older cmcan answers the plan and the report instead of a binder error
    parts = [part.schema] if partitioned else []
    schema = pa.unify_schemas([*schemas, *parts, _empty(table).schema], promote_options="permissive")
    fmt = pds.ParquetFileFormat(
        default_fragment_scan_options=pds.ParquetFragmentScanOptions(page_checksum_verification=True)
    )
    if not partitioned:
        return pds.dataset([str(f) for f in [*files, *flat]], schema=schema, format=fmt)
    parted = pds.dataset(
        [str(f) for f in files], schema=schema, format=fmt, partitioning=part, partition_base_dir=str(root / table)
    )
    if not flat:
        return parted
    return pds.dataset([parted, pds.dataset([str(f) for f in flat], schema=schema, format=fmt)])


def _locked(duckdb: Any) -> Any:
    return duckdb.connect(":memory:", config=dict(LOCKDOWN))


def plan_statement(sql: str) -> set[str]:
    """Check the statement (:func:`check_statement`) and name the data set's tables it reads, on a
    locked connection with nothing in it: DuckDB names the tables a statement needs that its catalog
    lacks (all of the data set's when it cannot tell, as for a join ``USING`` columns it cannot see).
    Nothing of the statement runs, and nothing is read yet."""
    duckdb = require_duckdb()
    con = _locked(duckdb)
    try:
        con.execute("SET lock_configuration = true")
        check_statement(con, sql)
        try:
            names = {n.lower() for n in con.get_table_names(sql)}
        except duckdb.Error:
            return set(ALL_TABLES)
    finally:
        con.close()
    return {t for n in names for t in VIEW_TABLES.get(n, ())}


def connect(root: str | Path, verify: bool = True, tables: set[str] | None = None) -> Any:
    """A locked, in-memory DuckDB connection with the data set's views. ``tables``: the data tables
    the statement reads (default all): only those are opened and their files checked in full; a
    damaged file raises :class:`cmcan.fleet.dataset.Damaged`."""
    duckdb = require_duckdb()
    root = ds.open_dataset(Path(root), create=False)
    want = set(ALL_TABLES) if tables is None else tables
    logs, problems = _records(root, ds.SUMMARY_TABLE)
    quarantine, q_problems = _records(root, ds.QUARANTINE)
    if ds.QUARANTINE in want:
        problems += q_problems
    data: dict[str, list[Path]] = {t: [] for t in ds.DATA_TABLES}
    for rec in logs:
        for t in ds.DATA_TABLES:
            data[t] += ds.data_files(root, rec["machine"], rec, t)
        if verify and want & set(ds.DATA_TABLES):
            problems += ds.check_files(root, rec["machine"], rec, want & set(ds.DATA_TABLES))
    uplink: dict[str, list[Any]] = {}
    if want & {*UPLINK_TABLES, UPLINK_QUARANTINE}:  # the gateways' rows, from the ingest's commit records
        from cmcan.fleet.uplinkstore import committed_files

        uplink, up_problems = committed_files(root, verify)
        problems += up_problems
    if problems:
        raise ds.Damaged(problems)
    con = _locked(duckdb)
    try:
        con.register(ds.SUMMARY_TABLE, _records_table(ds.SUMMARY_TABLE, logs))
        con.register(ds.QUARANTINE, _records_table(ds.QUARANTINE, quarantine))
        for t in ds.DATA_TABLES:  # a table the statement does not read is not opened (nor there)
            if t in want:
                con.register(t, _data_dataset(root, t, data[t]))
        for t in (*UPLINK_TABLES, UPLINK_QUARANTINE):
            if t in want:
                files = uplink.get(t, [])
                con.register(
                    t,
                    _data_dataset(root, t, [p for m, p in files if m is not None], [p for m, p in files if m is None]),
                )
        _derived_views(con)
        con.execute("SET lock_configuration = true")
    except BaseException:
        con.close()
        raise
    return con


T = TypeVar("T")
READ_TRIES = 3  # a reading and two more on a fresh listing (see read)
log = logging.getLogger("cmcan.fleet")


def _uplink_listing(root: Path) -> tuple[tuple[str, int, int], ...]:
    """The ingest's commit records as they stand (name, size, change time): a fold or the removal of
    what it replaced changes them."""
    from cmcan.fleet.uplinkstore import record_paths

    out = []
    for p in record_paths(root):
        try:
            st = p.stat()
        except OSError:  # removed since it was listed: that is a change too
            continue
        out.append((p.name, st.st_size, st.st_mtime_ns))
    return tuple(out)


def read(root: str | Path, fn: Callable[[Any], T], tables: set[str] | None = None, verify: bool = True) -> T:
    """``fn(con)`` on a connection to the data set (:func:`connect`). A running ``cmcan fleet ingest``
    removes the flat files a fold replaced :data:`cmcan.fleet.uplinkstore.READER_GRACE_S` after it; a
    reader slower than that finds a file it listed gone. So where the reading failed and the ingest's
    commit records changed meanwhile, it is done again on a fresh listing (at most
    :data:`READ_TRIES` in all); a failure over unchanged records is what the data set holds, raised."""
    root = Path(root)
    for attempt in range(1, READ_TRIES + 1):
        before = _uplink_listing(root)
        try:
            con = connect(root, verify, tables)
            try:
                return fn(con)
            finally:
                con.close()
        except Exception as exc:
            if attempt == READ_TRIES or _uplink_listing(root) == before:
                raise
            log.info("the data set's uplink rows were folded while they were read (%s): reading again", exc)
    raise AssertionError("unreachable")  # the loop returns or raises


def _derived_views(con: Any) -> None:
    con.execute(
        """CREATE VIEW machine_logs AS
           SELECT *, coalesce(sum(duration_h) OVER (PARTITION BY machine ORDER BY first_time_s, log_hash
                  ROWS BETWEEN UNBOUNDED PRECEDING AND 1 PRECEDING), 0.0) AS offset_h
           FROM logs"""
    )
    # A machine's fit: the earliest judged log among those replayed with its latest log's inputs.
    con.execute(
        """CREATE VIEW machines AS
           WITH latest AS (
               SELECT machine, arg_max(config_hash || ':' || dbc_hash || ':' || model_hash, first_time_s) AS inputs
               FROM logs GROUP BY machine),
           judged AS (
               SELECT l.machine, arg_min(l.fit, l.first_time_s) AS fit,
                      arg_min(l.fit_median_pct, l.first_time_s) AS fit_median_pct,
                      arg_min(l.log_name, l.first_time_s) AS fit_log
               FROM logs l JOIN latest ON l.machine = latest.machine
                    AND l.config_hash || ':' || l.dbc_hash || ':' || l.model_hash = latest.inputs
               WHERE l.fit IN ('fits', 'does_not_fit') GROUP BY l.machine)
           SELECT m.machine, coalesce(j.fit, 'unknown') AS fit, j.fit_median_pct, j.fit_log
           FROM (SELECT DISTINCT machine FROM logs) m LEFT JOIN judged j ON m.machine = j.machine"""
    )


# -- one statement ----------------------------------------------------------------------------------------


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else type(exc).__name__


def check_statement(con: Any, sql: str) -> None:
    """One SELECT (or EXPLAIN) statement, else :class:`QueryRefused`."""
    duckdb = require_duckdb()
    try:
        statements = con.extract_statements(sql)
    except duckdb.Error as exc:
        raise CmcanError(f"query failed: {_first_line(exc)}", Kind.DATA) from None
    if len(statements) != 1:
        raise QueryRefused(
            f"query refused: {len(statements)} statements; fleet query runs one SELECT over the data set's views"
        )
    kind = statements[0].type.name
    if kind not in ALLOWED_STATEMENTS:
        raise QueryRefused(
            f"query refused: statement type {kind}; fleet query is read-only and runs one SELECT over the views "
            "timeline, events, logs, quarantine, machine_logs, machines and the uplink's tables (docs/security.md)"
        )


def run_sql(root: str | Path, sql: str, verify: bool = True) -> tuple[list[str], list[tuple[Any, ...]]]:
    duckdb = require_duckdb()

    def run(con: Any) -> tuple[list[str], list[tuple[Any, ...]]]:
        try:
            rel = con.sql(sql)
            if rel is None:  # a statement without a result
                return [], []
            return list(rel.columns), rel.fetchall()
        except duckdb.PermissionException as exc:
            raise QueryRefused(f"query refused: {_first_line(exc)}") from None
        except duckdb.Error as exc:  # DuckDB's own message says what is wrong with the statement
            raise CmcanError(f"query failed: {_first_line(exc)}", Kind.DATA) from None

    return read(root, run, plan_statement(sql), verify)


# -- printing -------------------------------------------------------------------------------------------


def is_time_column(name: str) -> bool:
    """Epoch seconds (``time_s``, ``first_time_s``, ``min(time_s)``, ...)."""
    return "time_s" in name or name.endswith("_t_s")


EPOCH_LIKE = 1e8  # a number this large is printed with fixed decimals whatever its column is called


def _cell(v: Any, time_col: bool) -> str:
    """A value for the table format: times (epoch seconds) to the microsecond, other numbers to 10
    significant digits, so nothing prints as 1.76841e+09."""
    if v is None:
        return "NULL"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isfinite(v) and (time_col or abs(v) >= EPOCH_LIKE):
            return f"{v:.6f}"
        return f"{v:.10g}"
    return str(v)


def format_rows(columns: list[str], rows: list[tuple[Any, ...]], fmt: str = "table", max_rows: int = 100) -> str:
    if fmt == "csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(columns)
        w.writerows([["" if v is None else v for v in r] for r in rows])
        return buf.getvalue()
    if fmt == "json":
        return json.dumps([dict(zip(columns, r, strict=True)) for r in rows], default=str, indent=1) + "\n"
    shown = rows[:max_rows]
    times = [is_time_column(c) for c in columns]
    cells = [columns, *[[_cell(v, times[i]) for i, v in enumerate(r)] for r in shown]]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    more = f"({len(rows)} rows, first {max_rows} shown; --format csv for all)\n" if len(rows) > max_rows else ""
    return "\n".join(lines) + "\n" + more
