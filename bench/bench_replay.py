"""Benchmark: replay throughput and the daemon's CPU time per received frame.

Side by side over the same 1-million-frame candump log:
- baseline: a plain python-can ``LogReader`` loop with cantools ``decode_message`` on every frame;
- ``cmcan replay``'s path: its candump reader (python-can's semantics, no Message objects) feeding
  the monitor core (decode, windows, gate, model, warnings, output frames), as ``cmcan replay`` runs.
Then the daemon's loop (recv, core, send) on an in-memory bus, against a bare recv loop on the same
bus, in CPU seconds per frame. Target: the replay at least as fast as the baseline (ratio >= 1).

    python bench/bench_replay.py [--frames 1000000] [--log PATH]
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path

import can

from cmcan import config as cfgmod
from cmcan.assemble import build_monitor, dbc_for, load_model_for
from cmcan.daemon import Daemon, DaemonOptions
from cmcan.io.candump import iter_frames, write_candump
from cmcan.replay import FrameCollector, replay
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run
from cmcan.sim.run import simulate


def make_log(path: Path, n_frames: int) -> None:
    hours = n_frames / 310 / 3600 + 0.01  # 310 input frames per second
    s = scn.load(scn.shipped("two_set_validation")).with_overrides(duration_h=hours)
    db = cfgmod.load().dbc()
    f = frames_from_run(simulate(s, db), db)
    k = min(n_frames, len(f))
    write_candump(path, f.timestamp_s[:k], f.arbitration_id[:k], f.dlc[:k], f.data[:k])


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
    ap.add_argument("--log", type=Path, help="use this log instead of simulating one")
    args = ap.parse_args()
    cfg = cfgmod.load()
    db = dbc_for(cfg)
    model = load_model_for(cfg)
    with tempfile.TemporaryDirectory() as d:
        log = args.log or Path(d) / "bench.log"
        if args.log is None:
            make_log(log, args.frames)

        t0 = time.perf_counter()
        n_base = 0
        for msg in can.LogReader(str(log)):
            db.decode_message(msg.arbitration_id, msg.data)
            n_base += 1
        t_base = time.perf_counter() - t0

        mon = build_monitor(cfg, db, model)
        t0 = time.perf_counter()
        sink = FrameCollector()
        replay(mon, iter_frames(log), [sink])
        t_replay = time.perf_counter() - t0

        msgs = list(can.LogReader(str(log)))
    print(f"log                           {n_base} frames")
    print(f"baseline LogReader+decode     {t_base:7.2f} s  {n_base / t_base:10.0f} frames/s")
    print(
        f"cmcan replay                  {t_replay:7.2f} s  {n_base / t_replay:10.0f} frames/s  "
        f"({mon.counters['ticks']} ticks, {len(sink.frames_out)} frames emitted)"
    )
    print(f"ratio replay/baseline speed   {t_base / t_replay:7.2f} x  (target >= 1)")

    # Daemon: CPU seconds per received frame, its loop against a bare recv loop on the same bus.
    bare = MemoryBus(msgs)
    c0 = time.process_time()
    while bare.recv(0) is not None:
        pass
    c_bare = time.process_time() - c0
    mon = build_monitor(cfg, db, model)
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
    print(f"daemon CPU per received frame {c_daemon / n * 1e6:7.2f} us  ({bus.sent} frames sent)")
    print(f"bare recv loop CPU per frame  {c_bare / n * 1e6:7.2f} us")
    print(f"ratio daemon/bare             {c_daemon / c_bare:7.2f} x")
    print(f"target met: replay {'yes' if t_base / t_replay >= 1 else 'NO'}")


if __name__ == "__main__":
    main()
