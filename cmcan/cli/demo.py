"""``cmcan demo``: the main job on a machine with no CAN hardware."""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path
from typing import Any

from cmcan.cli.common import Subparsers
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind

DEFAULT_OUT = "cmcan-demo"
OUTPUTS = ("demo.png", "state")  # what a demo writes into its folder


def earlier_output(out: Path) -> list[str]:
    """What an earlier demo left in ``out`` (the plot, its state folder)."""
    return [name for name in OUTPUTS if (out / name).exists()]


def out_dir(arg: str | None, force: bool) -> Path:
    """Where this demo writes. A folder given with --out-dir that holds an earlier demo's output is
    refused without --force; without --out-dir the demo takes ./cmcan-demo, or where an earlier demo is
    in it the first free ./cmcan-demo-2, -3, ... (so the README's one command runs again and again,
    overwriting nothing)."""
    if arg is not None or force:
        out = Path(arg if arg is not None else DEFAULT_OUT)
        if out.exists() and not out.is_dir():
            raise CmcanError(f"{out}: exists and is not a folder", Kind.CANT_CREATE)
        taken = earlier_output(out)
        if taken and not force:
            raise CmcanError(
                f"{out}: holds an earlier demo's {' and '.join(taken)}; pass --force to overwrite them, or "
                "another --out-dir",
                Kind.CANT_CREATE,
            )
        return out
    for i in itertools.count(1):
        out = Path(DEFAULT_OUT if i == 1 else f"{DEFAULT_OUT}-{i}")
        if not out.exists() or (out.is_dir() and not earlier_output(out)):
            return out
    raise AssertionError("unreachable")


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "demo",
        help="run-to-failure demo through the real daemon on an in-process CAN bus",
        description="Simulate the 550 h run-to-failure scenario, stream its frames through the "
        "daemon (on an in-process python-can bus), and report each warning against the scheduled "
        "failures with its lead time. Exit 0 when every check passes.",
    )
    p.add_argument(
        "--out-dir",
        help=f"folder for the plot and the demo's state; an earlier demo's output there is kept unless --force "
        f"(default ./{DEFAULT_OUT}, or the first of ./{DEFAULT_OUT}-2, -3, ... without an earlier demo in it)",
    )
    p.add_argument("--force", action="store_true", help="overwrite an earlier demo's output in --out-dir")
    p.add_argument("--burst-s", type=float, default=5.0, help="seconds of data per burst (default 5)")
    p.add_argument("--every-min", type=float, default=30.0, help="operating minutes between bursts (default 30)")
    p.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
    p.add_argument("--no-plot", action="store_true", help="skip the plot")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cmcan.cli.errors import require_extra
    from cmcan.demo import run_demo

    if not args.no_plot:  # before the minute-long run, not after it
        try:
            require_extra("plot", "matplotlib")
        except CmcanError as exc:
            raise CmcanError(f"{exc}; or run it without the plot: cmcan demo --no-plot", exc.kind) from None
    out = out_dir(args.out_dir, args.force)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CmcanError(f"{out}: cannot create the demo folder: {exc.strerror}", Kind.CANT_CREATE) from None
    if not args.json:
        print(
            f"cmcan demo: simulating run_to_failure and streaming it through the daemon "
            f"({args.burst_s:g} s of data every {args.every_min:g} min of operation) into {out}/ ...",
            flush=True,
        )
    res = run_demo(out, args.burst_s, args.every_min, plot=not args.no_plot, config_path=args.config)
    d = res.to_dict()
    d["out_dir"] = str(out)
    if not args.no_plot:
        d["plot"] = str(out / "demo.png")
    if args.json:
        print_json(d)
    else:
        print(
            f"{res.frames_sent} frames sent, {res.frames_processed} processed by the daemon on {res.bus}, "
            f"{res.wall_s:.0f} s"
        )
        w = res.windows
        print(
            f"(time-lapse: filter {w['filter_samples']} samples, debounce {w['debounce_s']:g} s of evaluated "
            "operation, scaled to the demo's sampling density)"
        )
        if res.baseline:  # the on-board baseline's states as CM_BASELINE carried them
            states = ", ".join(f"{name} from {h:.1f} h" for h, name in res.baseline)
            print(f"the machine's own baseline (CM_BASELINE): {states}")
        print("warnings on the bus (CM_WARNING):")
        for t in res.transitions:
            print(f"  {t['operating_h']:8.1f} h  {t['from']:>5} -> {t['to']:<5} ({t['reason']})")
        eol = res.end_of_life
        if eol:
            print(f"end of life the prognosis counts to: {eol['configured_text']}: {eol['why']}")
            print(f"  (a machine's default: {eol['default_text']}; what it gives on this run is beside each failure)")
        print("scheduled failures:")
        for f in res.failures:
            if f["first_warning_h"] is None:
                print(f"  {f['fail_h']:8.1f} h  {f['component']} {f['kind']}: NO warning before it")
            else:
                print(
                    f"  {f['fail_h']:8.1f} h  {f['component']} {f['kind']}: {f['level']} warning at "
                    f"{f['first_warning_h']:.1f} h, lead time {f['lead_h']:.1f} h"
                )
            pg = f.get("prognosis")
            if pg is not None and pg.get("to_eol_h"):
                p10, p50, p90 = pg["to_eol_h"]
                print(
                    f"             CM_PROGNOSIS at {pg['at_h']:.1f} h: {pg['state']}, {p50:.1f} h to end of life "
                    f"(10-90 %: {p10:.1f}-{p90:.1f} h), truth {pg['truth_h']:.1f} h"
                )
            elif pg is not None:
                print(f"             CM_PROGNOSIS at {pg['at_h']:.1f} h: {pg['state'] or 'nothing'} (no trend)")
            dd = f.get("prognosis_default_eol")
            if dd is not None:
                print(f"             with the default end of life: {_default_eol_line(dd)}")
        for name, ok in res.checks.items():
            print(f"  [{'ok' if ok else 'FAIL'}] {name}")
        if not args.no_plot:
            print(f"plot: {out / 'demo.png'}")
    return 0 if res.passed else 1


def _default_eol_line(dd: dict[str, Any]) -> str:
    reached = dd["reached_h"]
    when = (
        f"the ratio reached it at {reached:.1f} h ({reached - dd['at_h']:.1f} h later)"
        if reached is not None
        else "the ratio did not reach it before the failure"
    )
    if dd["to_eol_h"] is None:
        return f"at {dd['at_h']:.1f} h {dd['state'] or 'nothing'} (no trend); {when}"
    p10, p50, p90 = ("never" if x is None else f"{x:.1f}" for x in dd["to_eol_h"])
    return f"at {dd['at_h']:.1f} h {p50} h to end of life (10-90 %: {p10}-{p90} h); {when}"
