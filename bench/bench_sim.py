"""Benchmark: wall time to simulate one hour of drive operation at sensor rates (100 Hz).

Target: under 10 s on the project's machine (2 cores). Printed next to a baseline run side by side:
a bare Python loop of the same number of steps with one multiply-add per step, the floor of any
per-step Python integrator. The ratio (simulator / bare loop) does not depend on the machine's speed.

Where the C helpers are built, the time integration is the C loop (``cmcan/sim/_drive_fast.c``); the
same simulation again with the Python loop it transcribes (the reference, what an install without a
C compiler or ``CMCAN_NATIVE=0`` runs), and the integrator alone on both loops, runs alternated and the
median taken, give its speed-up as a ratio.

    python bench/bench_sim.py [--hours 1.0] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

from cmcan.can.dbc import load_dbc
from cmcan.io import native
from cmcan.sim import drive
from cmcan.sim import run as sim_run
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run
from cmcan.sim.physics import DriveParams
from cmcan.sim.run import simulate


def bare_loop(n: int) -> float:
    x = 0.0
    for i in range(n):
        x = x * 0.999 + i
    return x


def side_by_side(runs: dict[str, Callable[[], object]], repeat: int) -> dict[str, float]:
    """Median wall time of each, the runs alternated."""
    times: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(repeat):
        for k, f in runs.items():
            t0 = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def integrator_inputs(n: int) -> drive.DriveInputs:
    """A wheel loader's kind of work: set points that change every 2 s, the oil from the heat balance."""
    rng = np.random.default_rng(1)
    hold = lambda lo, hi: np.repeat(rng.uniform(lo, hi, n // 200 + 1), 200)[:n]  # noqa: E731
    return drive.DriveInputs(
        hold(800.0, 2800.0),
        hold(10.0, 78.0),
        hold(0.0, 600.0),
        np.full(n, np.nan),
        np.full(n, 25.0),
        np.zeros(n),
        np.full(n, 2e-13),
        np.full(n, 1e-8),
        np.ones(n),
    )


def bench_loops(args: argparse.Namespace, s: scn.Scenario, db: object) -> None:
    if native.LIB is None or not hasattr(native.LIB, "cmcan_drive_integrate"):
        print("C loop              not built here (no C compiler, or CMCAN_NATIVE=0): the Python loop ran")
        return
    n = 100_000
    p, u, start = DriveParams(), integrator_inputs(n), drive.DriveState(100e5, 200.0, 45.0)
    t = side_by_side(
        {"c": lambda: drive.integrate(p, u, 0.01, start), "py": lambda: drive.integrate_python(p, u, 0.01, start)},
        args.repeat,
    )
    print(f"integrate, C loop   {t['c'] / n * 1e9:8.0f} ns per step  ({n} steps, median of {args.repeat})")
    print(f"integrate, Python   {t['py'] / n * 1e9:8.0f} ns per step  (the reference loop, side by side)")
    print(f"ratio Python/C loop {t['py'] / t['c']:8.1f} x")

    def with_python_loop() -> None:
        sim_run.integrate = drive.integrate_python
        try:
            simulate(s, db)
        finally:
            sim_run.integrate = drive.integrate

    t = side_by_side({"c": lambda: simulate(s, db), "py": with_python_loop}, args.repeat)
    print(f"simulate, C loop    {t['c']:8.3f} s  (median of {args.repeat})")
    print(f"simulate, Python    {t['py']:8.3f} s  (the same run with the Python loop, side by side)")
    print(f"ratio Python/C loop {t['py'] / t['c']:8.1f} x")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--scenario", default="two_set_train", help="shipped scenario name or file")
    ap.add_argument("--repeat", type=int, default=3, help="alternated runs of each loop (median)")
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
    bench_loops(args, s, db)


if __name__ == "__main__":
    main()
