"""``cmcan evaluate``: the paper's protocol on D_trn / D_tst / D_val, figures and plots."""

from __future__ import annotations

import argparse

from cmcan.cli.common import Subparsers, add_keep_truncated, load_config, load_model, load_points
from cmcan.cli.errors import ensure_writable, require_extra
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "evaluate",
        help="evaluate a model on D_trn/D_tst/D_val",
        description="D_trn and D_tst are the TRAIN run split at --t-trn-h; D_val is the --val run, healthy "
        "before --t-dam-h and damaged after. Further healthy runs with --healthy. Exit status 0 when every "
        "check passes, 1 otherwise.",
    )
    p.add_argument("train", help="the healthy run the model was trained on (CSV or CAN log)")
    p.add_argument("--t-trn-h", type=float, required=True, help="end of training (hours from the run's start)")
    p.add_argument("--val", help="validation run that degrades after --t-dam-h")
    p.add_argument("--t-dam-h", type=float, help="damage onset in the validation run (hours from its start)")
    p.add_argument("--healthy", action="append", default=[], help="another healthy run (repeatable)")
    p.add_argument("--model", help="model file (default: the configuration's)")
    p.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    p.add_argument("--plot", help="write predicted-minus-measured over time to this PNG")
    p.add_argument("--force", action="store_true", help="overwrite an existing plot")
    add_keep_truncated(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.val and args.t_dam_h is None:
        raise CmcanError("--val needs --t-dam-h (the damage onset)", Kind.USAGE)
    plot_path = ensure_writable(args.plot, args.force) if args.plot else None
    if plot_path is not None:
        require_extra("plot", "matplotlib")
    cfg = load_config(args.config)
    from cmcan.model.evaluate import format_report, protocol

    model = load_model(cfg, args.model)
    keep = args.keep_truncated
    train_op = load_points(args.train, cfg, keep_truncated=keep)
    val_op = load_points(args.val, cfg, keep_truncated=keep) if args.val else None
    healthy = {h: load_points(h, cfg, keep_truncated=keep) for h in args.healthy}
    report, sets = protocol(model, train_op, args.t_trn_h, val_op, args.t_dam_h, healthy)
    report["model"] = str(model.path)
    if plot_path is not None:
        from cmcan.plots import plot_residuals

        plot_residuals(sets, report, plot_path)
        report["plot"] = str(plot_path)
    if args.json:
        print_json(report)
    else:
        print(format_report(report))
    return 0 if report["passed"] else 1
