"""``cmcan replay``: a CAN log through the daemon's monitor core, offline."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cmcan.cli.common import Subparsers, add_keep_truncated, load_config
from cmcan.cli.errors import ensure_writable, require_extra
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind

if TYPE_CHECKING:  # the replay's modules are imported when it runs: the parser starts without numpy
    from cmcan.fitcheck import FitVerdict
    from cmcan.io.candump import Cut
    from cmcan.replay import ReplaySummary

# cmcan.replay.ENGINES, said here so that the parser need not import the replay (tests/test_startup.py)
ENGINES = ("columnar", "streaming")


def add_subparser(sub: Subparsers) -> None:
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
    p.add_argument(
        "--engine",
        choices=ENGINES,
        default="columnar",
        help="columnar (default): the log in chunks of arrays; streaming: frame by frame as the daemon. "
        "Both give the same output byte for byte",
    )
    p.add_argument("--json", action="store_true", help="print the summary (warnings, counters) as JSON")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    add_keep_truncated(p)
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
    from cmcan.assemble import assemble

    aliases = channel_map(args.channel_map, cfg)
    args.channel_map_names = list(aliases)
    mon = assemble(cfg, args.model, log_aliases=aliases).monitor
    sinks = _Sinks(outs, cfg.quantity, prognosis=mon.prognosis is not None)
    res, cut = _replay(args, mon, sinks.all)
    assert res.first_t is not None  # a log without frames raised NoFrames, leaving no output behind
    if sinks.plot is not None:
        from cmcan.plots import plot_ratio

        th = cfg.thresholds
        plot_ratio(
            sinks.plot.timeline, res.first_t, th.low_pct, th.high_pct, outs["plot"], title=f"CM ratio: {args.log}"
        )
    summary = _summary(args, cfg, mon, res, sinks.fit.verdict(), cut, merged_alone=not aliases)
    if args.json:
        print_json(summary)
    else:
        _print(args.log, res, summary)
    return 0


class _Sinks:
    """What the replay writes (timeline, emitted frames, the plot's ticks) and the fit check."""

    def __init__(self, outs: dict[str, Path], quantity: str, prognosis: bool = False) -> None:
        from cmcan.fitcheck import FitWindow
        from cmcan.replay import EmitWriter, TimelineCollector, TimelineWriter

        self.all: list[Any] = []
        if "out" in outs:  # the prognosis's columns where the monitor runs one
            self.all.append(TimelineWriter(outs["out"], quantity, prognosis))
        if "emit" in outs:
            self.all.append(EmitWriter(outs["emit"]))
        self.plot = TimelineCollector() if "plot" in outs else None
        if self.plot is not None:
            self.all.append(self.plot)
        self.fit = FitWindow()  # does the configuration fit this machine at all (its first operating hour)
        self.all.append(self.fit)


def _replay(args: argparse.Namespace, mon: Any, sinks: list[Any]) -> tuple[ReplaySummary, Cut | None]:
    from cmcan.replay import replay_file

    progress = _Progress(Path(args.log)) if sys.stdout.isatty() and not args.json else None
    cuts: list[Cut] = []  # where a log read with --keep-truncated was cut
    try:
        res = replay_file(
            args.log,
            mon,
            sinks,
            engine=args.engine,
            progress=progress,
            keep_truncated=args.keep_truncated,
            on_cut=cuts.append,
        )
    except CmcanError:  # a log that cannot be read names itself (truncated, corrupt, a reader missing)
        raise
    except (ValueError, OSError) as exc:
        raise CmcanError(f"{args.log}: cannot read as a CAN log: {exc}", Kind.DATA) from None
    finally:
        if progress is not None:
            progress.done()
    return res, (cuts[0] if cuts else None)


def _summary(
    args: argparse.Namespace,
    cfg: Any,
    mon: Any,
    res: ReplaySummary,
    fit: FitVerdict,
    cut: Cut | None,
    merged_alone: bool,
) -> dict[str, Any]:
    """What ``--json`` prints; notes on stderr for what the user should know."""
    from cmcan.fitcheck import DOES_NOT_FIT

    seen = mon.channels_seen()
    if len(seen) > 1 and len(cfg.channel_list) == 1 and merged_alone and not cfg.channels.from_log:
        print(
            f"cmcan replay: note: the log's channels {', '.join(sorted(seen))} were all read as "
            f"{cfg.bus.channel}; give --channel-map LOG={cfg.bus.channel} to read one of them only",
            file=sys.stderr,
        )
    if fit.verdict == DOES_NOT_FIT:
        print(f"cmcan replay: warning: {fit.describe()}", file=sys.stderr)
    for name in sorted(set(args.channel_map_names) - set(seen)):
        print(
            f"cmcan replay: warning: --channel-map names {name!r}, which the log does not have "
            f"(it has {', '.join(sorted(seen)) or 'no channel names'})",
            file=sys.stderr,
        )
    if res.counters["accepted"] == 0:
        print(f"cmcan replay: warning: {nothing_matched(mon, res.snapshot)}", file=sys.stderr)
    return {
        "log": str(args.log),
        "channels": {k: v for k, v in sorted(seen.items())},
        "channels_renamed": sorted(k for k, v in seen.items() if v is not None and k != v),
        "first_timestamp_s": res.first_t,
        "duration_h": res.duration_h,
        "warnings": res.warnings,
        "final": res.snapshot,
        "totals": res.totals,
        "frames_emitted": res.frames_emitted if args.emit else None,
        "fit": {
            "verdict": fit.verdict,
            "median_pct": _finite(fit.median_pct),
            "points": fit.points,
            "window_h": fit.window_h,
        },
        "cut": cut.to_dict() if cut is not None else None,
    }


def nothing_matched(mon: Any, snapshot: dict[str, Any]) -> str:
    """What a log had against what the configuration expects, when not one input frame was used."""
    want = "; ".join(f"{m.name} ({_what(m)} on {m.channel or 'the bus'})" for m in mon.inputs)
    has = ", ".join(_seen(u) for u in snapshot["unknown_ids"][:8])
    c = snapshot["counters"]
    other = {k: c[k] for k in ("unknown_channel", "bad_fd", "bad_length", "own_address", "error_frame") if c[k]}
    extra = "".join(f", {k.replace('_', ' ')} {v}" for k, v in other.items())
    return (
        f"not one frame of the log was an input: the configuration expects {want}; "
        f"the log's busiest other identifiers: {has or 'none'}{extra}"
    )


def _what(m: Any) -> str:
    return f"PGN 0x{m.pgn:04X}" if m.pgn is not None else f"id 0x{m.frame_id:X}"


def _seen(u: dict[str, Any]) -> str:
    j1939 = f" (PGN 0x{u['pgn']:04X} from {u['source']})" if "pgn" in u else ""
    return f"{u['id']}{j1939} x{u['frames']} on {u['channel'] or '?'}"


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _print(log: str, res: ReplaySummary, summary: dict[str, Any]) -> None:
    c = res.counters
    print(
        f"{log}: {c['frames_total']} frames ({c['accepted']} inputs), {summary['duration_h']:.2f} h, "
        f"{c['evaluated']} of {c['ticks']} ticks evaluated"
    )
    for w in summary["warnings"]:
        ratio = f", filtered ratio {w['ratio_filt_pct']:.2f} %" if w["ratio_filt_pct"] is not None else ""
        print(f"  {w['operating_h']:9.3f} h  {w['from']:>5} -> {w['to']:<5} ({w['reason']}{ratio})")
    if not summary["warnings"]:
        print("  no warnings")
    b = res.snapshot.get("baseline")
    if b is not None:  # the on-board baseline where configured (docs/commissioning.md)
        print(
            f"  baseline {b['state']}: {b['learned_h']:.2f} h learned, {b['coverage_pct']:.0f} % of the envelope, "
            f"distance from the type model {b['distance_lpm']:+.2f} l/min"
        )


class _Progress:
    """A one-line progress bar on stderr for long replays at a terminal."""

    def __init__(self, path: Path) -> None:
        self.total = max(path.stat().st_size, 1)
        self.shown = -1

    def __call__(self, done_bytes: int, frames: int) -> None:
        if done_bytes < 0:  # how far into the file is unknown: frames only
            sys.stderr.write(f"\rreplay {frames:,} frames")
            sys.stderr.flush()
            self.shown = 0
            return
        pct = min(100, int(100 * done_bytes / self.total))
        if pct != self.shown:
            self.shown = pct
            bar = "#" * (pct // 4)
            sys.stderr.write(f"\rreplay [{bar:<25}] {pct:3d} %  {frames:,} frames")
            sys.stderr.flush()

    def done(self) -> None:
        if self.shown >= 0:
            sys.stderr.write("\n")
