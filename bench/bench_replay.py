"""Benchmark: replay throughput, the limit of reading the log, memory, the J1939 machine, and the
daemon's CPU per frame.

Side by side over the same candump log (1 million frames by default), each end to end with the
timeline (``--out``) and the emitted frames (``--emit``) written:
- baseline: a plain python-can ``LogReader`` loop with cantools ``decode_message`` on every frame;
- the streaming engine (``cmcan replay --engine streaming``): frame by frame, as the daemon;
- the columnar engine (``cmcan replay``, the default): the log in chunks of arrays;
- the limit: reading and parsing the log into arrays alone, and the columnar engine's share of it;
- where the columnar time goes: the engine alone on the log's chunks already in memory (its output
  columns made, nothing written: the ceiling if reading and writing cost nothing), and the CPU of
  each stage run on its own (reading + parsing, the engine, formatting and writing the two files),
  against the replay's wall time on two threads besides the engine's.
The baseline and the columnar engine run in alternating rounds (``--rounds``), the best of each
counting, as timeit does; the columnar engine once more with numpy alone, as an install without a
C compiler for its reading and writing helpers has it. All outputs are compared byte for byte.
Then the peak RSS of ``cmcan replay`` with ``--out`` and ``--emit`` on a 4-million-frame log, per
engine (a process each; the columnar one with and without the C helpers).

Then the same scenario on the example J1939 machine (29-bit identifiers matched on PGN, message
counters and checksums checked, DM1): its time per frame against the 11-bit machine's through each
engine (the columnar one, and the streaming one, the daemon's core), in rounds of every machine back
to back (``--repeat`` of them, three times as many for the short columnar runs): the median of the
rounds' ratios (and the best of each machine's times), once more without the checksum checks and
without checks and DM1 to tell the 29-bit path's cost from the checks' and the diagnostics'. Each
round runs the 11-bit log twice: how far the log differs from itself between runs (the median of
|ratio - 1|) is the noise, and "no slower" means a median ratio not above 1 by more than that;
and both engines' outputs compared on it. Last, the daemon's loop (recv, core, send) on an
in-memory bus against a bare recv loop, in CPU seconds per frame, in ``--daemon-rounds`` alternating
rounds: the best, the median and the spread between runs of the same code (the noise figure;
``bench_daemon_instructions.py`` counts instructions instead, which do not drift).

Targets: columnar >= 20x the baseline; the 4 M-frame replay under 150 MB RSS; the J1939 machine no
slower per frame than the 11-bit one; the daemon's CPU per received frame <= 10 us.

    python bench/bench_replay.py [--frames 1000000] [--big-frames 4000000] [--repeat 5] [--config FILE] [--log PATH]
                                 [--daemon-rounds 5]

``--config FILE`` (with ``--log``, or a simulated log through that configuration) measures that
machine only, without the J1939 comparison.
"""

from __future__ import annotations

import argparse
import filecmp
import importlib.util
import math
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import can

from cmcan import config as cfgmod
from cmcan.assemble import assemble, bus_plan, dbc_for
from cmcan.can.frame import FrameColumns
from cmcan.daemon.loop import Daemon, DaemonOptions
from cmcan.io import native
from cmcan.io.candump import write_candump
from cmcan.io.columns import column_chunks
from cmcan.monitor.tick import TickColumns
from cmcan.replay import EmitWriter, ReplaySummary, TimelineWriter, replay_columns, replay_file
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run
from cmcan.sim.run import simulate

ROOT = Path(__file__).resolve().parents[1]
J1939_CONFIG = ROOT / "config" / "j1939-example.yaml"


def make_log(path: Path, n_frames: int, cfg: cfgmod.Config) -> None:
    """``n_frames`` of the excavator-like run on this machine's bus (its identifiers, channels,
    counters and checksums), about 310 input frames per second; a long log repeats up to two hours
    of simulation with shifted times, written in pieces (the 4 M-frame log stays small in memory)."""
    db = dbc_for(cfg)
    plan = bus_plan(cfg, db)
    base = scn.load(scn.shipped("two_set_validation"))
    hours = min(2.0, n_frames / 310 / 3600 + 0.01)
    f = frames_from_run(simulate(base.with_overrides(duration_h=hours), db, plan.mapping), db, plan=plan)
    chans, ext = f.channels(cfg.bus.channel), f.is_extended()
    span = float(f.timestamp_s[-1] - f.timestamp_s[0]) + 0.01
    written = 0
    rep = 0
    with open(path, "w", encoding="ascii") as out:
        while written < n_frames:
            k = min(n_frames - written, len(f))
            part = path.with_name(f"{path.name}.part")
            write_candump(
                part, f.timestamp_s[:k] + rep * span, f.arbitration_id[:k], f.dlc[:k], f.data[:k], chans[:k], ext[:k]
            )
            out.write(part.read_text())
            part.unlink()
            written += k
            rep += 1


@contextmanager
def numpy_only() -> Iterator[None]:
    """The columnar replay as an install without a C compiler has it: numpy reads and writes."""
    saved, native.LIB = native.LIB, None
    try:
        yield
    finally:
        native.LIB = saved


def timed(fn):
    t0 = time.perf_counter()
    r = fn()
    return time.perf_counter() - t0, r


def peak_rss_mb(args: list[str], env: dict[str, str] | None = None) -> tuple[float, float]:
    """Peak RSS (MB) and wall time of a command run as its own process."""
    t0 = time.perf_counter()
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            "import resource, subprocess, sys; "
            "subprocess.run(sys.argv[1:], check=True, stdout=subprocess.DEVNULL); "
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)",
            *args,
        ],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    return int(r.stdout.strip()) / 1024.0, time.perf_counter() - t0


def gateway_env(tmp: Path) -> dict[str, str]:
    """The environment of a gateway's install (runtime dependencies only): python-can imports
    asammdf, and with it pandas, whenever it is installed (the ``mf4`` extra, part of ``test``),
    which a gateway does not have; here its import fails as it would there."""
    block = tmp / "no-mf4"
    block.mkdir(exist_ok=True)
    (block / "asammdf.py").write_text("raise ImportError('asammdf is not on a gateway')\n")
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(block), os.environ.get("PYTHONPATH")]))}


def engine_run(cfg: cfgmod.Config, log: Path, out: Path, engine: str) -> ReplaySummary:
    """One replay with ``--out`` and ``--emit``, into ``out``.csv and ``out``.emit.log."""
    mon = assemble(cfg).monitor
    sinks = [TimelineWriter(out.with_suffix(".csv"), cfg.quantity), EmitWriter(out.with_suffix(".emit.log"))]
    return replay_file(log, mon, sinks, engine=engine)


class Keep:
    """A sink that keeps what the engine gives it (the engine's output made, nothing written)."""

    wants_ticks = wants_frames = True

    def __init__(self) -> None:
        self.t0 = 0.0
        self.tick_chunks: list[TickColumns] = []
        self.frame_chunks: list[FrameColumns] = []

    def start(self, t0: float) -> None:
        self.t0 = t0

    def ticks(self, chunk: TickColumns) -> None:
        self.tick_chunks.append(chunk)

    def frames(self, frames: FrameColumns) -> None:
        self.frame_chunks.append(frames)

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


def stages(cfg: cfgmod.Config, log: Path, out: Path, t_naive: float, t_col: float, n_frames: int) -> None:
    """The columnar replay's stages one at a time on this thread (CPU seconds, best of 3): reading and
    parsing, the engine on chunks in memory, the two writers on the engine's output; and the engine's
    wall time alone, the ceiling of anything done to reading and writing."""
    cpu = time.process_time
    chunks: list[FrameColumns] = []
    best = {"parse": math.inf, "engine": math.inf, "engine_wall": math.inf, "write": math.inf}
    for _ in range(3):
        c0 = cpu()
        chunks = list(column_chunks(log))
        best["parse"] = min(best["parse"], cpu() - c0)
    keep = Keep()
    for _ in range(3):
        keep = Keep()
        mon = assemble(cfg).monitor
        c0, w0 = cpu(), time.perf_counter()
        replay_columns(mon, chunks, [keep])
        best["engine"] = min(best["engine"], cpu() - c0)
        best["engine_wall"] = min(best["engine_wall"], time.perf_counter() - w0)
    for _ in range(3):
        sinks = [TimelineWriter(out.with_suffix(".csv"), cfg.quantity), EmitWriter(out.with_suffix(".emit.log"))]
        c0 = cpu()
        for s in sinks:
            s.start(keep.t0)
        for tc in keep.tick_chunks:
            sinks[0].ticks(tc)
        for fc in keep.frame_chunks:
            sinks[1].frames(fc)
        for s in sinks:
            s.close()
        best["write"] = min(best["write"], cpu() - c0)
    total = best["parse"] + best["engine"] + best["write"]
    wall = best["engine_wall"]
    print(
        f"columnar engine alone (in memory) {wall:7.2f} s {n_frames / wall:11.0f} frames/s  {t_naive / wall:6.1f} x "
        f"baseline  (its output made, nothing read or written: the ceiling of reading and writing)"
    )
    print(
        f"CPU per stage on its own          parse {best['parse']:.3f} s + engine {best['engine']:.3f} s + "
        f"write {best['write']:.3f} s = {total:.3f} s; the replay took {t_col:.3f} s wall on 2 cores"
    )


def same_output(a: Path, b: Path, sa: ReplaySummary, sb: ReplaySummary) -> bool:
    return (
        filecmp.cmp(a.with_suffix(".csv"), b.with_suffix(".csv"), shallow=False)
        and filecmp.cmp(a.with_suffix(".emit.log"), b.with_suffix(".emit.log"), shallow=False)
        and sa.counters == sb.counters
        and sa.warnings == sb.warnings
    )


class MemoryBus(can.BusABC):
    def __init__(self, msgs: list[can.Message]) -> None:
        super().__init__(channel="memory")
        self.msgs = msgs
        self.i = 0
        self.sent = 0

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.i >= len(self.msgs):
            return None, False
        self.i += 1
        return self.msgs[self.i - 1], False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent += 1


def _bare_recv_cpu(msgs: list[can.Message]) -> float:
    """CPU seconds per frame of a bare recv loop over the in-memory bus."""
    bare = MemoryBus(msgs)
    c0 = time.process_time()
    while bare.recv(0) is not None:
        pass
    c = time.process_time() - c0
    bare.shutdown()
    return c / len(msgs)


def _daemon_loop_cpu(cfg: cfgmod.Config, msgs: list[can.Message]) -> tuple[float, int]:
    """CPU seconds per frame of the daemon's loop (recv, core, send) over the in-memory bus, and the
    frames it sent."""
    mon = assemble(cfg).monitor
    bus = MemoryBus(msgs)
    daemon = Daemon(cfg, mon, None, lambda: bus, options=DaemonOptions(idle_after_s=3600))
    th = threading.Thread(target=daemon.run)
    c0 = time.process_time()
    th.start()
    while mon.counters["frames_total"] < len(msgs):
        time.sleep(0.05)
    c = time.process_time() - c0
    daemon.stop()
    th.join()
    return c / len(msgs), bus.sent


def daemon_cpu(cfg: cfgmod.Config, log: Path, rounds: int = 5) -> tuple[float, float]:
    """The daemon's CPU per received frame against a bare recv loop, in ``rounds`` alternating rounds;
    prints each side's best, median and worst and the spread between runs of the same code (the
    noise figure: on a shared machine it is larger than most changes). Returns the daemon's best and
    median, in us."""
    msgs = list(can.LogReader(str(log)))
    daemon_us, bare_us, sent = [], [], 0
    for _ in range(rounds):
        bare_us.append(_bare_recv_cpu(msgs) * 1e6)
        d, sent = _daemon_loop_cpu(cfg, msgs)
        daemon_us.append(d * 1e6)
    for name, xs in (("daemon CPU per received frame", daemon_us), ("bare recv loop CPU per frame", bare_us)):
        best, med, worst = min(xs), statistics.median(xs), max(xs)
        print(
            f"{name:<33} best {best:6.2f} us, median {med:6.2f}, worst {worst:6.2f} over {rounds} rounds"
            f" (spread {worst / best - 1:4.0%})"
        )
    print(
        f"daemon / bare loop: {statistics.median(daemon_us) / statistics.median(bare_us):.1f} x (medians);"
        f" {sent} frames sent for {len(msgs)} received"
    )
    return min(daemon_us), statistics.median(daemon_us)


def j1939_comparison(base_cfg: cfgmod.Config, log: Path, tmp: Path, n_frames: int, repeat: int) -> tuple[bool, bool]:
    """The J1939 machine against the 11-bit one, per frame, through each engine (the columnar one,
    ``cmcan replay``'s default, and the streaming one, the daemon's core); both engines' outputs on
    the J1939 log. Returns (per-frame target met by both engines, outputs identical)."""
    j_cfg = cfgmod.load(J1939_CONFIG)
    j_log = tmp / "bench-j1939.log"
    make_log(j_log, n_frames, j_cfg)
    no_cs = {k: replace(m, checksum="none") for k, m in j_cfg.messages.items()}
    # as the 11-bit machine checks its inputs: message counters, no checksums, no DM1
    no_dm1 = replace(j_cfg.j1939, dm1=replace(j_cfg.j1939.dm1, enabled=False))
    no_features = replace(j_cfg, messages=no_cs, j1939=no_dm1)
    machines = {
        "11-bit": (base_cfg, log),
        "J1939": (j_cfg, j_log),
        "J1939, no checksum": (replace(j_cfg, messages=no_cs), j_log),
        "J1939, no cs/DM1": (no_features, j_log),  # the 29-bit path alone
        "11-bit, again": (base_cfg, log),  # the same log once more: how far a log differs from itself
    }
    best: dict[tuple[str, str], float] = {}
    frames: dict[str, int] = {}
    # per round: J1939 against the mean of the round's two 11-bit runs, and those two against each other
    rounds: dict[str, list[float]] = {"columnar": [], "streaming": []}
    same_log: dict[str, list[float]] = {"columnar": [], "streaming": []}
    for engine in ("columnar", "streaming"):
        # rounds of every machine back to back: the best of each, and each round's ratio (the columnar
        # engine's runs are short and spread more: three times the rounds)
        for _ in range(3 * repeat if engine == "columnar" else repeat):
            this: dict[str, float] = {}
            for name, (cfg, path) in machines.items():
                run = lambda cfg=cfg, path=path, e=engine: replay_file(path, assemble(cfg).monitor, [], engine=e)  # noqa: E731
                t, s = timed(run)
                best[engine, name] = min(best.get((engine, name), float("inf")), t)
                frames[name] = s.counters["frames_total"]
                this[name] = t / frames[name]
            a, a2 = this["11-bit"], this["11-bit, again"]
            rounds[engine].append(this["J1939"] / ((a + a2) / 2))
            same_log[engine].append(a2 / a)
    parse: dict[str, float] = {}
    for _ in range(repeat):  # the text alone: a 29-bit identifier is 8 hex digits in a candump line, not 3
        for name, path in (("11-bit", log), ("J1939", j_log)):
            parse[name] = min(parse.get(name, float("inf")), timed(lambda p=path: sum(map(len, column_chunks(p))))[0])
    met = True
    for engine in ("columnar", "streaming"):
        per = {name: best[engine, name] / frames[name] for name in machines}
        per["11-bit"] = min(per["11-bit"], per.pop("11-bit, again"))
        for name in per:
            print(f"per frame, {engine:<9} {name:<18} {per[name] * 1e6:6.3f} us  (best of {len(rounds[engine])})")
        ratio = per["J1939"] / per["11-bit"]
        r = sorted(rounds[engine])
        median = statistics.median(r)
        # "no slower": not above 1 by more than the 11-bit log differs from itself between two runs
        noise = statistics.median(abs(x - 1.0) for x in same_log[engine])
        ok = median <= 1.0 + noise
        met = met and ok
        print(
            f"ratio J1939/11-bit, {engine:<9}   {median:7.3f} x  median of {len(r)} rounds ({r[0]:.3f}..{r[-1]:.3f}; "
            f"best against best {ratio:.3f} x); the 11-bit log against itself differs by {noise:.3f} "
            f"(median): no slower {'yes' if ok else 'NO'}  (target: <= 1 + that)"
        )
        print(
            f"  without its checksum checks "
            f"{per['J1939, no checksum'] / per['11-bit']:.2f} x (the TSC1 checks: "
            f"{(per['J1939'] - per['J1939, no checksum']) * 1e6:+.3f} us/frame); the 29-bit path alone "
            f"(counters, no checksum, no DM1) {per['J1939, no cs/DM1'] / per['11-bit']:.2f} x"
        )
    p11, pj = parse["11-bit"] / frames["11-bit"], parse["J1939"] / frames["J1939"]
    gap = best["columnar", "J1939"] / frames["J1939"] - best["columnar", "11-bit"] / frames["11-bit"]
    print(
        f"reading + parsing alone per frame: 11-bit {p11 * 1e6:.3f} us, J1939 {pj * 1e6:.3f} us "
        f"({j_log.stat().st_size / log.stat().st_size:.2f} x the bytes): {(pj - p11) * 1e6:+.3f} us/frame "
        f"of the columnar engine's {gap * 1e6:+.3f} us/frame"
    )
    t_s, s_s = timed(lambda: engine_run(j_cfg, j_log, tmp / "j_streaming", "streaming"))
    t_c, s_c = timed(lambda: engine_run(j_cfg, j_log, tmp / "j_columnar", "columnar"))
    same = same_output(tmp / "j_streaming", tmp / "j_columnar", s_s, s_c)
    print(
        f"J1939 log, --out --emit: streaming {t_s:.2f} s, columnar {t_c:.2f} s; "
        f"outputs {'identical' if same else 'DIFFERENT'}"
    )
    return met, same


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--big-frames", type=int, default=4_000_000, help="log size for the memory figure (0: skip)")
    ap.add_argument("--repeat", type=int, default=5, help="J1939 comparison: rounds of replays of each log")
    ap.add_argument("--rounds", type=int, default=3, help="baseline against columnar: rounds, the best of each")
    ap.add_argument("--config", help="measure this machine only (default: the shipped 11-bit one, then J1939)")
    ap.add_argument("--log", type=Path, help="use this log instead of simulating one")
    ap.add_argument("--daemon-rounds", type=int, default=5, help="daemon CPU: alternating rounds (best, median)")
    args = ap.parse_args()
    cfg = cfgmod.load(args.config)
    db = dbc_for(cfg)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        log = args.log or tmp / "bench.log"
        if args.log is None:
            make_log(log, args.frames, cfg)

        def naive() -> int:
            n = 0
            for msg in can.LogReader(str(log)):
                db.decode_message(msg.arbitration_id, msg.data)
                n += 1
            return n

        # the baseline and the columnar engine in alternating rounds, the best of each (as timeit)
        t_naive = t_col = t_numpy = math.inf
        for _ in range(args.rounds):
            t, n = timed(naive)
            t_naive = min(t_naive, t)
            t, s_col = timed(lambda: engine_run(cfg, log, tmp / "columnar", "columnar"))
            t_col = min(t_col, t)
            with numpy_only():
                t, s_np = timed(lambda: engine_run(cfg, log, tmp / "numpy", "columnar"))
            t_numpy = min(t_numpy, t)
        t_parse, _ = timed(lambda: sum(len(c) for c in column_chunks(log)))
        t_stream, s_stream = timed(lambda: engine_run(cfg, log, tmp / "streaming", "streaming"))
        same = same_output(tmp / "streaming", tmp / "columnar", s_stream, s_col) and same_output(
            tmp / "streaming", tmp / "numpy", s_stream, s_np
        )
        fps = lambda t: n / t  # noqa: E731
        print(
            f"log                               {n} frames, {log.stat().st_size / 1e6:.1f} MB, "
            f"{s_col.counters['ticks']} ticks, {s_col.frames_emitted} frames emitted"
        )
        print(
            f"C helpers (reading, writing)      {'built: ' + native.LIB_NAME if native.LIB else 'NOT built: numpy'}; "
            f"baseline and columnar: best of {args.rounds} alternating rounds"
        )
        print(f"baseline LogReader+decode_message {t_naive:7.2f} s {fps(t_naive):11.0f} frames/s")
        print(
            f"streaming engine (--out, --emit)  {t_stream:7.2f} s {fps(t_stream):11.0f} frames/s  "
            f"{t_naive / t_stream:6.1f} x baseline"
        )
        print(
            f"columnar engine  (--out, --emit)  {t_col:7.2f} s {fps(t_col):11.0f} frames/s  "
            f"{t_naive / t_col:6.1f} x baseline  (target >= 20 x)"
        )
        print(
            f"  the same, numpy only            {t_numpy:7.2f} s {fps(t_numpy):11.0f} frames/s  "
            f"{t_naive / t_numpy:6.1f} x baseline  (an install without a C compiler; CMCAN_NATIVE=0)"
        )
        print(
            f"limit: reading + parsing alone    {t_parse:7.2f} s {fps(t_parse):11.0f} frames/s  "
            f"= {100 * t_parse / t_col:4.0f} % of the columnar engine's time"
        )
        print(f"engines' outputs byte for byte    {'identical' if same else 'DIFFERENT'}")
        stages(cfg, log, tmp / "stages", t_naive, t_col, n)

        rss_ok = True
        if args.big_frames:
            big = tmp / "big.log"
            make_log(big, args.big_frames, cfg)
            runs = [("columnar", True, "1"), ("columnar", True, "0"), ("streaming", True, "1")]
            if importlib.util.find_spec("asammdf") is not None:
                runs.append(("columnar", False, "1"))
            for name, gateway, c_helpers in runs:
                cmd = [sys.executable, "-m", "cmcan", "replay", str(big), "--engine", name, "--force"]
                cmd += ["--out", str(tmp / f"big_{name}.csv"), "--emit", str(tmp / f"big_{name}.emit.log")]
                if args.config:
                    cmd += ["--config", args.config]
                env = gateway_env(tmp) if gateway else dict(os.environ)
                env["CMCAN_NATIVE"] = c_helpers
                rss, wall = peak_rss_mb(cmd, env)
                if name == "columnar" and gateway:
                    rss_ok = rss_ok and rss < 150
                how = "runtime deps" if gateway else "+mf4 extra"
                if name == "columnar" and c_helpers == "0":
                    how += ", numpy only"
                print(
                    f"peak RSS, {args.big_frames / 1e6:.0f} M frames, {name:<9} {rss:7.1f} MB  ({wall:.1f} s, {how})"
                    + ("  (target < 150 MB)" if name == "columnar" and gateway else "")
                    + ("  (python-can imports asammdf and pandas)" if not gateway else "")
                )
            big.unlink()

        j_ok = j_same = None
        if args.config is None and args.log is None:
            j_ok, j_same = j1939_comparison(cfg, log, tmp, args.frames, args.repeat)
        d_best, d_median = daemon_cpu(cfg, log, args.daemon_rounds)
    verdict = [
        f"columnar >= 20x {'yes' if t_naive / t_col >= 20 else 'NO'}",
        f"outputs identical {'yes' if same else 'NO'}",
        f"RSS {'yes' if rss_ok else 'NO'}" if args.big_frames else "",
        f"J1939 per frame {'yes' if j_ok else 'NO'}, J1939 outputs identical {'yes' if j_same else 'NO'}"
        if j_ok is not None
        else "",
        f"daemon CPU/frame <= 10 us: best {'yes' if d_best <= 10 else 'NO'} ({d_best:.2f}),"
        f" median {'yes' if d_median <= 10 else 'NO'} ({d_median:.2f})",
    ]
    print("targets: " + "; ".join(v for v in verdict if v))


if __name__ == "__main__":
    main()
