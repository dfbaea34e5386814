"""SQL over the fleet data set with DuckDB: one view per table, over the committed files only.

``timeline``, ``events``, ``logs`` and ``quarantine`` are views over the Parquet files with the hive
partition columns ``machine`` (text) and ``day`` (date) added and files of differing columns unioned
by name (a column added by a later cmcan reads as NULL in older files). ``machine_logs`` adds each
log's offset on its machine's operating-hour axis (the logged hours of the machine's earlier logs),
so ``operating_h = offset_h + log_time_h`` places a timeline row on the machine's life.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

from cmcan.errors import CmcanError, Kind
from cmcan.fleet import dataset as ds

# Columns of a table that has no file yet, so queries over an empty data set still run.
EMPTY = {
    "timeline": "time_s DOUBLE, log_time_h DOUBLE, ticks BIGINT, evaluated BIGINT, cm_ratio_raw_pct DOUBLE, "
    "cm_ratio_filt_pct DOUBLE, extra_leak_lpm DOUBLE, warning_level VARCHAR",
    "events": "time_s DOUBLE, log_time_h DOUBLE, from_level VARCHAR, to_level VARCHAR, reason VARCHAR, "
    "cm_ratio_filt_pct DOUBLE",
    "logs": "log VARCHAR, first_time_s DOUBLE, last_time_s DOUBLE, duration_h DOUBLE, evaluated_h DOUBLE, "
    "warnings_low BIGINT, warnings_high BIGINT, faults BIGINT, final_level VARCHAR, threshold_low_pct DOUBLE, "
    "threshold_high_pct DOUBLE, cm_ratio_filt_last_pct DOUBLE",
    "quarantine": "log VARCHAR, stage VARCHAR, reason VARCHAR, quarantined_at VARCHAR",
}


PROVENANCE_KEYS = ("log_hash", "config_hash", "dbc_hash", "model_hash")


def require_duckdb() -> Any:
    try:
        import duckdb
    except ImportError:
        raise CmcanError(
            "this needs the 'fleet' extra: pip install 'cmcan[fleet]' (duckdb is missing)", Kind.UNAVAILABLE
        ) from None
    return duckdb


def connect(root: str | Path) -> Any:
    """An in-memory DuckDB connection with the data set's views."""
    duckdb = require_duckdb()
    root = ds.open_dataset(Path(root), create=False)
    con = duckdb.connect(":memory:")
    try:
        _views(con, root)
    except duckdb.Error as exc:  # a data set file that DuckDB cannot read (corrupt, cut short)
        con.close()
        raise CmcanError(f"{root}: cannot read the data set: {str(exc).splitlines()[0]}", Kind.DATA) from None
    return con


def _views(con: Any, root: Path) -> None:
    for table in (ds.SUMMARY_TABLE, "quarantine", *ds.DATA_TABLES):  # logs first: the data views join it
        depth = "machine=*/*.parquet" if table == "quarantine" else "machine=*/day=*/*.parquet"
        pattern = (root / table / depth).as_posix().replace("'", "''")
        if next((root / table).glob(depth), None) is None:
            cols = (
                "machine VARCHAR"
                + (", day DATE" if table != "quarantine" else "")
                + ", "
                + EMPTY[table]
                + PROVENANCE_COLUMNS
            )
            con.execute(f"CREATE VIEW {table} AS SELECT * FROM (SELECT {_nulls(cols)}) WHERE false")
            continue
        types = "{'machine': 'VARCHAR'" + (", 'day': 'DATE'}" if table != "quarantine" else "}")
        src = (
            f"read_parquet('{pattern}', hive_partitioning = true, union_by_name = true, "
            f"hive_types = {types}, hive_types_autocast = false)"
        )
        if table in ds.DATA_TABLES:  # rows of committed logs only (an interrupted commit leaves orphans)
            name = f"_{table}_all"
            con.execute(f"CREATE VIEW {name} AS SELECT * FROM {src}")
            con.execute(
                f"CREATE VIEW {table} AS SELECT * FROM {name} t WHERE EXISTS (SELECT 1 FROM logs l WHERE "
                + " AND ".join(f"l.{c} = t.{c}" for c in ("machine", *PROVENANCE_KEYS))
                + ")"
            )
        else:
            con.execute(f"CREATE VIEW {table} AS SELECT * FROM {src}")
    con.execute(
        """CREATE VIEW machine_logs AS
           SELECT *, coalesce(sum(duration_h) OVER (PARTITION BY machine ORDER BY first_time_s, log_hash
                  ROWS BETWEEN UNBOUNDED PRECEDING AND 1 PRECEDING), 0.0) AS offset_h
           FROM logs"""
    )


PROVENANCE_COLUMNS = (
    ", log_hash VARCHAR, config_hash VARCHAR, dbc_hash VARCHAR, model_hash VARCHAR, cmcan_version VARCHAR"
)


def _nulls(cols: str) -> str:
    return ", ".join(f"NULL::{c.strip().split(' ', 1)[1]} AS {c.strip().split(' ', 1)[0]}" for c in cols.split(","))


def run_sql(root: str | Path, sql: str) -> tuple[list[str], list[tuple[Any, ...]]]:
    con = connect(root)
    try:
        rel = con.sql(sql)
    except Exception as exc:  # DuckDB's own message says what is wrong with the statement
        raise CmcanError(f"query failed: {str(exc).splitlines()[0]}", Kind.DATA) from None
    if rel is None:  # a statement without a result
        return [], []
    try:
        return list(rel.columns), rel.fetchall()
    except Exception as exc:
        raise CmcanError(f"query failed: {str(exc).splitlines()[0]}", Kind.DATA) from None


def _cell(v: Any) -> str:
    if v is None:
        return "NULL"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.6g}"
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
    cells = [columns, *[[_cell(v) for v in r] for r in shown]]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    more = f"({len(rows)} rows, first {max_rows} shown; --format csv for all)\n" if len(rows) > max_rows else ""
    return "\n".join(lines) + "\n" + more
