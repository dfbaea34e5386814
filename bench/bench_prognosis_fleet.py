"""Benchmark: the prognosis over a simulated fleet: no trend on its healthy machines, and what it says
of the degrading ones.

A fleet as ``cmcan simulate fleet`` writes it (:func:`cmcan.fleet.simfleet.write_fleet`; all three
machine types, mixed and constant duty, each machine's own oil; half of the machines degrade: motor
or pump wear, or the motor's displacement control drifting), ``--machines`` machines of ``--hours``
operating hours each, written once to ``--cache``. Each machine's logs in order go through one monitor
(the columnar engine) with its type's configuration and model and a ``prognosis`` section with the
defaults (end of life: ratio 90 %, on the high side 110 %): what a fleet gets by turning it on.

Printed per machine: its fate (truth), the first tick with a trend (operating hour, direction), and
for a degrading machine the estimate 10 h before its failure against the truth. The target: no trend
on any healthy machine (issue 30). The degrading ones are for information: the defaults' end of life
is not the simulated loss of function (the run-to-failure benchmark, ``bench_prognosis.py``, scores
the estimates against it).

    python bench/bench_prognosis_fleet.py [--machines 12] [--hours 150] [--seed 3] [--jobs 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_baseline import fleet, type_raw  # a sibling script: its fleet cache and type configuration

PROGNOSIS = {"enabled": True}  # the defaults: what a fleet gets by turning it on
BEFORE_H = 10.0


def fleet_spec(args: argparse.Namespace) -> Any:
    from cmcan.sim.fleet import FleetSpec

    return FleetSpec(machines=args.machines, hours=args.hours, seed=args.seed, degrading_share=0.5)


def load_cfg(root: Path, type_name: str) -> Any:
    from cmcan import config as cfgmod

    d = root / "types" / type_name
    raw = {**type_raw(root, type_name), "prognosis": PROGNOSIS}
    return cfgmod.from_dict(raw, f"{d / 'cmcan.yaml'} + prognosis section", d)


def run_machine(job: dict[str, Any]) -> dict[str, Any]:
    from cmcan.assemble import assemble
    from cmcan.io.columns import column_chunks
    from cmcan.replay import TimelineCollector, replay_columns

    root, m = Path(job["root"]), job["machine"]
    logs = [root / lg["log"] for lg in m["logs"]]
    t0 = time.perf_counter()
    mon = assemble(load_cfg(root, m["type"])).monitor
    sink = TimelineCollector()
    replay_columns(mon, (c for p in logs for c in column_chunks(p)), [sink])
    tl = sink.timeline
    t, state, direction, p50 = tl.t_run_s, tl.prognosis_state, tl.prognosis_direction, tl.prognosis_to_eol_p50_h
    h = (t - m["start_epoch_s"]) / 3600.0
    out: dict[str, Any] = {"machine": m["machine"], "seconds": time.perf_counter() - t0}
    trend = np.flatnonzero(state >= 2)
    out["first_trend_h"] = float(h[trend[0]]) if len(trend) else None
    out["direction"] = {1: "low", 2: "high"}.get(int(direction[trend[0]]), "?") if len(trend) else None
    if m["degrading"]:
        fail_h = m["failures"][0]["fail_h"]
        near = np.flatnonzero(np.abs(h - (fail_h - BEFORE_H)) <= 0.5)
        out["p50_before_h"] = float(np.nanmedian(p50[near])) if len(near) and (state[near] >= 2).any() else None
    return out


def fate(m: dict[str, Any]) -> str:
    if not m["degrading"]:
        return "healthy"
    f = m["failures"][0]
    return f"{m['degradation']} {f['onset_h']:.0f}->{f['fail_h']:.0f} h"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=12)
    ap.add_argument("--hours", type=float, default=150.0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/cmcan-bench-prognosis-fleet"))
    args = ap.parse_args()
    import json

    t0 = time.perf_counter()
    root = fleet(args.cache, fleet_spec(args))
    truth = json.loads((root / "truth.json").read_text())
    machines = truth["machines"]
    jobs = [{"root": str(root), "machine": m} for m in machines]
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        results = list(ex.map(run_machine, jobs))
    print(f"{'machine':8} {'type':8} {'fate':32} {'first trend':>12} {'side':>5} {'p50 10 h before':>16}")
    false = healthy = 0
    for m, r in zip(machines, results, strict=True):
        first = "-" if r["first_trend_h"] is None else f"{r['first_trend_h']:.1f} h"
        before = r.get("p50_before_h")
        before_s = "" if not m["degrading"] else ("none" if before is None else f"{before:.1f} h")
        print(f"{m['machine']:8} {m['type']:8} {fate(m):32} {first:>12} {r['direction'] or '-':>5} {before_s:>16}")
        if not m["degrading"]:
            healthy += 1
            false += r["first_trend_h"] is not None
    print()
    ok = "met" if false == 0 else "NOT met"
    print(f"trends on healthy machines: {false} of {healthy} (wanted 0: {ok})")
    print(f"wall time {time.perf_counter() - t0:.0f} s ({args.machines} machines x {args.hours:g} h, seed {args.seed})")


if __name__ == "__main__":
    main()
