"""``cmcan replay``: a CAN log through the daemon's monitor core, offline."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from cmcan.assemble import assemble
from cmcan.cli.common import load_config
from cmcan.cli.errors import ensure_writable, require_extra
from cmcan.errors import CmcanError, Kind
from cmcan.io.candump import iter_frames
from cmcan.replay import replay, warnings_summary, write_emitted, write_timeline


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="run a CAN log through the monitor (timeline, emitted frames, warnings)",
        description="Run a log in any format python-can's LogReader reads (candump -l .log, .asc, .blf, .trc, "
        ".csv, .db, .mf4, also .gz) through the same monitor core as cmcan run, on the log's own timestamps.",
    )
    p.add_argument("log", help="CAN log")
    p.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
    p.add_argument("--model", help="model file (default: the configuration's)")
    p.add_argument(
        "--channel-map",
        action="append",
        default=[],
        metavar="LOG=CONFIGURED",
        help="read the log's channel LOG as the configured channel CONFIGURED (repeatable); once given, "
        "log channels not named are on no configured channel. Without it a log channel is read as the "
        "configured channel of the same name, or, with a single configured channel, as that one "
        "(channels.from_log in the configuration says the same)",
    )
    p.add_argument("--out", help="write the evaluation timeline as CSV")
    p.add_argument("--emit", help="write the frames the daemon would have sent as a candump -l log")
    p.add_argument("--plot", help="write the CM ratio over operating hours as PNG")
    p.add_argument("--json", action="store_true", help="print the summary (warnings, counters) as JSON")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=run)


def channel_map(pairs: list[str], cfg: Any) -> dict[str, str]:
    """``--channel-map LOG=CONFIGURED`` pairs, each target a configured channel (usage error otherwise)."""
    out = {}
    names = [c.name for c in cfg.channel_list]
    for pair in pairs:
        log_name, sep, target = pair.partition("=")
        if not sep or not log_name or not target:
            raise CmcanError(f"--channel-map {pair!r}: expected LOG=CONFIGURED, e.g. can0=vcan0", Kind.USAGE)
        if target not in names:
            raise CmcanError(
                f"--channel-map {pair!r}: {target!r} is not a configured channel ({', '.join(names)})", Kind.USAGE
            )
        out[log_name] = target
    return out


def run(args: argparse.Namespace) -> int:
    outs = {k: ensure_writable(getattr(args, k), args.force) for k in ("out", "emit", "plot") if getattr(args, k)}
    if "plot" in outs:
        require_extra("plot", "matplotlib")
    if not Path(args.log).exists():
        raise CmcanError(f"{args.log}: log file not found", Kind.NO_INPUT)
    cfg = load_config(args.config, check_dbc=False)
    aliases = channel_map(args.channel_map, cfg)
    mon = assemble(cfg, args.model, keep_timeline=bool(args.out or args.plot), log_aliases=aliases).monitor
    try:
        res = replay(mon, iter_frames(args.log), emit=bool(args.emit))
    except (ValueError, OSError) as exc:
        raise CmcanError(f"{args.log}: cannot read as a CAN log: {exc}", Kind.DATA) from None
    if res.first_t is None:
        raise CmcanError(f"{args.log}: no frames in the log", Kind.DATA)
    t0 = res.first_t
    if "out" in outs:
        write_timeline(outs["out"], mon.timeline, t0)
    if "emit" in outs:
        write_emitted(outs["emit"], res.frames_out)
    if "plot" in outs:
        from cmcan.plots import plot_ratio

        th = cfg.thresholds
        plot_ratio(mon.timeline, t0, th.low_pct, th.high_pct, outs["plot"], title=f"CM ratio: {args.log}")
    seen = mon.channels_seen()
    merged = sorted(k for k, v in seen.items() if v is not None and k != v)
    if len(seen) > 1 and len(cfg.channel_list) == 1 and not aliases and not cfg.channels.from_log:
        print(
            f"cmcan replay: note: the log's channels {', '.join(sorted(seen))} were all read as "
            f"{cfg.bus.channel}; give --channel-map LOG={cfg.bus.channel} to read one of them only",
            file=sys.stderr,
        )
    summary = {
        "log": str(args.log),
        "channels": {k: v for k, v in sorted(seen.items())},
        "channels_renamed": merged,
        "first_timestamp_s": t0,
        "duration_h": ((res.last_t or t0) - t0) / 3600.0,
        "warnings": warnings_summary(mon, t0),
        "final": mon.snapshot(),
        "totals": {k: v for k, v in mon.save_totals().to_dict().items() if not k.startswith("filter_")},
        "frames_emitted": len(res.frames_out) if args.emit else None,
    }
    if args.json:
        json.dump(summary, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        c = mon.counters
        print(
            f"{args.log}: {c['frames_total']} frames ({c['accepted']} inputs), {summary['duration_h']:.2f} h, "
            f"{c['evaluated']} of {c['ticks']} ticks evaluated"
        )
        for w in summary["warnings"]:
            ratio = f", filtered ratio {w['ratio_filt_pct']:.2f} %" if w["ratio_filt_pct"] is not None else ""
            print(f"  {w['operating_h']:9.3f} h  {w['from']:>5} -> {w['to']:<5} ({w['reason']}{ratio})")
        if not summary["warnings"]:
            print("  no warnings")
    return 0
