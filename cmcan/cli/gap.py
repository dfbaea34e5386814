"""``cmcan gap``: sim-to-real gap diagnosis (diagnose, bench, effects)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from cmcan.errors import CmcanError, Kind


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "gap",
        help="sim-to-real gap diagnosis",
        description="Where the simulator departs from measured data, which unmodelled effect causes "
        "it, and how far the gap shrinks once it is added, judged on withheld data.",
    )
    gsub = p.add_subparsers(dest="gap_command", metavar="ACTION", required=True)
    d = gsub.add_parser("diagnose", help="diagnose the gap between REAL and the simulator")
    d.add_argument(
        "real",
        help="measured data: run CSV (time_s, pump_speed_rpm, pump_disp_cc, dp_bar, temp_c, "
        "motor_speed_rpm) or a CAN log read through the configuration's DBC",
    )
    d.add_argument("--out", required=True, help="folder for report.json, report.md and the plots")
    d.add_argument(
        "--drive",
        help="drive parameters (YAML with 'drive' and 'losses' sections as in a scenario); "
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
    d.add_argument("--config", help="configuration for CAN logs (default: the shipped one)")
    d.add_argument("--no-plots", action="store_true")
    d.add_argument("--force", action="store_true", help="write into an existing report folder")
    d.add_argument("--json", action="store_true", help="print report.json to stdout")
    d.set_defaults(func=run_diagnose)
    b = gsub.add_parser("bench", help="check the diagnosis on data whose effect it is not told")
    b.add_argument("--trials", type=int, default=100)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--minutes", type=float, default=20.0, help="minutes of data per trial (default 20)")
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=run_bench)
    e = gsub.add_parser("effects", help="list the candidate effects")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=run_effects)


def _need_scipy() -> None:
    try:
        import scipy.optimize  # noqa: F401
    except ImportError:
        raise CmcanError("the gap diagnosis needs scipy (pip install 'cmcan[gap]')", Kind.UNAVAILABLE) from None


def load_drive(path: str | None):
    from cmcan.sim import scenario as scn
    from cmcan.sim.physics import DriveParams

    if path is None:
        return DriveParams()
    from cmcan.schema import SchemaError, load_yaml

    try:
        raw = load_yaml(path)
        if not isinstance(raw, dict):
            raise SchemaError(path, "", "expected a mapping with 'drive' and/or 'losses'")
        unknown = set(raw) - {"drive", "losses"}
        if unknown:
            raise SchemaError(path, sorted(unknown)[0], "unknown field (known: drive, losses)")
        doc = {
            "name": "drive",
            "seed": 0,
            "duration_h": 1.0,
            "oil": {"model": "prescribed", "temp_c": 50},
            "duty": {"kind": "constant", "pump_speed_rpm": 1000, "pump_disp_pct": 50, "dp_bar": 100},
            **raw,
        }
        return scn.from_dict(doc, source=path).params
    except SchemaError as exc:
        raise CmcanError(str(exc), Kind.CONFIG) from None


def run_diagnose(args: argparse.Namespace) -> int:
    _need_scipy()
    from cmcan.assemble import dbc_for, frame_matcher
    from cmcan.cli.common import load_config
    from cmcan.gap import data as gapdata
    from cmcan.gap import report as rep
    from cmcan.gap.diagnose import diagnose
    from cmcan.model.features import DataError

    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.force:
        raise CmcanError(f"{out}: folder exists and is not empty; pass --force to write into it", Kind.CANT_CREATE)
    if not Path(args.real).exists():
        raise CmcanError(f"{args.real}: file not found", Kind.NO_INPUT)
    p = load_drive(args.drive)
    cfg = load_config(args.config)
    try:
        db = dbc_for(cfg)
        d = gapdata.load(args.real, args.quantity, cfg.gate_limits, db, cfg.signals, frame_matcher(cfg, db))
    except DataError as exc:
        raise CmcanError(str(exc), Kind.DATA) from None
    try:
        report, arrays = diagnose(d, p, args.holdout)
    except ValueError as exc:
        raise CmcanError(str(exc), Kind.USAGE) from None
    files = rep.write(out, report, d, arrays, plots=not args.no_plots)
    if args.json:
        json.dump(report, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        gb, ga = report["gap_before"], report["gap_after"]
        print(f"{args.real}: {report['verdict']}; selected: {', '.join(report['selected']) or 'none'}")
        print(
            f"  gap {gb['rmse']:.2f} {report['unit']} ({gb['rmse_pct']:.2f} %) -> {ga['rmse']:.2f} "
            f"{report['unit']}; withheld ({report['holdout']['spec']}) {gb['heldout_rmse']:.2f} -> "
            f"{ga['heldout_rmse']:.2f} ({100 * ga['heldout_reduction']:.0f} % less)"
        )
        dom = report["where"]["dominant_region"]
        print(f"  most of the gap at {dom['variable']} {dom['range'][0]:.1f}..{dom['range'][1]:.1f}")
        print("  wrote " + ", ".join(str(f) for f in files))
    return 0


def run_bench(args: argparse.Namespace) -> int:
    _need_scipy()
    from cmcan.gap.bench import run_trial, summarize

    if args.trials < 1:
        raise CmcanError("--trials must be at least 1", Kind.USAGE)
    trials = [run_trial(args.seed * 100_003 + i, minutes=args.minutes) for i in range(args.trials)]
    s = summarize(trials)
    if args.json:
        json.dump(s, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        for k, v in s.items():
            if k != "per_trial":
                print(f"{k:<45} {v if not isinstance(v, float) else f'{v:.3f}'}")
    return 0


def run_effects(args: argparse.Namespace) -> int:
    from cmcan.gap.effects import LIBRARY

    lib = [e.describe() for e in LIBRARY.values()]
    if args.json:
        json.dump(lib, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        for e in lib:
            pars = ", ".join(f"{q['name']} [{q['unit']}]" for q in e["parameters"])
            print(f"{e['name']:<20} {e['formula']:<50} {pars}")
    return 0
