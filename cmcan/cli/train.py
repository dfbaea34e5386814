"""``cmcan train``: fit the gray-box model on healthy data and write it as one ONNX file."""

from __future__ import annotations

import argparse
import json
import sys

from cmcan.cli.common import load_config, load_points
from cmcan.cli.errors import ensure_writable, require_extra
from cmcan.errors import CmcanError, Kind


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train the gray-box model on healthy data (needs cmcan[train])",
        description="Train on D_trn = steady points of DATA in [--t-start-h, --t-trn-h) hours from its start; "
        "residual statistics on D_tst = the steady points after --t-trn-h. DATA is a run CSV as cmcan simulate "
        "writes it, or a CAN log (candump -l, .asc, .blf, ...) decoded through the configuration's DBC and "
        "signal mapping.",
    )
    p.add_argument("data", help="healthy run: CSV or CAN log")
    p.add_argument("--out", required=True, help="model file to write (.onnx)")
    p.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
    p.add_argument("--t-trn-h", type=float, required=True, help="end of the training span (hours from start)")
    p.add_argument("--t-start-h", type=float, default=0.0, help="start of the training span (default 0)")
    p.add_argument("--force", action="store_true", help="overwrite an existing model file")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = ensure_writable(args.out, args.force)
    require_extra("train", "scipy")
    require_extra("train", "onnx")
    cfg = load_config(args.config)
    from cmcan.model.physics import TERMS
    from cmcan.model.train import train_on_points

    op = load_points(args.data, cfg)
    try:
        blob, model, stats = train_on_points(
            op, args.t_trn_h, cfg.motor_disp_cc, source=str(args.data), t_start_h=args.t_start_h
        )
    except ValueError as exc:
        raise CmcanError(str(exc), Kind.DATA) from None
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_bytes(blob)
    tmp.replace(out)
    summary = {
        "model": str(out),
        "physics": dict(zip(TERMS, model.coef.tolist(), strict=True)),
        "eta_vol": model.eta_vol,
        "envelope": model.envelope,
        "residual_stats": stats,
    }
    if args.json:
        json.dump(summary, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(
            f"wrote {out}: {stats['set']} RMSE {stats['rmse']:.2f} {stats['unit']} over "
            f"{stats['points']} steady points, "
            f"ratio p1..p99 {stats['ratio_p1_pct']:.2f}..{stats['ratio_p99_pct']:.2f} %"
        )
    return 0
