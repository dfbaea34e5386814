"""``cmcan gap``: sim-to-real gap diagnosis (diagnose, bench, effects)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from cmcan.cli.common import Subparsers
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind
from cmcan.roles import MODEL_INPUTS, QUANTITIES

ROLES = (*MODEL_INPUTS, *QUANTITIES)


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "gap",
        help="sim-to-real gap diagnosis",
        description="Where the simulator departs from measured data, which unmodelled effect or sensor "
        "error causes it, and how far the gap shrinks once it is added, judged on withheld data.",
    )
    gsub = p.add_subparsers(dest="gap_command", metavar="ACTION", required=True)
    d = gsub.add_parser("diagnose", help="diagnose the gap between REAL and the simulator")
    d.add_argument(
        "real",
        help="measured data: a run CSV (time_s, pump_speed_rpm, pump_disp_cc, dp_bar, temp_c and the "
        "output), a CAN log read through the configuration's DBC, or with --points/--column an "
        "operating-point table (one row per operating point)",
    )
    d.add_argument("--out", required=True, help="folder for report.json, report.md and the plots")
    d.add_argument(
        "--drive",
        help="the machine: YAML with 'drive', 'losses' and 'fluid' sections as in a scenario; "
        "default: the reference drive",
    )
    d.add_argument(
        "--holdout",
        help="withheld region: VAR:topNN, VAR:bottomNN (VAR dp_bar, temp_c, pump_speed_rpm, "
        "pump_disp_cc, time) or random25; default: the hottest quarter, or the highest-pressure quarter "
        "where the oil temperature hardly varies",
    )
    d.add_argument(
        "--quantity",
        default="motor_speed_rpm",
        choices=("motor_speed_rpm", "flow_lpm"),
        help="output quantity compared (default motor_speed_rpm)",
    )
    pts = d.add_argument_group("operating-point tables (cycle means, rig logs)")
    pts.add_argument("--points", metavar="SPEC", help="YAML naming columns, constants and row filters")
    pts.add_argument("--column", action="append", default=[], metavar="ROLE=COLUMN", help="the column holding a role")
    pts.add_argument(
        "--constant",
        action="append",
        default=[],
        metavar="ROLE=VALUE",
        help="a role without a sensor, held at VALUE (a constant-speed pump)",
    )
    pts.add_argument(
        "--where", action="append", default=[], metavar="COND", help="keep rows where COND holds (pump_leak=0)"
    )
    d.add_argument("--config", help="configuration for CAN logs and the gate (default: the shipped one)")
    d.add_argument("--no-plots", action="store_true")
    d.add_argument("--force", action="store_true", help="write into an existing report folder")
    d.add_argument("--json", action="store_true", help="print report.json to stdout")
    d.set_defaults(func=run_diagnose)
    b = gsub.add_parser("bench", help="check the diagnosis on data whose effect it is not told")
    b.add_argument("--trials", type=int, default=100)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--minutes", type=float, default=20.0, help="minutes of data per trial (default 20)")
    b.add_argument("--jobs", type=int, default=1, help="processes to run trials in (same figures; default 1)")
    b.add_argument("--json", action="store_true", help="the summary and every trial as JSON")
    b.set_defaults(func=run_bench)
    e = gsub.add_parser("effects", help="list the candidate effects")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=run_effects)


def _need_scipy() -> None:
    try:
        import scipy.optimize  # noqa: F401
    except ImportError:
        raise CmcanError("the gap diagnosis needs scipy (pip install 'cmcan[gap]')", Kind.UNAVAILABLE) from None


def load_drive(path: str | None) -> Any:
    """The machine from a drive file (the reference drive without one); 66 if missing, 78 if malformed."""
    from cmcan.schema import SchemaError
    from cmcan.sim.physics import DriveParams
    from cmcan.sim.scenario import load_drive as load

    if path is None:
        return DriveParams()
    if not Path(path).is_file():
        raise CmcanError(f"{path}: drive file not found", Kind.NO_INPUT)
    try:
        return load(path)
    except SchemaError as exc:
        raise CmcanError(str(exc), Kind.CONFIG) from None


def _pairs(items: list[str], option: str, number: bool) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        role, sep, value = item.partition("=")
        role, value = role.strip(), value.strip()
        if not sep or not role or not value:
            raise CmcanError(f"{option} {item!r}: expected ROLE=VALUE", Kind.USAGE)
        if role not in ROLES:
            raise CmcanError(f"{option} {item!r}: role {role!r} is not one of {', '.join(ROLES)}", Kind.USAGE)
        if number:
            try:
                out[role] = float(value)
            except ValueError:
                raise CmcanError(f"{option} {item!r}: {value!r} is not a number", Kind.USAGE) from None
        else:
            out[role] = value
    return out


def _point_spec(args: argparse.Namespace) -> Any:
    """The operating-point spec from --points and the command-line options, or None for a time series."""
    from cmcan.io.points import Condition, PointsError, PointSpec

    if not (args.points or args.column or args.constant or args.where):
        return None
    spec = PointSpec(source="the command line")
    if args.points:
        try:
            spec = PointSpec.load(args.points)
        except PointsError as exc:  # the spec file is configuration
            raise CmcanError(str(exc), Kind.NO_INPUT if exc.problem == "noinput" else Kind.CONFIG) from None
    try:
        where = tuple(Condition.parse(w) for w in args.where)
    except PointsError as exc:
        raise CmcanError(str(exc), Kind.USAGE) from None
    cli = PointSpec(
        _pairs(args.column, "--column", number=False),
        _pairs(args.constant, "--constant", number=True),
        where,
        "the command line",
    )
    return spec.merged(cli)


def _load_data(args: argparse.Namespace, spec: Any, drive: Any) -> Any:
    """The real data, gated as the drive ``drive`` is sized (the configuration's gates where it has the
    same output)."""
    from cmcan.gap import data as gapdata
    from cmcan.io.points import PointsError
    from cmcan.model.features import DataError

    if not Path(args.real).is_file():
        raise CmcanError(f"{args.real}: file not found", Kind.NO_INPUT)
    try:
        if spec is not None:
            return gapdata.load_points(args.real, spec, args.quantity, drive=drive)
        from cmcan.assemble import dbc_for, frame_matcher
        from cmcan.cli.common import load_config
        from cmcan.sim.scenario import drive_differences

        cfg = load_config(args.config)
        for diff in drive_differences(drive, cfg.motor_disp_cc, cfg.drive.pump_disp_max_cc, cfg.oil):
            # the simulator's drive against the log's machine: the gap would be the sizes' difference
            logging.getLogger("cmcan").warning(
                "%s: the drive the gap is measured against (%s) is not the machine of %s: %s; give --drive the "
                "machine's drive, losses and fluid",
                args.real,
                args.drive or "the reference drive: no --drive",
                cfg.source,
                diff,
            )
        db = dbc_for(cfg)
        match = frame_matcher(cfg, db)
        data = gapdata.load(args.real, args.quantity, cfg.gate_limits, db, cfg.signals, match, drive=drive)
        note = match.merged_note(cfg)
        if note is not None:
            logging.getLogger("cmcan").warning("%s: %s", args.real, note)
        return data
    except PointsError as exc:
        code = {"noinput": Kind.NO_INPUT, "spec": Kind.CONFIG if args.points else Kind.USAGE}.get(
            exc.problem, Kind.DATA
        )
        raise CmcanError(str(exc), code) from None
    except DataError as exc:
        raise CmcanError(str(exc), Kind.DATA) from None


def run_diagnose(args: argparse.Namespace) -> int:
    _need_scipy()
    from cmcan.gap import report as rep
    from cmcan.gap.diagnose import diagnose

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CmcanError(f"{out}: exists and is not a folder", Kind.CANT_CREATE)
    if out.exists() and any(out.iterdir()) and not args.force:
        raise CmcanError(f"{out}: folder exists and is not empty; pass --force to write into it", Kind.CANT_CREATE)
    spec = _point_spec(args)
    p = load_drive(args.drive)
    d = _load_data(args, spec, p)
    try:
        diag, arrays = diagnose(d, p, args.holdout)
    except ValueError as exc:  # a --holdout the data cannot serve
        raise CmcanError(str(exc), Kind.USAGE) from None
    try:
        files = rep.write(out, diag, d, arrays, plots=not args.no_plots)
    except OSError as exc:
        raise CmcanError(f"{out}: cannot write the report: {exc.strerror or exc}", Kind.CANT_CREATE) from None
    if args.json:
        sys.stdout.write(rep.to_json(diag) + "\n")
        return 0
    gb, ga, u = diag.before, diag.after, diag.unit
    level = f"; confidence {diag.confidence.level}" if diag.confidence else ""
    print(f"{args.real}: {diag.verdict}{level}")
    for f in diag.fitted:
        print("  " + ", ".join(f"{f.name}.{q.name} = {q.value:.4g} ± {q.uncertainty:.2g} {q.unit}" for q in f.params))
    for flag in diag.flags:
        print(f"  flag: {flag.message}")
    choice = rep.choice_text(diag)
    if choice:
        print(f"  {choice}")
    print(f"  judged: {rep.coverage_text(diag)}")
    print(
        f"  gap {gb.rmse:.3g} {u} ({gb.rmse_pct:.2f} %) -> {ga.rmse:.3g} {u}; withheld ({diag.holdout.spec}, "
        f"{diag.holdout.judged_points} judged) {gb.heldout_rmse:.3g} -> {ga.heldout_rmse:.3g} "
        f"({100 * ga.heldout_reduction:.0f} % less)"
    )
    if diag.holdout.degenerate:
        print(f"  hold-out: {diag.holdout.degenerate}")
    dom = diag.where.dominant
    if dom is not None:
        print(f"  most of the gap at {dom.variable} {dom.lo:.4g}..{dom.hi:.4g}")
    print("  wrote " + ", ".join(str(f) for f in files))
    return 0


def run_bench(args: argparse.Namespace) -> int:
    _need_scipy()
    from dataclasses import asdict

    from cmcan.gap import bench

    if args.trials < 1:
        raise CmcanError("--trials must be at least 1", Kind.USAGE)
    if args.minutes < 1:
        raise CmcanError("--minutes must be at least 1", Kind.USAGE)
    if args.jobs < 1:
        raise CmcanError("--jobs must be at least 1", Kind.USAGE)
    s = bench.summarize(bench.run(args.seed, args.trials, args.minutes, args.jobs))
    if args.json:
        out = asdict(s)
        for row, lv in zip(out["by_level"], s.by_level, strict=True):
            row["rate"] = lv.rate
        for key in ("single_right", "single_high", "none_right", "two_found", "outside_unnamed", "region_located"):
            out[key]["rate"] = getattr(s, key).rate
        print_json(out)
        return 0
    for line in bench_table(s, args):
        print(line)
    return 0


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.1f} %"


def bench_table(s: Any, args: argparse.Namespace) -> list[str]:
    """The bench's summary as Markdown tables; every rate with the trials it counts (k/n)."""
    singles = s.single_right.n
    lines = [
        f"cmcan gap bench --trials {args.trials} --seed {args.seed}: {s.trials} trials on the dynamic simulator",
        "",
        "| figure | trials (rate) |",
        "|---|---|",
        f"| single effects named right | {s.single_right} |",
        f"| single effects answered with high confidence | {s.single_high} |",
        f"| median withheld gap reduction (single effects) | {_pct(s.median_heldout_reduction_single)} "
        f"(median of {singles}) |",
        f"| ambiguous answers among single effects | {s.ambiguous_single}/{singles} |",
        f"| no effect: answered right | {s.none_right} |",
        f"| two effects: both found | {s.two_found} |",
        f"| outside the library: named with high confidence | {s.outside_named_high}/{s.outside_unnamed.n} |",
        f"| outside the library: nothing named | {s.outside_unnamed} |",
        f"| high-pressure leak located at high pressure | {s.region_located} |",
        "",
        "| confidence | answers naming an effect | right | rate | of them single-effect cases |",
        "|---|---|---|---|---|",
    ]
    for row in s.by_level:
        rate = f"{row.right}/{row.answers} ({_pct(row.rate)})" if row.answers else "0/0 (n/a)"
        lines.append(f"| {row.level} | {row.answers} | {row.right} | {rate} | {row.singles} |")
    lines += ["", "| single effect | trials | named right |", "|---|---|---|"]
    for name, (n, right) in s.by_effect.items():
        lines.append(f"| {name} | {n} | {right} |")
    return lines


def run_effects(args: argparse.Namespace) -> int:
    from cmcan.gap.effects import LIBRARY

    lib = [e.describe() for e in LIBRARY.values()]
    if args.json:
        print_json(lib)
    else:
        for e in lib:
            pars = ", ".join(f"{q['name']} [{q['unit']}] {q['plausible']}" for q in e["parameters"])
            print(f"{e['name']:<26} {e['kind']:<9} {e['formula']:<50} {pars}")
    return 0
