"""Benchmark: the fleet replay on Dask against the same work in one process, and its scaling.

A simulated fleet of ``--logs`` machines, one log of about ``--frames`` frames each (40 x 1 M by
default, written once to ``--cache``), goes through the same per-log work three ways into fresh data
sets:

- baseline: one process, no Dask, the logs one after another through the task function the workers
  run (``cmcan.fleet.task.process_log``: hash, replay with the default engine, timeline and
  summary reductions, Parquet commit);
- ``cmcan fleet replay``'s path on an embedded LocalCluster with 1 worker, then with 2 workers.

Printed: frames/s of each, Dask's overhead on 1 worker against the baseline (%), and the scaling
ratio (2 workers / 1 worker; 2.0 is perfect on 2 free cores). The machine's other load shows in the
figures: run it on a quiet machine.

    python bench/bench_fleet.py [--logs 40] [--frames 1000000] [--workers 1,2] [--cache DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

from cmcan.fleet import dataset as ds
from cmcan.fleet.run import run_fleet
from cmcan.fleet.simfleet import write_fleet
from cmcan.fleet.sources import discover
from cmcan.fleet.task import Options, process_log
from cmcan.sim.fleet import FleetSpec

FRAMES_PER_BURST = 3100  # 10 s bursts at 310 input frames per second


def fleet(cache: Path, logs: int, frames: int) -> Path:
    """The benchmark's fleet: ``logs`` machines with one log each of about ``frames`` frames."""
    out = cache / f"fleet-{logs}x{frames}"
    if (out / "manifest.csv").exists():
        return out
    hours = frames / FRAMES_PER_BURST / 3.0  # a burst every 20 min: 3 bursts per hour
    spec = FleetSpec(machines=logs, hours=round(hours, 2), seed=7, log_hours=hours + 1.0)
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    s = write_fleet(spec, out)
    print(f"fleet written: {s['logs']} logs, {s['frames'] / 1e6:.1f} M frames in {time.perf_counter() - t:.0f} s")
    return out


def single_process(jobs: list, root: Path) -> tuple[float, int]:
    ds.open_dataset(root, create=True)
    opt = Options(dataset=str(root))
    t = time.perf_counter()
    cpu = time.process_time()
    frames = 0
    for j in jobs:
        r = process_log(j, opt)
        assert r["status"] == "done", r
        frames += r["frames"]
    return time.perf_counter() - t, time.process_time() - cpu, frames


def on_dask(jobs: list, root: Path, workers: int) -> tuple[float, float, float, int]:
    """(seconds for the whole run with the cluster's start and stop, seconds of the tasks, CPU seconds
    of the tasks on the workers plus this process's (client and scheduler), frames)."""
    from cmcan.fleet.run import make_client

    t0 = time.perf_counter()
    client = make_client(None, workers)
    t1 = time.perf_counter()
    cpu_driver = time.process_time()
    task_cpu = []
    rep = run_fleet(
        jobs, Options(dataset=str(root)), client=client, progress=lambda r, _rep: task_cpu.append(r["cpu_s"])
    )
    cpu = time.process_time() - cpu_driver + sum(task_cpu)
    t2 = time.perf_counter()
    client.close()
    client.cluster.close()
    t3 = time.perf_counter()
    assert rep.counts["done"] == len(jobs), rep.to_dict()
    return t3 - t0, t2 - t1, cpu, rep.frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=40)
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "cmcan-bench-fleet")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    src = fleet(args.cache, args.logs, args.frames)
    jobs = discover([str(src / "manifest.csv")])
    work = Path(tempfile.mkdtemp(prefix="cmcan-bench-fleet-ds-"))
    res: dict = {"logs": len(jobs), "cores": os.cpu_count()}
    try:
        secs, cpu, frames = single_process(jobs, work / "single")
        res["frames"] = frames
        res["single_process"] = {"s": round(secs, 1), "cpu_s": round(cpu, 1), "frames_per_s": round(frames / secs)}
        print(
            f"single process (no Dask): {frames / 1e6:.1f} M frames in {secs:.1f} s = {frames / secs:,.0f} frames/s"
            f" ({cpu:.1f} CPU s)"
        )
        for w in [int(x) for x in args.workers.split(",") if x.strip()]:
            total, tasks, cpu_w, frames_w = on_dask(jobs, work / f"dask{w}", w)
            assert frames_w == frames
            res[f"dask_{w}"] = {
                "s": round(total, 1),
                "s_tasks": round(tasks, 1),
                "cpu_s": round(cpu_w, 1),
                "frames_per_s": round(frames / total),
            }
            print(
                f"Dask, {w} worker(s): {total:.1f} s ({tasks:.1f} s running tasks) = {frames / total:,.0f} frames/s"
                f" ({cpu_w:.1f} CPU s in tasks and driver)"
            )
        if "dask_1" in res:
            over = (res["dask_1"]["s"] - res["single_process"]["s"]) / res["single_process"]["s"] * 100.0
            res["dask_overhead_pct"] = round(over, 1)
            print(f"Dask overhead on 1 worker vs the single process: {over:+.1f} % of wall-clock time")
        for w in (1, 2):
            if f"dask_{w}" in res:
                cpu_over = (res[f"dask_{w}"]["cpu_s"] / res["single_process"]["cpu_s"] - 1.0) * 100.0
                res[f"dask_{w}_cpu_overhead_pct"] = round(cpu_over, 1)
                print(f"Dask overhead with {w} worker(s) in CPU time (robust to other load): {cpu_over:+.1f} %")
        if "dask_1" in res and "dask_2" in res:
            ratio = res["dask_2"]["frames_per_s"] / res["dask_1"]["frames_per_s"]
            res["scaling_2_vs_1"] = round(ratio, 2)
            print(f"scaling 2 workers / 1 worker: {ratio:.2f}x (2.00 = perfect)")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
