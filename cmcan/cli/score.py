"""``cmcan score``: the CM ratio of every operating point of a data file, one row per point."""

from __future__ import annotations

import argparse
import csv
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cmcan.cli.common import Subparsers, add_data_options, load_config, load_data, load_model
from cmcan.cli.errors import ensure_writable, require_extra
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind

SCORE_COLUMNS = ("cm_ratio_pct", "predicted", "extra_leak_lpm", "status")
# A worn drive reads a few percent low before it stops working: a median outside this is no wear but
# data that do not match the configuration (a unit, a column), said as a warning.
PLAUSIBLE_MEDIAN_PCT = (50.0, 150.0)
log = logging.getLogger("cmcan")


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "score",
        help="the CM ratio of every operating point of a data file (CSV out, JSON summary)",
        description="Gate every operating point of DATA as the monitor does and score those that pass with "
        "the model: the output CSV has the input's columns (a table's own, or a time series' time, role means "
        "and ground truth) plus cm_ratio_pct, predicted (in the quantity's unit), extra_leak_lpm and status "
        "(evaluated, extrapolated = outside the training envelope, or gated:<reason>). No point that passes "
        "the gates is dropped.",
    )
    p.add_argument("data", help="run CSV, CAN log, or with --points an operating-point table")
    p.add_argument("--out", required=True, help="scores CSV to write")
    p.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
    p.add_argument("--model", help="model file (default: the configuration's)")
    add_data_options(p)
    p.add_argument(
        "--label",
        metavar="COLUMN=HEALTHY",
        help="summarize per value of this label column, with the AUC of each value against the healthy one",
    )
    p.add_argument("--plot", help="write the ratio per point (coloured by --label) to this PNG")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=run)


def _label(args: argparse.Namespace) -> tuple[str, float] | None:
    if not args.label:
        return None
    col, sep, value = args.label.partition("=")
    try:
        if not sep or not col.strip():
            raise ValueError
        return col.strip(), float(value)
    except ValueError:
        raise CmcanError(
            f"--label {args.label!r}: expected COLUMN=HEALTHY_VALUE, e.g. pump_leak=0", Kind.USAGE
        ) from None


def _fmt(v: float, digits: int = 6) -> str:
    return "" if not math.isfinite(v) else f"{v:.{digits}g}"


# Times in fixed decimals: epoch seconds to the microsecond (a log's own resolution) and operating
# hours to 3.6 us; significant digits would round an epoch time to whole seconds.
FIXED_DECIMALS = {"time_s": 6, "operating_h": 9}


def _column_formatter(name: str) -> Callable[[float], str]:
    decimals = FIXED_DECIMALS.get(name)
    if decimals is None:
        return lambda v: _fmt(v, 10)
    return lambda v: "" if not math.isfinite(v) else f"{v:.{decimals}f}"


def write_scores(path: Path, names: list[str], rows: list[list[str]]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(names)
        w.writerows(rows)
    tmp.replace(path)


def run(args: argparse.Namespace) -> int:
    out = ensure_writable(args.out, args.force)
    plot_path = ensure_writable(args.plot, args.force) if args.plot else None
    if plot_path is not None:
        require_extra("plot", "matplotlib")
    if plot_path is not None and plot_path.resolve() == out.resolve():
        raise CmcanError("--plot and --out name the same file", Kind.USAGE)
    label = _label(args)
    cfg = load_config(args.config)
    import numpy as np

    from cmcan.assemble import envelope_for
    from cmcan.model.score import score, summary

    model = load_model(cfg, args.model)
    op, keep = load_data(args, cfg, envelope_for(cfg, model.envelope))
    op = op.select(keep)
    if len(op) == 0:
        raise CmcanError(f"{args.data}: no operating points left to score (check --where)", Kind.DATA)
    s = score(model, op, cfg.lpm_per_unit, cfg.gate_limits)
    cols = op.columns()
    labels = None
    if label is not None:
        if label[0] not in cols:
            raise CmcanError(f"--label {label[0]}: no such column; there are {', '.join(cols)}", Kind.USAGE)
        labels = cols[label[0]]
    status = s.status()
    if op.is_table:
        names = [*op.header, *SCORE_COLUMNS]
        lead = [list(c) for c in op.cells]
    else:
        names = [*cols, *SCORE_COLUMNS]
        lead = np.column_stack([cols[c] for c in cols]).tolist()
        fmts = [_column_formatter(c) for c in cols]
        lead = [[f(v) for f, v in zip(fmts, row, strict=True)] for row in lead]
    rows = [
        [*lead[i], _fmt(s.ratio_pct[i]), _fmt(s.predicted[i]), _fmt(s.extra_leak_lpm[i]), status[i]]
        for i in range(len(op))
    ]
    write_scores(out, names, rows)
    th = cfg.thresholds
    result: dict[str, Any] = {
        "data": str(args.data),
        "model": str(model.path),
        "quantity": cfg.quantity,
        "out": str(out),
        **summary(s, th.low_pct, th.high_pct, labels, None if label is None else label[1]),
    }
    if label is not None:
        result["label"] = {"column": label[0], "healthy": label[1]}
    if plot_path is not None:
        from cmcan.plots import plot_scores

        x = op.rows.astype(float) if op.is_table else op.hours
        r = s.rated
        plot_scores(
            x[r],
            s.ratio_pct[r],
            None if labels is None else labels[r],
            s.extrapolated[r],
            th.low_pct,
            th.high_pct,
            plot_path,
            f"data row of {Path(args.data).name}" if op.is_table else "operating hours (h)",
            "" if label is None else label[0],
            title=f"CM ratio per operating point: {Path(args.data).name}",
        )
        result["plot"] = str(plot_path)
    if args.json:
        print_json(result)
    else:
        print(_text(result))
    rated = result["ratio"]
    if not rated["points"]:  # the scores say why per point; a run that rates nothing is not a success
        gated = ", ".join(f"{k} {n}" for k, n in result["status"]["gated"].items()) or "none"
        raise CmcanError(
            f"{args.data}: none of its {result['points']} points could be rated (gated: {gated}); "
            f"each point's status is in {out}",
            Kind.DATA,
        )
    measured = op.measured[s.rated]
    if len(measured) > 1 and not np.ptp(measured) > 0.0:
        log.warning(
            "%s: the measured %s is %g at every rated point: a stuck sensor or a constant column; the ratios "
            "only follow the model's prediction",
            args.data,
            cfg.quantity,
            float(measured[0]),
        )
    median = rated["ratio_p50_pct"]
    if not PLAUSIBLE_MEDIAN_PCT[0] <= median <= PLAUSIBLE_MEDIAN_PCT[1]:
        log.warning(
            "%s: the median CM ratio is %.1f %%: no drive that still runs is that far from its model; check the "
            "data's units and columns against the configuration (the output %s, pressures in bar, speeds in rpm, "
            "temperatures in degrees C)",
            args.data,
            median,
            cfg.quantity,
        )
    return 0


def _text(r: dict[str, Any]) -> str:
    st = r["status"]
    gated = ", ".join(f"{k} {n}" for k, n in st["gated"].items()) or "none"
    lines = [
        f"wrote {r['out']}: {r['points']} points, {st['evaluated']} evaluated, {st['extrapolated']} extrapolated "
        f"(outside the training envelope), {r['without_ratio']} without a ratio (gated: {gated})"
    ]
    f = r["ratio"]
    if f["points"]:
        lo, hi = r["thresholds_pct"]
        lines.append(
            f"  ratio p1 {f['ratio_p1_pct']:.2f} %, median {f['ratio_p50_pct']:.2f} %, p99 {f['ratio_p99_pct']:.2f} %;"
            f" {f['below_low_pct']:.1f} % of points below {lo:g} %, {f['above_high_pct']:.1f} % above {hi:g} %"
        )
    for v, g in r.get("labels", {}).items():
        if not g["points"]:
            lines.append(f"  {r['label']['column']} = {v}: no rated points")
            continue
        if "auc_vs_healthy" not in g:
            auc = " (healthy)"
        elif g["auc_vs_healthy"] is None:
            auc = ", no AUC (no healthy point rated to compare with)"
        else:
            auc = f", AUC vs healthy {g['auc_vs_healthy']:.4f}"
        lines.append(
            f"  {r['label']['column']} = {v}: {g['points']} points, median {g['ratio_p50_pct']:.2f} %, "
            f"{g['below_low_pct']:.1f} % below {r['thresholds_pct'][0]:g} %{auc}"
        )
    return "\n".join(lines)
