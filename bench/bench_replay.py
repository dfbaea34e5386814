"""Benchmark: replay throughput, the limit of reading the log, memory, and the daemon's CPU per frame.

Side by side over the same candump log (1 million frames by default), each end to end with the
timeline (``--out``) and the emitted frames (``--emit``) written:
- baseline: a plain python-can ``LogReader`` loop with cantools ``decode_message`` on every frame;
- the streaming engine (``cmcan replay --engine streaming``): frame by frame, as the daemon;
- the columnar engine (``cmcan replay``, the default): the log in chunks of arrays;
- the limit: reading and parsing the log into arrays alone, and the columnar engine's share of it.
Both engines' outputs are compared byte for byte. Then the peak RSS of ``cmcan replay`` with
``--out`` and ``--emit`` on a 4-million-frame log, per engine (a process each), and the daemon's loop
(recv, core, send) on an in-memory bus against a bare recv loop, in CPU seconds per frame.

Targets: columnar >= 20x the baseline; the 4 M-frame replay under 150 MB RSS.

    python bench/bench_replay.py [--frames 1000000] [--big-frames 4000000] [--config FILE] [--log PATH]
"""

from __future__ import annotations

import argparse
import filecmp
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import can

from cmcan import config as cfgmod
from cmcan.assemble import assemble, dbc_for
from cmcan.daemon import Daemon, DaemonOptions
from cmcan.io.candump import write_candump
from cmcan.io.columns import column_chunks
from cmcan.replay import EmitWriter, TimelineWriter, replay_file
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run
from cmcan.sim.run import simulate


def make_log(path: Path, n_frames: int, cfg: cfgmod.Config) -> None:
    """``n_frames`` of the excavator-like run, written in pieces (the 4 M-frame log stays small in
    memory): about 310 input frames per second."""
    db = dbc_for(cfg)
    base = scn.load(scn.shipped("two_set_validation"))
    hours = min(2.0, n_frames / 310 / 3600 + 0.01)
    f = frames_from_run(simulate(base.with_overrides(duration_h=hours), db), db)
    written = 0
    span = float(f.timestamp_s[-1] - f.timestamp_s[0]) + 0.01
    with open(path, "w", encoding="ascii") as out:
        rep = 0
        while written < n_frames:
            k = min(n_frames - written, len(f))
            part = path.with_name(f"{path.name}.part")
            write_candump(part, f.timestamp_s[:k] + rep * span, f.arbitration_id[:k], f.dlc[:k], f.data[:k])
            out.write(part.read_text())
            part.unlink()
            written += k
            rep += 1


def timed(fn) -> tuple[float, object]:
    t0 = time.perf_counter()
    r = fn()
    return time.perf_counter() - t0, r


def peak_rss_mb(args: list[str]) -> tuple[float, float]:
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
    )
    return int(r.stdout.strip()) / 1024.0, time.perf_counter() - t0


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--big-frames", type=int, default=4_000_000, help="log size for the memory figure (0: skip)")
    ap.add_argument("--config", help="configuration (default: the shipped one)")
    ap.add_argument("--log", type=Path, help="use this log instead of simulating one")
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

        def parse_only() -> int:
            return sum(len(c) for c in column_chunks(log))

        def engine(name: str):
            mon = assemble(cfg).monitor
            sinks = [TimelineWriter(tmp / f"{name}.csv"), EmitWriter(tmp / f"{name}.emit.log")]
            return replay_file(log, mon, sinks, engine=name)

        t_naive, n = timed(naive)
        t_parse, _ = timed(parse_only)
        t_stream, s_stream = timed(lambda: engine("streaming"))
        t_col, s_col = timed(lambda: engine("columnar"))
        same = (
            filecmp.cmp(tmp / "streaming.csv", tmp / "columnar.csv", shallow=False)
            and filecmp.cmp(tmp / "streaming.emit.log", tmp / "columnar.emit.log", shallow=False)
            and s_stream.counters == s_col.counters
            and s_stream.warnings == s_col.warnings
        )
        fps = lambda t: n / t  # noqa: E731
        print(
            f"log                               {n} frames, {log.stat().st_size / 1e6:.1f} MB, "
            f"{s_col.counters['ticks']} ticks, {s_col.frames_emitted} frames emitted"
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
            f"limit: reading + parsing alone    {t_parse:7.2f} s {fps(t_parse):11.0f} frames/s  "
            f"= {100 * t_parse / t_col:4.0f} % of the columnar engine's time"
        )
        print(f"engines' outputs byte for byte    {'identical' if same else 'DIFFERENT'}")

        if args.big_frames:
            big = tmp / "big.log"
            make_log(big, args.big_frames, cfg)
            for name in ("columnar", "streaming"):
                cmd = [
                    sys.executable,
                    "-m",
                    "cmcan",
                    "replay",
                    str(big),
                    "--engine",
                    name,
                    "--out",
                    str(tmp / f"big_{name}.csv"),
                    "--emit",
                    str(tmp / f"big_{name}.emit.log"),
                ]
                if args.config:
                    cmd += ["--config", args.config]
                rss, wall = peak_rss_mb(cmd)
                print(
                    f"peak RSS, {args.big_frames / 1e6:.0f} M frames, {name:<9} {rss:7.1f} MB  ({wall:.1f} s)"
                    + ("  (target < 150 MB)" if name == "columnar" else "")
                )
            big.unlink()

        # The daemon: CPU seconds per received frame, its loop against a bare recv loop.
        msgs = list(can.LogReader(str(log)))
    bare = MemoryBus(msgs)
    c0 = time.process_time()
    while bare.recv(0) is not None:
        pass
    c_bare = time.process_time() - c0
    mon = assemble(cfg).monitor
    bus = MemoryBus(msgs)
    daemon = Daemon(cfg, mon, None, lambda: bus, options=DaemonOptions(idle_after_s=3600))
    th = threading.Thread(target=daemon.run)
    c0 = time.process_time()
    th.start()
    while mon.counters["frames_total"] < len(msgs):
        time.sleep(0.05)
    c_daemon = time.process_time() - c0
    daemon.stop()
    th.join()
    n = len(msgs)
    print(f"daemon CPU per received frame     {c_daemon / n * 1e6:7.2f} us  ({bus.sent} frames sent)")
    print(f"bare recv loop CPU per frame      {c_bare / n * 1e6:7.2f} us   ratio {c_daemon / c_bare:.2f} x")
    print(f"targets met: columnar {'yes' if t_naive / t_col >= 20 else 'NO'}, outputs {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
