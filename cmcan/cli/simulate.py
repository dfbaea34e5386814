"""``cmcan simulate``: a scenario to a run CSV and, optionally, a candump log."""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cmcan.cli.common import Subparsers
from cmcan.cli.errors import ensure_writable
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind
from cmcan.roles import MOTOR_SPEED

if TYPE_CHECKING:
    from cmcan.sim.fleet import FleetSpec

_log = logging.getLogger("cmcan.simulate")


def shipped_scenarios() -> list[str]:
    """The names of the shipped scenarios, in ``cmcan.sim.scenario.shipped_dir()``: found without
    importing the simulator, which the parser does not need (numpy, cantools)."""
    from cmcan import sim

    return sorted(p.stem for p in (Path(sim.__file__).resolve().parent / "scenarios").glob("*.yaml"))


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate a drive scenario to CSV and candump log",
        description="Simulate a scenario (a YAML file, or the name of a shipped one: "
        + ", ".join(shipped_scenarios())
        + ") and write the run as CSV and, with --candump, as a candump -l log. "
        "`cmcan simulate fleet --machines N --hours H --out DIR` writes a whole fleet instead: logs of N "
        "machines of a few drive sizes (each type with its configuration and model), a manifest and the "
        "ground truth (docs/fleet.md).",
    )
    p.add_argument("scenario", help="scenario YAML file or shipped scenario name, or 'fleet'")
    p.add_argument("--out", required=True, help="run CSV to write (for fleet: the folder to write)")
    p.add_argument("--candump", help="also write the input frames as a candump -l log")
    p.add_argument(
        "--channel",
        help="channel name in the candump log for frames on bus.channel (default: the configuration's bus.channel, "
        "can0 without --config); messages the configuration puts on other channels keep theirs",
    )
    p.add_argument("--dbc", help="DBC to encode frames with (default: the shipped dbc/cmcan.dbc)")
    p.add_argument(
        "--config",
        help="write the frames as this machine sends them: its DBC, signal mapping, channels, identifiers "
        "(11- or 29-bit, J1939 source addresses), alive counters and checksums",
    )
    p.add_argument("--seed", type=int, help="override the scenario's seed")
    p.add_argument("--duration-h", type=float, help="override the scenario's duration (hours)")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.add_argument("--json", action="store_true", help="print a summary as JSON")
    f = p.add_argument_group("fleet (with SCENARIO = fleet)")
    f.add_argument("--machines", type=int, help="number of machines")
    f.add_argument("--hours", type=float, help="operating hours of each machine")
    f.add_argument("--degrading-share", type=float, default=0.5, help="share of machines that degrade (0.5)")
    f.add_argument("--log-hours", type=float, default=24.0, help="operating hours per log file (24)")
    f.add_argument("--burst-s", type=float, default=10.0, help="time-lapse: seconds sampled per burst (10)")
    f.add_argument("--every-min", type=float, default=20.0, help="time-lapse: one burst every N minutes (20)")
    f.add_argument("--types", metavar="T[,T...]", help="machine types in turn (compact, mid, large; default all three)")
    f.add_argument("--oil-c", metavar="LO,HI", help="range of each machine's mean oil temperature, C (45,70)")
    f.add_argument(
        "--oil-swing-c", metavar="LO,HI", help="range of the swing of its oil temperature over 10 h, +- C (5,20)"
    )
    f.add_argument(
        "--unit-spread",
        type=float,
        nargs="?",
        const=1.0,
        metavar="SCALE",
        help="unit-to-unit variation: each machine its own displacements, healthy leakage and sensor errors "
        "within datasheet tolerances, times SCALE (1; docs/simulator.md)",
    )
    f.add_argument("--arriving-leaks", type=int, metavar="N", help="N healthy machines arrive leaking from hour 0")
    f.add_argument(
        "--arriving-leak-pct", metavar="LO,HI", help="their leak, %% of the type's rated flow at 480 bar (4,8)"
    )
    p.set_defaults(func=run)


FLEET_ONLY = (
    "machines",
    "hours",
    "types",
    "oil_c",
    "oil_swing_c",
    "unit_spread",
    "arriving_leaks",
    "arriving_leak_pct",
)


def run(args: argparse.Namespace) -> int:
    if args.scenario == "fleet":
        return run_fleet(args)
    from cmcan.can.dbccache import load_compiled
    from cmcan.io.candump import write_candump
    from cmcan.io.runcsv import write_run_csv
    from cmcan.schema import SchemaError
    from cmcan.sim import scenario as scn
    from cmcan.sim.frames import frames_from_run
    from cmcan.sim.run import simulate

    used = [f"--{k.replace('_', '-')}" for k in FLEET_ONLY if getattr(args, k) is not None]
    if used:
        raise CmcanError(f"{', '.join(used)} only apply to `cmcan simulate fleet`", Kind.USAGE)
    out = ensure_writable(args.out, args.force)
    log = ensure_writable(args.candump, args.force) if args.candump else None
    path = scn.resolve(args.scenario)
    if not path.exists():
        raise CmcanError(f"{args.scenario}: no such scenario file or shipped scenario", Kind.NO_INPUT)
    try:
        s = scn.load(path)
        top = {}
        if args.seed is not None:
            top["seed"] = args.seed
        if args.duration_h is not None:
            top["duration_h"] = args.duration_h
        if top:
            s = s.with_overrides(**top)
    except SchemaError as exc:
        exc.kind = Kind.DATA if exc.kind == Kind.CONFIG else exc.kind  # a scenario is data, not configuration
        raise
    if args.config and args.dbc:
        raise CmcanError("give --config or --dbc, not both (the configuration names its DBC)", Kind.USAGE)
    plan = None
    channel = args.channel or "can0"
    if args.config:
        from cmcan.assemble import bus_plan, check_against_dbc, dbc_for
        from cmcan.daemon.preflight import load_config

        cfg = load_config(args.config)
        if cfg.quantity != MOTOR_SPEED:
            raise CmcanError(
                f"{cfg.source}: drive.quantity is {cfg.quantity}: the simulator models a closed-circuit drive, "
                f"whose output is the motor speed ({MOTOR_SPEED}); a flow machine's frames cannot be simulated",
                Kind.USAGE,
            )
        db = dbc_for(cfg)
        check_against_dbc(cfg, db)
        for diff in scn.drive_differences(s.params, cfg.motor_disp_cc, cfg.drive.pump_disp_max_cc, cfg.oil):
            # frames of another drive through this machine's DBC: its model reads them as worn or mispositioned
            _log.warning(
                "%s: the simulated drive is not the machine of %s: %s; give the scenario the machine's drive: "
                "and fluid: sections (docs/simulator.md)",
                path,
                cfg.source,
                diff,
            )
        plan = bus_plan(cfg, db)
        channel = args.channel or cfg.bus.channel
    else:
        db = load_compiled(args.dbc)
    r = simulate(s, db, plan.mapping if plan is not None else None)
    write_run_csv(out, r.columns)
    n_frames = 0
    if log is not None:
        f = frames_from_run(r, db, plan=plan)
        n_frames = write_candump(
            log, f.timestamp_s, f.arbitration_id, f.dlc, f.data, channel=f.channels(channel), extended=f.is_extended()
        )
    summary = {
        "scenario": s.name,
        "samples": len(r),
        "bursts": r.meta["bursts"],
        "operating_h": float(r["operating_h"][-1]) if len(r) else 0.0,
        "csv": str(out),
        "candump": str(log) if log else None,
        "frames": n_frames,
        "scheduled_failures": r.meta["scheduled_failures"],
    }
    if args.json:
        print_json(summary)
    else:
        print(
            f"{s.name}: {len(r)} samples ({summary['operating_h']:.2f} h) -> {out}"
            + (f", {n_frames} frames -> {log}" if log else "")
        )
    return 0


def run_fleet(args: argparse.Namespace) -> int:
    from cmcan.cli.errors import require_extra

    require_extra("train", "onnx")
    require_extra("train", "scipy")
    from cmcan.fleet.simfleet import remove_outputs, write_fleet

    if args.machines is None or args.hours is None:
        raise CmcanError("simulate fleet needs --machines N and --hours H", Kind.USAGE)
    for opt in ("candump", "dbc", "duration_h"):
        if getattr(args, opt) is not None:
            raise CmcanError(f"--{opt.replace('_', '-')} does not apply to `cmcan simulate fleet`", Kind.USAGE)
    spec = fleet_spec(args)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CmcanError(f"{out}: exists and is not a folder", Kind.CANT_CREATE)
    if args.force and out.is_dir():
        remove_outputs(out)
    summary = write_fleet(spec, out, force=args.force, progress=None if args.json else print)
    summary["next"] = next_commands(out)
    if args.json:
        print_json(summary)
    else:
        print(
            f"{out}: {summary['machines']} machines ({summary['degrading']} degrading), {summary['logs']} logs, "
            f"{summary['frames'] / 1e6:.1f} M frames; manifest.csv and truth.json beside them"
        )
        print(
            "next (the folder is read through its manifest.csv: each machine with its type's configuration and "
            "model):\n" + "".join(f"  {c}\n" for c in summary["next"]),
            end="",
        )
    return 0


def fleet_spec(args: argparse.Namespace) -> FleetSpec:
    """The fleet the options ask for, checked (a usage error names what is wrong)."""
    from cmcan.sim.fleet import FleetSpec, UnitSpread

    extra: dict[str, Any] = {}
    if args.types is not None:
        extra["types"] = tuple(t.strip() for t in args.types.split(",") if t.strip())
    for opt, key in (
        ("oil_c", "oil_temp_c"),
        ("oil_swing_c", "oil_swing_c"),
        ("arriving_leak_pct", "arriving_leak_pct"),
    ):
        if getattr(args, opt) is not None:
            extra[key] = _pair(f"--{opt.replace('_', '-')}", getattr(args, opt))
    if args.unit_spread is not None:
        if not (math.isfinite(args.unit_spread) and args.unit_spread >= 0):
            raise CmcanError(f"simulate fleet: --unit-spread SCALE must be >= 0, got {args.unit_spread}", Kind.USAGE)
        extra["spread"] = UnitSpread().scaled(args.unit_spread)
    if args.arriving_leaks is not None:
        extra["arriving_leaks"] = args.arriving_leaks
    spec = FleetSpec(
        machines=args.machines,
        hours=args.hours,
        seed=args.seed if args.seed is not None else 1,
        degrading_share=args.degrading_share,
        burst_s=args.burst_s,
        every_min=args.every_min,
        log_hours=args.log_hours,
        **extra,
    )
    try:
        spec.check()
    except ValueError as exc:
        raise CmcanError(f"simulate fleet: {exc}", Kind.USAGE) from None
    return spec


def _pair(opt: str, text: str) -> tuple[float, float]:
    parts = text.split(",")
    try:
        lo, hi = (float(x) for x in parts)
    except ValueError:
        raise CmcanError(f"simulate fleet: {opt} expects LO,HI (two numbers), got {text!r}", Kind.USAGE) from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise CmcanError(f"simulate fleet: {opt} expects finite numbers, got {text!r}", Kind.USAGE)
    return lo, hi


def next_commands(out: Path) -> list[str]:
    """What to run on a simulated fleet: replay it (through its manifest) and report on it."""
    import shlex

    name = str(out).rstrip("/") or "."
    ds = f"{name}-ds"
    return [
        f"cmcan fleet replay {shlex.quote(name)} --out {shlex.quote(ds)}",
        f"cmcan fleet report {shlex.quote(ds)} --out {shlex.quote(name + '-report.html')}",
    ]
