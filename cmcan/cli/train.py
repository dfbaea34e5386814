"""``cmcan train``: fit the gray-box model on healthy data and write it as one ONNX file."""

from __future__ import annotations

import argparse
import logging
import math

from cmcan.cli.common import Subparsers, add_data_options, load_config, load_data
from cmcan.cli.errors import ensure_writable, require_extra
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind

log = logging.getLogger("cmcan")


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "train",
        help="train the gray-box model on healthy data (needs cmcan[train])",
        description="Train on D_trn = steady points of DATA in [--t-start-h, --t-trn-h) hours from its start "
        "(the whole run by default); residual statistics on D_tst = the steady points after --t-trn-h. DATA is "
        "a run CSV as cmcan simulate writes it, a CAN log (candump -l, .asc, .blf, ...) decoded through the "
        "configuration's DBC and signal mapping, or with --points an operating-point table (one row per "
        "operating point, e.g. a load cycle's means). Prints how many points each gate refused and why.",
    )
    p.add_argument("data", help="healthy data: run CSV, CAN log, or with --points an operating-point table")
    p.add_argument("--out", required=True, help="model file to write (.onnx)")
    p.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
    p.add_argument("--t-trn-h", type=float, help="end of the training span (hours from start; default: all)")
    p.add_argument("--t-start-h", type=float, default=0.0, help="start of the training span (default 0)")
    add_data_options(p)
    p.add_argument("--force", action="store_true", help="overwrite an existing model file")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = ensure_writable(args.out, args.force)
    if args.points and (args.t_trn_h is not None or args.t_start_h):
        raise CmcanError(
            "--t-trn-h and --t-start-h split a time series; with --points select rows with --where", Kind.USAGE
        )
    require_extra("train", "scipy")
    require_extra("train", "onnx")
    cfg = load_config(args.config)
    from cmcan.model.evaluate import HEALTHY_RATIO_BAND_PCT
    from cmcan.model.features import gate_report
    from cmcan.model.physics import TERMS
    from cmcan.model.train import train_on_points

    op, keep = load_data(args, cfg)
    t_trn_h = math.inf if args.t_trn_h is None else args.t_trn_h
    span = keep & (op.hours >= args.t_start_h) & (op.hours < t_trn_h)
    report = gate_report(op, cfg.gate_limits, span)
    try:
        blob, model, stats = train_on_points(
            op,
            t_trn_h,
            cfg.motor_disp_cc,
            source=str(args.data),
            t_start_h=args.t_start_h,
            extra_training_info={"where": list(args.where), "points_table": bool(args.points)},
            quantity=cfg.quantity,
            oil=cfg.oil,
            select=keep,
        )
    except ValueError as exc:
        detail = "\n".join(["", "gates over the training span:", *report.lines()]) if report.refused else ""
        raise CmcanError(f"{exc}{detail}", Kind.DATA) from None
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_bytes(blob)
    tmp.replace(out)
    warnings = list(model.doubts)
    lo, hi = HEALTHY_RATIO_BAND_PCT
    select = "--where" if args.points else "--t-start-h, --t-trn-h"
    if stats["points"] and not (stats["ratio_p1_pct"] >= lo and stats["ratio_p99_pct"] <= hi):
        # the model is written (the user may know better), but such data rarely make a healthy reference
        warnings.append(
            f"{stats['set']} ratio p1..p99 {stats['ratio_p1_pct']:.2f}..{stats['ratio_p99_pct']:.2f} % is outside "
            f"the {lo:g}..{hi:g} % of a model fit to a healthy drive: the data may include a worn or changing "
            f"drive, or another sender's frames; train on healthy data only ({select}) and check the model with "
            "cmcan evaluate"
        )
    summary = {
        "model": str(out),
        "quantity": cfg.quantity,
        "physics": dict(zip(TERMS, model.coef.tolist(), strict=True)),
        "eta_vol": model.eta_vol,
        "envelope": model.envelope,
        "residual_stats": stats,
        "gates": report.to_dict(),
        "warnings": warnings,
    }
    for doubt in warnings:  # the model is written: a warning, not a refusal (the physics may be unusual)
        log.warning("%s: %s", args.data, doubt)
    if args.json:
        print_json(summary)
    else:
        print(
            f"wrote {out}: {cfg.quantity} model; {stats['set']} RMSE {stats['rmse']:.4g} {stats['unit']} over "
            f"{stats['points']} steady points, "
            f"ratio p1..p99 {stats['ratio_p1_pct']:.2f}..{stats['ratio_p99_pct']:.2f} %"
        )
        print("  physics: " + ", ".join(f"{t} {c:.4g}" for t, c in summary["physics"].items()))
        print(f"  {report.passed} of {report.total} points passed the gates" + (":" if report.refused else ""))
        for line in report.lines():
            print(line)
    return 0
