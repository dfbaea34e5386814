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
        ".csv, .db, .mf4, also .gz) through the same monitor core as cmcan run, on the log's own timestamps. "
        "Several logs of one machine are its life: replayed in the order of their first frames, the monitor's "
        "state (filter, warning condition, counts, baseline, prognosis history) carried from each log to the "
        "next as the daemon carries it across a restart (not across more than a week between two logs; "
        "overlapping logs are refused); the outputs cover them all.",
    )
    p.add_argument("log", nargs="+", help="CAN log, or several logs of one machine")
    p.add_argument(
        "--state-in",
        metavar="FILE",
        help="start from this state (a daemon's state.json, or the --state-out of an earlier replay) instead of "
        "a fresh monitor",
    )
    p.add_argument(
        "--state-out",
        metavar="FILE",
        help="write the monitor's state at the end, as the daemon saves it (for the next replay's --state-in)",
    )
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
    names = ("out", "emit", "plot", "state_out")
    outs = {k: ensure_writable(getattr(args, k), args.force) for k in names if getattr(args, k)}
    if "plot" in outs:
        require_extra("plot", "matplotlib")
    logs = _logs(args.log)
    if not any(p.suffix.lower() == ".mf4" for p in logs):
        return _run(args, outs, logs)
    from cmcan.io import readproc  # (multiprocessing: only where a log is an MF4)

    if args.engine == "columnar":
        from cmcan.io.mf4columns import preload

        readproc.warm(preload)  # asammdf imported by the reader process while the monitor is built
    try:
        return _run(args, outs, logs)
    finally:
        readproc.cancel()  # the reader waiting for a next log, or one nothing took (a refused configuration)


def _run(args: argparse.Namespace, outs: dict[str, Path], logs: list[Path]) -> int:
    cfg = load_config(args.config, check_dbc=False)
    from cmcan.assemble import assemble, build_monitor
    from cmcan.monitor.totals import Totals

    aliases = channel_map(args.channel_map, cfg)
    args.channel_map_names = list(aliases)
    asm = assemble(cfg, args.model, totals=_state_in(args.state_in), log_aliases=aliases)
    mon = asm.monitor
    sinks = _Sinks(outs, cfg.quantity, prognosis=mon.prognosis is not None)
    life = [_Lasting(s) for s in sinks.all]  # one output for the whole life, closed after its last log
    summaries = []
    try:
        for i, (log, first_t) in enumerate(_in_time_order(logs)):
            if i:
                prev, prev_res = summaries[-1][0], summaries[-1][1]
                note = _carried(prev, prev_res.last_t, log, first_t)
                state = mon.save_totals().to_dict() if note is None else None
                mon = build_monitor(cfg, asm.db, asm.model, Totals.from_dict(state) if state else None, aliases)
                if note is not None:
                    print(f"cmcan replay: {log}: the state starts afresh: {note}", file=sys.stderr)
            last = mon.totals.history[-1] if mon.totals.history else None  # of the state it starts from
            res, cut = _replay(log, args, mon, life)
            assert res.first_t is not None  # a log without frames raised NoFrames, leaving no output behind
            res.warnings = res.warnings[_after(mon.totals.history, last) :]  # this log's own level changes
            summaries.append((log, res, _summary(log, args, cfg, mon, res, sinks.fit.verdict(), cut, not aliases)))
    except BaseException:
        for s in life:
            s.end(abort=True)
        raise
    for s in life:
        s.end()
    if sinks.plot is not None:
        from cmcan.plots import plot_ratio

        th = cfg.thresholds
        title = f"CM ratio: {logs[0]}" if len(logs) == 1 else f"CM ratio: {len(logs)} logs from {summaries[0][0]}"
        plot_ratio(sinks.plot.timeline, summaries[0][1].first_t, th.low_pct, th.high_pct, outs["plot"], title=title)
    if "state_out" in outs:
        _state_out(outs["state_out"], mon.save_totals())
    if args.json:
        print_json(summaries[0][2] if len(logs) == 1 else _life_summary([s for _, _, s in summaries]))
    else:
        for log, res, summary in summaries:
            _print(str(log), res, summary)
    return 0


def _after(history: list[Any], last: Any) -> int:
    """Where the level changes after ``last`` (the carried state's newest, None: none) begin in
    ``history``; 0 when the history has been trimmed past it (all are new)."""
    if last is None:
        return 0
    return next((i + 1 for i in range(len(history) - 1, -1, -1) if history[i] is last), 0)


def _logs(given: list[str]) -> list[Path]:
    logs = [Path(p) for p in given]
    for p in logs:
        if not p.exists():
            raise CmcanError(f"{p}: log file not found", Kind.NO_INPUT)
    seen: dict[Path, Path] = {}
    for p in logs:
        key = p.resolve()
        if key in seen:
            raise CmcanError(f"{p}: given twice (as {seen[key]} too): one life has each log once", Kind.USAGE)
        seen[key] = p
    return logs


def _in_time_order(logs: list[Path]) -> list[tuple[Path, float]]:
    """The logs in the order of their first frames, with those frames' times."""
    if len(logs) == 1:
        return [(logs[0], math.nan)]
    return sorted(((p, _first_stamp(p)) for p in logs), key=lambda x: x[1])


def _first_stamp(p: Path) -> float:
    from cmcan.io.candump import iter_frames

    try:
        for f in iter_frames(p, keep_truncated=True, on_cut=lambda cut: None):
            return f.timestamp_s
    except CmcanError:
        raise
    except (ValueError, OSError) as exc:
        raise CmcanError(f"{p}: cannot read as a CAN log: {exc}", Kind.DATA) from None
    raise CmcanError(f"{p}: no frames in the log", Kind.DATA)


def _carried(prev: Path, prev_last_t: float, log: Path, first_t: float) -> str | None:
    """Why the state does not carry from ``prev`` into ``log`` (None: it does), as the daemon's state
    would not after a week off; overlapping logs are refused: two recordings of one stretch are not
    one life."""
    from cmcan.fleet.chain import MAX_CARRY_GAP_H, OVERLAP_TOLERANCE_S

    gap_s = first_t - prev_last_t
    if gap_s < -OVERLAP_TOLERANCE_S:
        raise CmcanError(
            f"{log}: starts {-gap_s:.1f} s before {prev} ends: overlapping logs are not one machine's life "
            "(replay them one at a time)",
            Kind.DATA,
        )
    if gap_s > MAX_CARRY_GAP_H * 3600.0:
        return f"{gap_s / 3600.0:.1f} h after {prev} ended (more than {MAX_CARRY_GAP_H:g} h)"
    return None


def _state_in(path: str | None) -> Any:
    """--state-in: the state file read as the daemon reads one, refused (exit 65) where any part of it
    is damaged: offline, the user's file is meant whole."""
    if path is None:
        return None
    from cmcan.service.statefile import MAX_STATE_BYTES, NotAFile, TooLarge, examine, read_limited

    try:
        raw = read_limited(Path(path), MAX_STATE_BYTES)
    except FileNotFoundError:
        raise CmcanError(f"--state-in {path}: file not found", Kind.NO_INPUT) from None
    except (NotAFile, TooLarge, OSError) as exc:
        raise CmcanError(f"--state-in {path}: cannot read: {exc}", Kind.NO_INPUT) from None
    reading = examine(raw)
    if reading.damage:
        what = "; ".join(f"{d.part}: {d.problem}" for d in reading.damage)
        raise CmcanError(f"--state-in {path}: not a usable state: {what}", Kind.DATA)
    return reading.totals


def _state_out(path: Path, totals: Any) -> None:
    import json

    from cmcan.service.statefile import write_atomic

    write_atomic(path.parent, path.name, json.dumps(totals.to_dict(), indent=1).encode("utf-8"))


class _Lasting:
    """A sink kept open across the logs of one life: started at the first log's first frame, closed
    (or aborted) once, after the last."""

    def __init__(self, sink: Any) -> None:
        self.sink = sink
        self.wants_ticks, self.wants_frames = sink.wants_ticks, sink.wants_frames
        self.started = False

    def start(self, t0: float) -> None:
        if not self.started:
            self.started = True
            self.sink.start(t0)

    def ticks(self, chunk: Any) -> None:
        self.sink.ticks(chunk)

    def frames(self, frames: Any) -> None:
        self.sink.frames(frames)

    def close(self) -> None:  # the end of one log: the life goes on
        pass

    def abort(self) -> None:  # a log that failed: the whole output goes (end(abort=True) follows)
        pass

    def end(self, abort: bool = False) -> None:
        if abort or not self.started:
            self.sink.abort()
        else:
            self.sink.close()


def _life_summary(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """--json for several logs: each log's summary in time order, with the life's warnings and its end."""
    return {
        "logs": parts,
        "warnings": [{**w, "log": p["log"]} for p in parts for w in p["warnings"]],
        "final": parts[-1]["final"],
        "totals": parts[-1]["totals"],
    }


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


def _replay(log: Path, args: argparse.Namespace, mon: Any, sinks: list[Any]) -> tuple[ReplaySummary, Cut | None]:
    from cmcan.replay import replay_file

    progress = _Progress(log) if sys.stdout.isatty() and not args.json else None
    cuts: list[Cut] = []  # where a log read with --keep-truncated was cut
    try:
        res = replay_file(
            log,
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
        raise CmcanError(f"{log}: cannot read as a CAN log: {exc}", Kind.DATA) from None
    finally:
        if progress is not None:
            progress.done()
    return res, (cuts[0] if cuts else None)


def _summary(
    log: Path,
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
        "log": str(log),
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
            f"distance from the type model {b['distance_lpm']:+.2f} l/min, pressure part {b['pressure_part_lpm']:+.2f}"
            + (f" (suspect by its {' and '.join(b['suspect_by'])})" if b["suspect_by"] else "")
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
