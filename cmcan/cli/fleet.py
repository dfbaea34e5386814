"""``cmcan fleet``: replay many machines' logs on Dask into a Parquet data set, report on it, query it;
``fleet train`` (a machine-type model from it) is :mod:`cmcan.cli.fleet_train`."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from cmcan.cli import fleet_ingest, fleet_train
from cmcan.cli.common import Subparsers
from cmcan.cli.errors import EX_DATAERR, ensure_writable, require_extra
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "fleet",
        help="many machines' logs on Dask into a Parquet data set; report and SQL over it",
        description="Fleet scale (needs the 'fleet' extra). See docs/fleet.md for the data set's tables.",
    )
    fsub = p.add_subparsers(dest="fleet_command", metavar="FLEET_COMMAND", required=True)

    r = fsub.add_parser(
        "replay",
        help="replay and diagnose every log of the sources into the data set",
        description="Replay every log of the SOURCES (folders, glob patterns, manifest CSVs with columns "
        "machine,log[,config][,model], single logs) through the monitor on Dask and add the results to the "
        "Parquet data set DATASET. A log already there with the same hashes is skipped; a log that fails "
        "goes to the quarantine table. Exit status 0, or 65 when a log of this run was quarantined.",
    )
    r.add_argument("sources", nargs="+", help="folder, glob pattern ('quote/*/it.log'), manifest .csv or log")
    r.add_argument("--out", required=True, help="data set folder (created if missing)")
    r.add_argument("--config", help="configuration for logs without one in a manifest (default: the shipped one)")
    r.add_argument("--model", help="model for logs without one in a manifest (default: the configuration's)")
    r.add_argument("--rate-hz", type=float, default=1.0, help="timeline rows per second of log time (default 1)")
    r.add_argument("--scheduler", help="address of an existing Dask scheduler (default: an embedded LocalCluster)")
    r.add_argument("--workers", type=int, help="worker processes of the embedded cluster (default: one per core)")
    r.add_argument("--timeout-s", type=float, default=3600.0, help="quarantine a log whose replay takes longer")
    r.add_argument("--retry-quarantined", action="store_true", help="try again the logs quarantined before")
    r.add_argument(
        "--follow-symlinks",
        action="store_true",
        help="read symbolic links in folders and manifests that point outside them (refused by default)",
    )
    r.add_argument(
        "--manifest-root",
        metavar="DIR",
        help="the folder every path of a manifest must lie under (default: the manifest's own folder)",
    )
    r.add_argument(
        "--keep-truncated",
        action="store_true",
        help="replay a log whose last line was cut (a logger killed) up to its last whole line, and record "
        "the cut in the logs table (default: such a log is refused, naming the line)",
    )
    r.add_argument("--engine", default="columnar", choices=("columnar", "streaming"), help="replay engine")
    r.add_argument("--json", action="store_true", help="print the run's summary as JSON")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr")
    r.set_defaults(func=run_replay)

    rep = fsub.add_parser("report", help="one self-contained HTML page over the data set")
    rep.add_argument("dataset", help="data set folder")
    rep.add_argument("--out", required=True, help="HTML file to write")
    rep.add_argument("--trend-hours", type=float, default=50.0, help="rank by the ratio trend over these last hours")
    rep.add_argument("--max-machines", type=int, default=50, help="draw at most this many machines (ranked)")
    rep.add_argument("--force", action="store_true", help="overwrite an existing report")
    rep.set_defaults(func=run_report)

    pl = fsub.add_parser(
        "plan",
        help="the service plan: one row per machine, ranked by urgency",
        description="One row per machine of the data set, ranked: a warning now, the prognosis imminent, a "
        "trend (by p10 then p50 hours to end of life), a ratio that cannot be judged (baseline suspect, "
        "configuration or model not fitting, a sensor fault), learning, no trend, no prognosis. Each row: the "
        "warning level, the baseline's and the prognosis's state, the operating hours to the warning and to "
        "end of life (p10/p50/p90), a calendar date for each from the machine's utilisation, what end of life "
        "means for it, and flags (docs/fleet.md).",
    )
    pl.add_argument("dataset", help="data set folder")
    pl.add_argument(
        "--at",
        metavar="TIME",
        help="the plan as it stood at TIME (ISO 8601 date or time, UTC unless it says otherwise, or epoch "
        "seconds): only rows up to it; ages counted to it (default: everything, ages to now)",
    )
    pl.add_argument("--json", action="store_true", help='print {"machines": [...]} as JSON')
    pl.add_argument(
        "--aemp",
        metavar="FILE",
        help="also write the plan as an ISO 15143-3 (AEMP 2.0) fleet snapshot (XML; cmcan's results as named "
        "extension elements, docs/fleet-telematics.md)",
    )
    pl.add_argument("--force", action="store_true", help="overwrite an existing --aemp file")
    pl.set_defaults(func=run_plan)

    q = fsub.add_parser(
        "query",
        help="SQL over the data set with DuckDB",
        description="Run SQL on the views timeline, events, logs, quarantine, machine_logs, machines and the "
        "uplink's uplink_summaries, uplink_events, uplink_dropped, uplink_status, uplink_quarantine (docs/fleet.md).",
    )
    q.add_argument("dataset", help="data set folder")
    q.add_argument("sql", help='the statement, e.g. "SELECT machine, sum(warnings_low) FROM logs GROUP BY 1"')
    q.add_argument("--format", choices=("table", "csv", "json"), default="table", help="output format")
    q.add_argument("--max-rows", type=int, default=100, help="rows shown in table format")
    q.add_argument(
        "--no-verify",
        action="store_true",
        help="do not hash the data files the statement reads against their commit records (faster on a large "
        "data set; the records themselves are still checked)",
    )
    q.set_defaults(func=run_query)

    fleet_train.add_parser(fsub)
    fleet_ingest.add_parser(fsub)

    d = fsub.add_parser(
        "drop",
        help="remove every row of a machine from the data set",
        description="Remove a machine's logs, timeline, events and quarantine rows (its summaries first, so its "
        "logs leave the data set at once). The logs themselves are not touched; replaying them again adds them back.",
    )
    d.add_argument("dataset", help="data set folder")
    d.add_argument("--machine", action="append", required=True, help="machine id (repeat for several)")
    d.add_argument("--json", action="store_true", help="print what was removed as JSON")
    d.set_defaults(func=run_drop)


def _check_options(args: argparse.Namespace) -> None:
    if not (0 < args.rate_hz <= 100):
        raise CmcanError(f"--rate-hz: expected a rate in (0, 100] Hz, got {args.rate_hz}", Kind.USAGE)
    if args.workers is not None and args.workers < 1:
        raise CmcanError(f"--workers: expected at least 1, got {args.workers}", Kind.USAGE)
    if args.scheduler and args.workers:
        raise CmcanError("--workers sizes the embedded cluster; it does not apply with --scheduler", Kind.USAGE)
    if args.timeout_s <= 0:
        raise CmcanError(f"--timeout-s: expected a positive number of seconds, got {args.timeout_s}", Kind.USAGE)
    for opt in ("config", "model"):
        v = getattr(args, opt)
        if v and not Path(v).is_file():
            raise CmcanError(f"--{opt} {v}: file not found", Kind.NO_INPUT)


def run_replay(args: argparse.Namespace) -> int:
    require_extra("fleet", "distributed")
    require_extra("fleet", "pyarrow")
    _check_options(args)
    from cmcan.fleet.run import run_fleet
    from cmcan.fleet.sources import find_logs
    from cmcan.fleet.task import Options

    if args.manifest_root and not Path(args.manifest_root).is_dir():
        raise CmcanError(f"--manifest-root {args.manifest_root}: no such folder", Kind.NO_INPUT)
    found = find_logs(args.sources, args.config, args.model, args.follow_symlinks, args.manifest_root)
    for note in found.notes:
        print(f"cmcan fleet replay: {note}", file=sys.stderr)
    for r in found.refused:
        print(f"cmcan fleet replay: {r.line()}", file=sys.stderr)
    if not found.jobs and not found.refused:
        raise CmcanError(f"no logs found in {', '.join(args.sources)}", Kind.NO_INPUT)
    opt = Options(
        dataset=args.out,
        rate_hz=args.rate_hz,
        timeout_s=args.timeout_s,
        retry_quarantined=args.retry_quarantined,
        engine=args.engine,
        keep_truncated=args.keep_truncated,
    )
    last = [0.0]

    def progress(res: dict[str, Any], rep: Any) -> None:
        if args.quiet:
            return
        n = sum(rep.counts.values())
        if res["status"] == "quarantined":
            print(f"quarantined {res['machine']} {res['log']}: {res.get('reason')}", file=sys.stderr)
        for m in res.get("moved_from") or ():
            print(f"moved {res['log']} from machine {m} to {res['machine']}", file=sys.stderr)
        if res.get("redone"):
            print(f"replayed again {res['machine']} {res['log']}: its committed files were damaged", file=sys.stderr)
        now = time.monotonic()
        if now - last[0] >= 2.0 or n == rep.logs:
            last[0] = now
            print(
                f"[{n}/{rep.logs}] {rep.counts['done']} done, {rep.counts['skipped']} skipped, "
                f"{rep.counts['quarantined']} quarantined, {rep.frames / 1e6:.1f} M frames",
                file=sys.stderr,
            )

    try:
        rep = run_fleet(
            found.jobs, opt, scheduler=args.scheduler, workers=args.workers, progress=progress, refused=found.refused
        )
    except KeyboardInterrupt:
        print(
            "cmcan fleet replay: interrupted; the logs committed so far stay in the data set, "
            "run the same command again to do the rest",
            file=sys.stderr,
        )
        raise
    for note in rep.notes:
        print(f"cmcan fleet replay: {note}", file=sys.stderr)
    d = rep.to_dict()
    if args.json:
        print_json(d)
    else:
        rate = f", {d['frames_per_s'] / 1e3:.0f} k frames/s" if d["frames_per_s"] else ""
        extra = "".join(
            f", {n} {what}"
            for n, what in (
                (d["refused"], "refused (not read)"),
                (len(d["moved"]), "moved to another machine"),
                (len(d["redone"]), "replayed again (damaged)"),
                (len(d["cut"]), "replayed up to a cut last line"),
            )
            if n
        )
        print(
            f"{args.out}: {d['logs']} logs: {d['done']} replayed, {d['skipped']} skipped (already there), "
            f"{d['quarantined']} quarantined{extra}; {d['frames'] / 1e6:.2f} M frames in {d['seconds']:.1f} s "
            f"on {d['workers']} workers{rate}"
        )
    return EX_DATAERR if d["quarantined"] or d["refused"] else 0


def run_report(args: argparse.Namespace) -> int:
    require_extra("fleet", "duckdb")
    require_extra("plot", "matplotlib")
    out = ensure_writable(args.out, args.force)
    from cmcan.fleet.report import write_report

    n = write_report(args.dataset, out, args.trend_hours, args.max_machines)
    print(f"{out}: fleet report ({n / 1e3:.0f} kB, self-contained)")
    return 0


def parse_time(text: str, option: str) -> float:
    """Epoch seconds from an ISO 8601 date or time (UTC unless it carries an offset) or a number."""
    import datetime as dt

    try:
        return float(text)
    except ValueError:
        pass
    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError:
        raise CmcanError(
            f"{option} {text!r}: expected an ISO 8601 date or time (2026-03-01, 2026-03-01T14:30) or epoch seconds",
            Kind.USAGE,
        ) from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return t.timestamp()


def run_plan(args: argparse.Namespace) -> int:
    require_extra("fleet", "duckdb")
    from cmcan.fleet.plan import build, format_table

    at_s = None if args.at is None else parse_time(args.at, "--at")
    now_s = time.time() if at_s is None else at_s
    if args.aemp:
        from cmcan.fleet.aemp import export

        out = ensure_writable(args.aemp, args.force)
        text, rows = export(args.dataset, at_s, now_s)
        tmp = out.with_name(f".{out.name}.tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(out)
        print(f"{out}: ISO 15143-3 fleet snapshot of {len(rows)} machines", file=sys.stderr)
    else:
        rows = build(args.dataset, at_s, now_s)
    if args.json:
        print_json({"at": at_s, "machines": [r.to_dict() for r in rows]})
    else:
        sys.stdout.write(format_table(rows) if rows else f"{args.dataset}: no machine heard\n")
    return 0


def run_query(args: argparse.Namespace) -> int:
    require_extra("fleet", "duckdb")
    from cmcan.fleet.query import format_rows, run_sql

    cols, rows = run_sql(args.dataset, args.sql, verify=not args.no_verify)
    sys.stdout.write(format_rows(cols, rows, args.format, args.max_rows))
    return 0


def run_drop(args: argparse.Namespace) -> int:
    from cmcan.fleet import dataset as ds

    root = ds.open_dataset(Path(args.dataset), create=False)
    for m in args.machine:
        ds.check_machine(m, "--machine")
    removed = {}
    with ds.writer_lock(root):
        have = {m for t in ds.TABLES for m in ds.machines_in(root, t)}
        missing = [m for m in args.machine if m not in have]
        if missing:
            raise CmcanError(f"{root}: no rows of machine {', '.join(missing)}; nothing was removed", Kind.NO_INPUT)
        for m in args.machine:
            removed[m] = ds.drop_machine(root, m)
    if args.json:
        print_json({"dataset": str(root), "removed": removed})
    else:
        for m, n in removed.items():
            print(
                f"{root}: removed machine {m}: {n['logs']} logs ({n['timeline']} timeline, {n['events']} events "
                f"files), {n['quarantine']} quarantine rows"
            )
    return 0
