"""``cmcan fleet train``: a machine-type model from many machines' healthy operating points in the data set."""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from pathlib import Path
from typing import Any

from cmcan.cli.common import Subparsers
from cmcan.cli.errors import ensure_writable, require_extra
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind

log = logging.getLogger("cmcan")


def add_parser(fsub: Subparsers) -> None:
    t = fsub.add_parser(
        "train",
        help="a machine-type model from many machines' healthy points in the data set (needs cmcan[train])",
        description="Fit one model for the machines of --machine-type (from --types FILE, a CSV machine,type as "
        "`cmcan simulate fleet` writes it, or the machines named with --machine) on their healthy timeline rows: "
        "every tick evaluated inside the envelope, a finite operating point, warning level ok, before the "
        "machine's first ratio warning (and --until-h). Same fit as `cmcan train`; the unit-to-unit spread "
        "(each machine's mean residual in l/min) goes into the model's training metadata (docs/fleet.md). A machine "
        "whose offset is far from the others' (more than 3.5 robust SDs from their median: it arrives leaking, or "
        "its displacement is set high) is named and left out of the fit and the spread; --keep keeps it.",
    )
    t.add_argument("dataset", help="data set folder (cmcan fleet replay --out)")
    t.add_argument("--machine-type", required=True, metavar="TYPE", help="the type to train (its name is recorded)")
    who = t.add_mutually_exclusive_group(required=True)
    who.add_argument("--types", metavar="FILE", help="CSV with columns machine,type: the machines of TYPE")
    who.add_argument("--machine", action="append", metavar="ID", help="a machine of TYPE (repeat for several)")
    t.add_argument("--exclude", action="append", default=[], metavar="ID", help="leave a machine out (repeat)")
    t.add_argument(
        "--keep", action="append", default=[], metavar="ID", help="never leave this machine out as an outlier (repeat)"
    )
    t.add_argument("--until-h", type=float, help="only rows before this operating hour of each machine")
    t.add_argument("--min-points", type=int, default=20, help="healthy points each machine must have (default 20)")
    t.add_argument("--out", required=True, help="model file to write (.onnx)")
    t.add_argument("--force", action="store_true", help="overwrite an existing model file")
    t.add_argument("--scheduler", help="address of an existing Dask scheduler (default: an embedded LocalCluster)")
    t.add_argument("--workers", type=int, help="worker processes of the embedded cluster (default: one per core)")
    t.add_argument(
        "--no-verify", action="store_true", help="do not hash the timeline files against their commit records"
    )
    t.add_argument("--json", action="store_true", help="print the summary as JSON")
    t.set_defaults(func=run)


def _check_options(args: argparse.Namespace) -> None:
    if args.workers is not None and args.workers < 1:
        raise CmcanError(f"--workers: expected at least 1, got {args.workers}", Kind.USAGE)
    if args.scheduler and args.workers:
        raise CmcanError("--workers sizes the embedded cluster; it does not apply with --scheduler", Kind.USAGE)
    if args.until_h is not None and not (math.isfinite(args.until_h) and args.until_h > 0):
        raise CmcanError(f"--until-h: expected a positive number of hours, got {args.until_h}", Kind.USAGE)
    if args.min_points < 1:
        raise CmcanError(f"--min-points: expected at least 1, got {args.min_points}", Kind.USAGE)
    if not args.machine_type.strip():
        raise CmcanError("--machine-type: expected a type name", Kind.USAGE)


def _selected(args: argparse.Namespace) -> list[str]:
    from cmcan.fleet import dataset as ds
    from cmcan.fleet.train import machines_of_type, read_types

    if args.types:
        if not Path(args.types).is_file():
            raise CmcanError(f"--types {args.types}: file not found", Kind.NO_INPUT)
        chosen = machines_of_type(read_types(args.types), args.machine_type, args.types)
    else:
        chosen = sorted(set(args.machine))
    for m in (*chosen, *args.exclude, *args.keep):
        ds.check_machine(
            m, "--exclude" if m in args.exclude else "--keep" if m in args.keep else (args.types or "--machine")
        )
    for option, named in (("--exclude", args.exclude), ("--keep", args.keep)):
        stray = [m for m in named if m not in chosen]
        if stray:
            raise CmcanError(
                f"{option} {', '.join(stray)}: not a machine of type {args.machine_type} ({', '.join(chosen)})",
                Kind.USAGE,
            )
    both = sorted(set(args.exclude) & set(args.keep))
    if both:
        raise CmcanError(f"--exclude and --keep both name {', '.join(both)}", Kind.USAGE)
    return [m for m in chosen if m not in args.exclude]


def _write_atomic(out: Path, blob: bytes) -> None:
    import uuid  # here: the parser imports this module

    tmp = out.with_name(f".{out.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        tmp.write_bytes(blob)
        os.replace(tmp, out)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise CmcanError(f"{out}: cannot write the model: {exc.strerror or exc}", Kind.CANT_CREATE) from None


def run(args: argparse.Namespace) -> int:
    out = ensure_writable(args.out, args.force)
    _check_options(args)
    require_extra("fleet", "distributed")
    require_extra("fleet", "pyarrow")
    require_extra("train", "scipy")
    require_extra("train", "onnx")
    from cmcan.fleet import dataset as ds
    from cmcan.fleet.points import drive_facts, gather_points, machine_logs
    from cmcan.fleet.train import check_points, common_facts, fit_type, selection_info

    root = ds.open_dataset(Path(args.dataset), create=False)
    chosen = _selected(args)
    have = set(ds.machines_in(root, ds.SUMMARY_TABLE))
    if not have:
        raise CmcanError(f"{root}: no committed log in the data set (run cmcan fleet replay first)", Kind.NO_INPUT)
    absent = [m for m in chosen if m not in have]
    logs = [machine_logs(root, m) for m in chosen if m in have]
    logs = [lg for lg in logs if lg.records]
    if not logs:
        raise CmcanError(
            f"{root}: no logs of the machines of type {args.machine_type} ({', '.join(chosen) or 'none'})",
            Kind.NO_INPUT,
        )
    for m in absent:
        print(
            f"cmcan fleet train: machine {m} (type {args.machine_type}) has no logs in {root}: left out",
            file=sys.stderr,
        )
    facts = common_facts({lg.machine: drive_facts(lg, str(root)) for lg in logs}, str(root))
    until_h = math.inf if args.until_h is None else args.until_h
    points = gather_points(root, logs, until_h, not args.no_verify, args.scheduler, args.workers)
    check_points(points, args.min_points, str(root))
    selection = selection_info(args.until_h, args.exclude, args.min_points)
    try:
        res = fit_type(points, facts, args.machine_type, str(root), selection, keep=args.keep)
    except ValueError as exc:
        raise CmcanError(f"{root}: type {args.machine_type}: {exc}", Kind.DATA) from None
    _write_atomic(out, res.blob)
    summary = _summary(out, args.machine_type, facts, points, res, absent)
    for doubt in summary["warnings"]:  # the model is written: a warning, as cmcan train gives it
        log.warning("%s: %s", out, doubt)
    if args.json:
        print_json(summary)
    else:
        _print(summary)
    return 0


def _summary(
    out: Path, machine_type: str, facts: Any, points: list[Any], res: Any, absent: list[str]
) -> dict[str, Any]:
    from cmcan.model.physics import TERMS

    spread = res.training["unit_spread"]
    offset = {**spread["per_machine"], **spread["outliers"]}
    return {
        "model": str(out),
        "machine_type": machine_type,
        "quantity": facts.quantity,
        "motor_disp_cc": facts.motor_disp_cc,
        "machines": {
            mp.machine: {
                "points": len(mp),
                "rows": mp.rows,
                "refused": mp.refused,
                "offset_lpm": offset[mp.machine]["offset_lpm"],
                "reference_offset_lpm": spread["reference"].get("offset_lpm", {}).get(mp.machine),
                "left_out": spread["outliers"].get(mp.machine, {}).get("why"),
            }
            for mp in points
        },
        "absent": absent,
        "physics": dict(zip(TERMS, res.model.coef.tolist(), strict=True)),
        "residual_stats": res.residual_stats,
        "unit_spread": spread,
        "warnings": list(res.model.doubts),
    }


def _print(s: dict[str, Any]) -> None:
    st, sp = s["residual_stats"], s["unit_spread"]
    vm = f", V_M {s['motor_disp_cc']:g} cm3/rev" if s["motor_disp_cc"] is not None else ""
    print(
        f"wrote {s['model']}: type {s['machine_type']} model ({s['quantity']}{vm}) from {sp['machines']} machines, "
        f"{st['points']} healthy points; RMSE {st['rmse']:.4g} {st['unit']}, "
        f"ratio p1..p99 {st['ratio_p1_pct']:.2f}..{st['ratio_p99_pct']:.2f} %"
    )
    worst = max(sp["per_machine"], key=lambda m: abs(sp["per_machine"][m]["offset_lpm"]))
    print(
        f"  unit spread: offset SD {sp['offset_sd_lpm']:.3g} l/min over {sp['machines']} machines, "
        f"largest |offset| {sp['offset_max_abs_lpm']:.3g} l/min ({worst})"
    )
    ref = sp["reference"]
    if ref["applied"]:
        print(
            f"  judged against the replay model too: a machine more than {ref['bound_lpm']:.3g} l/min off it "
            "is left out"
        )
    else:
        print(f"  not judged against the replay model: {ref.get('why') or 'more than half of the machines lie off it'}")
    for m, d in s["machines"].items():
        out = f"; left out: {d['left_out']}" if d["left_out"] else ""
        vs = (
            f" ({d['reference_offset_lpm']:+.3f} against the replay model)"
            if d["reference_offset_lpm"] is not None
            else ""
        )
        print(f"  {m}: {d['points']} points of {d['rows']} rows, offset {d['offset_lpm']:+.3f} l/min{vs}{out}")
    if sp["outliers"]:
        print(f"  left out of the type ({sp['rule']}): {', '.join(sp['outliers'])}")
