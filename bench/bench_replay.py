"""Benchmark: replay throughput and the daemon's CPU time per received frame.

Side by side over the same 1-million-frame candump log:
- baseline: a plain python-can ``LogReader`` loop with cantools ``decode_message`` on every frame;
- ``cmcan replay``'s path: its candump reader (python-can's semantics, no Message objects) feeding
  the monitor core (match, health checks, decode, windows, gate, model, warnings, output frames).
Then the same scenario on the example J1939 machine (29-bit identifiers matched on PGN, message
counters and checksums checked, DM1): its replay time per frame against the 11-bit machine's, best
of ``--repeat`` runs each, interleaved; and the J1939 machine once more without its checksum checks,
to tell the cost of the 29-bit path from that of the checks. Then the daemon's loop (recv, core,
send) on an in-memory bus, against a bare recv loop on the same bus, in CPU seconds per frame.
Targets: the replay at least as fast as the baseline (ratio >= 1); the J1939 machine no slower per
frame than the 11-bit one.

    python bench/bench_replay.py [--frames 1000000] [--repeat 3] [--log PATH] [--config FILE]

``--config FILE`` (with ``--log``, or a simulated log through that configuration) measures one
machine only.
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import can

from cmcan import config as cfgmod
from cmcan.assemble import build_monitor, bus_plan, dbc_for, load_model_for
from cmcan.daemon import Daemon, DaemonOptions
from cmcan.io.candump import iter_frames, write_candump
from cmcan.replay import replay
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run
from cmcan.sim.run import simulate

ROOT = Path(__file__).resolve().parents[1]
J1939_CONFIG = ROOT / "config" / "j1939-example.yaml"


def make_log(path: Path, n_frames: int, cfg: cfgmod.Config) -> None:
    hours = n_frames / 310 / 3600 + 0.01  # 310 input frames per second
    s = scn.load(scn.shipped("two_set_validation")).with_overrides(duration_h=hours)
    db = dbc_for(cfg)
    plan = bus_plan(cfg, db)
    f = frames_from_run(simulate(s, db, plan.mapping), db, plan=plan)
    k = min(n_frames, len(f))
    f = f.select(slice(0, k))
    write_candump(path, f.timestamp_s, f.arbitration_id, f.dlc, f.data, f.channels(cfg.bus.channel), f.is_extended())


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


def time_replay(cfg: cfgmod.Config, log: Path) -> tuple[float, int, int, dict[str, int]]:
    db = dbc_for(cfg)
    mon = build_monitor(cfg, db, load_model_for(cfg))
    t0 = time.perf_counter()
    res = replay(mon, iter_frames(log), emit=True)
    return time.perf_counter() - t0, mon.counters["frames_total"], len(res.frames_out), dict(mon.counters)


def daemon_cpu(cfg: cfgmod.Config, log: Path) -> None:
    db = dbc_for(cfg)
    model = load_model_for(cfg)
    msgs = list(can.LogReader(str(log)))
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=3, help="replays of each log; the best counts (default 3)")
    ap.add_argument("--log", type=Path, help="use this log instead of simulating one")
    ap.add_argument("--config", help="measure this machine only (default: the shipped 11-bit one, then J1939)")
    args = ap.parse_args()
    base_cfg = cfgmod.load(args.config)
    with tempfile.TemporaryDirectory() as d:
        log = args.log or Path(d) / "bench.log"
        if args.log is None:
            make_log(log, args.frames, base_cfg)
        db = dbc_for(base_cfg)

        t0 = time.perf_counter()
        n_base = 0
        for msg in can.LogReader(str(log)):
            db.decode_message(msg.arbitration_id, msg.data)
            n_base += 1
        t_base = time.perf_counter() - t0

        machines = {"configured" if args.config else "11-bit": (base_cfg, log)}
        if args.config is None and args.log is None:
            j_cfg = cfgmod.load(J1939_CONFIG)
            j_log = Path(d) / "bench-j1939.log"
            make_log(j_log, args.frames, j_cfg)
            machines["J1939"] = (j_cfg, j_log)
            # the same machine and log without its TSC1 checksum checks: what the 29-bit path itself costs
            no_cs = {k: replace(m, checksum="none") for k, m in j_cfg.messages.items()}
            machines["J1939, no checksum"] = (replace(j_cfg, messages=no_cs), j_log)
        best: dict[str, float] = {}
        info: dict[str, tuple[int, int, dict[str, int]]] = {}
        for _ in range(args.repeat):
            for name, (cfg, path) in machines.items():
                t, n, emitted, counters = time_replay(cfg, path)
                best[name] = min(best.get(name, float("inf")), t)
                info[name] = (n, emitted, counters)

        first = next(iter(machines))
        print(f"log                           {n_base} frames")
        print(f"baseline LogReader+decode     {t_base:7.2f} s  {n_base / t_base:10.0f} frames/s")
        for name, t in best.items():
            n, emitted, c = info[name]
            print(
                f"cmcan replay, {name:<15} {t:7.2f} s  {n / t:10.0f} frames/s  {t / n * 1e6:6.2f} us/frame  "
                f"({c['ticks']} ticks, {c['evaluated']} evaluated, {c['accepted']} inputs accepted, {emitted} emitted)"
            )
        print(f"ratio replay/baseline speed   {t_base / best[first]:7.2f} x  (target >= 1)")
        if "J1939" in best:
            per = {k: best[k] / info[k][0] for k in best}
            print(f"ratio J1939/11-bit per frame  {per['J1939'] / per['11-bit']:7.2f} x  (target <= 1)")
            print(
                f"  without its checksum checks {per['J1939, no checksum'] / per['11-bit']:7.2f} x  "
                f"(the TSC1 checks: {(per['J1939'] - per['J1939, no checksum']) * 1e6:+.2f} us/frame)"
            )
        daemon_cpu(base_cfg, log)
    print(f"target met: replay {'yes' if t_base / best[first] >= 1 else 'NO'}", end="")
    if "J1939" in best:
        ok = best["J1939"] / info["J1939"][0] <= best["11-bit"] / info["11-bit"][0]
        print(f", J1939 per frame {'yes' if ok else 'NO'}")
    else:
        print()


if __name__ == "__main__":
    main()
