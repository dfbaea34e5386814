"""Benchmark: wall time to simulate one hour of drive operation at sensor rates (100 Hz).

Target: under 10 s on the project's machine (2 cores). Printed next to a baseline run side by side:
a bare Python loop of the same number of steps with one multiply-add per step, the floor of any
per-step Python integrator. The ratio (simulator / bare loop) does not depend on the machine's speed.

    python bench/bench_sim.py [--hours 1.0]
"""

from __future__ import annotations

import argparse
import time

from cmcan.can.dbc import load_dbc
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run
from cmcan.sim.run import simulate


def bare_loop(n: int) -> float:
    x = 0.0
    for i in range(n):
        x = x * 0.999 + i
    return x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--scenario", default="two_set_train", help="shipped scenario name or file")
    args = ap.parse_args()
    s = scn.load(scn.resolve(args.scenario)).with_overrides(duration_h=args.hours)
    db = load_dbc()
    t0 = time.perf_counter()
    run = simulate(s, db)
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    frames = frames_from_run(run, db)
    t_frames = time.perf_counter() - t0
    t0 = time.perf_counter()
    bare_loop(len(run))
    t_base = time.perf_counter() - t0
    per_hour = t_sim / args.hours
    print(f"scenario            {s.name} ({args.hours:g} h, {len(run)} samples at {run.sample_rate_hz:g} Hz)")
    print(f"simulate            {t_sim:8.3f} s  ({per_hour:.3f} s per simulated hour; target < 10 s)")
    print(f"encode frames       {t_frames:8.3f} s  ({len(frames)} frames)")
    print(f"baseline bare loop  {t_base:8.3f} s  (same number of steps)")
    print(f"ratio sim/baseline  {t_sim / t_base:8.1f} x")
    print(f"real-time factor    {args.hours * 3600 / t_sim:8.0f} x faster than real time")
    print(f"target met          {'yes' if per_hour < 10 else 'NO'}")


if __name__ == "__main__":
    main()
