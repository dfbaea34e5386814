"""Benchmark: the service plan end to end, chained the way a fleet engineer chains the commands.

For each seed and unit-spread scale, through the real command line only:

1. ``cmcan simulate fleet`` (all three types, ``--unit-spread``, two machines arriving with a leak, half
   of the machines wearing or with a drifting displacement control);
2. ``cmcan fleet replay`` of every log with the types' shipped configurations;
3. ``cmcan fleet train`` per type on the machines' rows before the cut (``--until-h``): the type
   model, its leaking units named and left out;
4. each type's configuration with that model and ``baseline: {enabled: true}``, ``prognosis:
   {enabled: true}`` (every other key its default), and ``cmcan fleet replay`` of each machine's logs
   up to the cut (``--cut-h`` operating hours: the logs that end by then);
5. ``cmcan fleet plan --json`` on that data set, judged against the ground truth:

- every machine that fails within ``--within-h`` (60) h after the cut is caught (warning now, imminent
  or trend), its p10 to end of life never later than 1.2 x its true remaining hours + 5 h (the p50 is
  printed beside it);
- a machine that failed before the cut warns now;
- a healthy machine (no failure ahead, no arriving leak) shows no trend and no warning, and is not
  flagged (``baseline_suspect``, ``does_not_fit``, ``left_out_of_type``);
- a machine arriving with a leak is flagged (``baseline_suspect``, ``left_out_of_type``: fleet train
  named it, or a warning now);
- ``fleet train`` names both arriving leaks as outliers;
- every healthy machine's baseline, on the default learning settings, leaves learning (monitors on
  its own baseline) within 50 operating hours.

The end of life is the configuration's default (the ratio at 90 %, 110 % on the high side), not the
simulated loss of function, which a machine in the field does not know: it comes first, so the
hours to it are shorter than those to the failure. Printed: the plan per machine with the truth
beside it, and the totals per fleet and overall; ``--json FILE`` keeps them.

    python bench/bench_fleet_plan.py [--machines 12] [--hours 150] [--cut-h 100] [--seeds 41,42]
                                     [--spreads 1,1.5] [--work DIR] [--quick]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cmcan.monitor.baseline import Mode
from cmcan.sim.degradation import misposition_pct, wear_lpm

CAUGHT = ("warning_now", "imminent", "trend")
JUDGED_FLAGS = ("baseline_suspect", "does_not_fit", "left_out_of_type")  # the plan's verdicts on a unit
LATE_FACTOR, LATE_SLACK_H = 1.2, 5.0
LEARNED_WITHIN_H = 50.0


def cli(*args: str, ok: tuple[int, ...] = (0,)) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "cmcan", *args], capture_output=True, text=True)
    if r.returncode not in ok:
        raise SystemExit(f"cmcan {' '.join(args)}: exit {r.returncode}\n{r.stderr[-2000:]}")
    return r


def simulate(work: Path, args: argparse.Namespace, seed: int, spread: float) -> Path:
    sim = work / "sim"
    if not (sim / "truth.json").is_file():
        cli("simulate", "fleet", "--machines", str(args.machines), "--hours", f"{args.hours:g}",
            "--log-hours", f"{args.log_hours:g}", "--unit-spread", f"{spread:g}", "--arriving-leaks", "2",
            "--seed", str(seed), "--out", str(sim))  # fmt: skip
    return sim


def train_types(work: Path, sim: Path, args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """Replay the whole fleet with the shipped type configurations and train each type's model on the
    rows before the cut."""
    ds = work / "ds-train"
    if not ds.exists():
        cli("fleet", "replay", str(sim / "manifest.csv"), "--out", str(ds), "-q", "--json", ok=(0, 65))
    with open(sim / "types.csv", newline="") as f:
        types = sorted({row["type"] for row in csv.DictReader(f)})
    out = {}
    for t in types:
        model = work / f"type-{t}.onnx"
        r = cli("fleet", "train", str(ds), "--machine-type", t, "--types", str(sim / "types.csv"),
                "--until-h", f"{args.cut_h:g}", "--out", str(model), "--force", "--json")  # fmt: skip
        out[t] = {"model": model, "train": json.loads(r.stdout)}
    return out


def plan_at_cut(work: Path, sim: Path, trained: dict[str, dict[str, Any]], cut_h: float) -> list[dict[str, Any]]:
    """The type configurations with the trained models, the baseline and the prognosis; the logs that end
    by the cut replayed; the plan."""
    manifest = work / "manifest-cut.csv"
    configs = {}
    for t, tr in trained.items():
        raw = yaml.safe_load((sim / "types" / t / "cmcan.yaml").read_text())
        raw["model"] = str(tr["model"])
        raw["dbc"] = str((sim / "types" / t / raw["dbc"]).resolve())
        raw["baseline"] = {"enabled": True}
        raw["prognosis"] = {"enabled": True}
        p = work / f"type-{t}.yaml"
        p.write_text(yaml.safe_dump(raw, sort_keys=False))
        configs[t] = p
    truth = json.loads((sim / "truth.json").read_text())
    with open(manifest, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(("machine", "log", "config", "model"))
        for m in truth["machines"]:
            for lg in m["logs"]:
                if lg["to_h"] <= cut_h + 1e-9:
                    w.writerow(
                        (m["machine"], str(sim / lg["log"]), str(configs[m["type"]]), str(trained[m["type"]]["model"]))
                    )
    ds = work / "ds-plan"
    shutil.rmtree(ds, ignore_errors=True)
    cli("fleet", "replay", str(manifest), "--out", str(ds), "--manifest-root", "/", "-q", "--json", ok=(0, 65))
    rows = json.loads(cli("fleet", "plan", str(ds), "--json").stdout)["machines"]
    # the operating hour each machine's baseline first monitored (left learning on its own baseline)
    sql = (
        "SELECT t.machine, min(ml.offset_h + t.log_time_h) AS h FROM timeline t JOIN machine_logs ml "
        f"USING (machine, log_hash) WHERE t.baseline_state = {int(Mode.MONITORING)} GROUP BY 1"
    )
    got = json.loads(cli("fleet", "query", str(ds), sql, "--format", "json").stdout)
    monitoring = {r["machine"]: r["h"] for r in got}
    for r in rows:
        r["monitoring_from_h"] = monitoring.get(r["machine"])
    return rows


def size_at(events: list[dict[str, Any]], h: float) -> str:
    """What the machine's degradation amounts to at operating hour ``h``, against its size at failure
    (the simulator's truth; a wear's leakage at its reference point)."""
    out = []
    for ev in events:
        if ev["type"] == "wear" and "shape" in ev:  # a truth from before the simulator wrote the defaults: no size
            now = float(wear_lpm(ev, np.array([h]))[0])
            out.append(f"{ev['component']} leak {now:.2f} of {ev['fail_extra_lpm']:g} l/min")
        elif ev["type"] == "misposition":
            pct = float(misposition_pct(ev, np.array([h]))[0])
            out.append(f"misposition {pct:.2f} of {ev['pct']:g} %")
    return ", ".join(out)


def judge(truth: dict[str, Any], rows: list[dict[str, Any]], trained: dict[str, Any], cut_h: float, within_h: float):
    by = {r["machine"]: r for r in rows}
    keys = ("caught", "not_late", "failed_warns", "healthy_quiet", "healthy_unflagged", "leaks_flagged",
            "healthy_learned_50h")  # fmt: skip
    lines, tally = [], {k: [0, 0] for k in keys}
    for m in truth["machines"]:
        name = m["machine"]
        r = by.get(name)
        fails = [f["fail_h"] for f in m.get("failures", [])]
        fail_h = min(fails) if fails else math.inf
        remaining = fail_h - cut_h
        leak = m.get("unit", {}).get("arriving_leak_lpm", 0.0) > 0
        verdict = []
        if r is None:
            lines.append(f"  {name}: not in the plan")
            continue
        p10, p50 = r["to_eol_h"][0], r["to_eol_h"][1]
        if remaining <= 0:
            ok = r["warning_level"] in ("low", "high")
            tally["failed_warns"][0] += ok
            tally["failed_warns"][1] += 1
            verdict.append("failed before the cut: " + ("warns now" if ok else "NOT WARNING"))
        elif remaining <= within_h:
            caught = r["group"] in CAUGHT
            tally["caught"][0] += caught
            tally["caught"][1] += 1
            size = size_at(m.get("events", []), cut_h)
            verdict.append(
                f"fails in {remaining:.0f} h: "
                + ("caught" if caught else "MISSED")
                + (f" ({size} at the cut)" if size and not caught else "")
            )
            if p10 is not None:
                late = p10 > LATE_FACTOR * remaining + LATE_SLACK_H
                tally["not_late"][0] += not late
                tally["not_late"][1] += 1
                verdict.append("p10 LATE" if late else "p10 in time")
        elif not leak and not fails:
            quiet = r["group"] not in CAUGHT and r["prognosis_state"] not in ("trend", "imminent")
            tally["healthy_quiet"][0] += quiet
            tally["healthy_quiet"][1] += 1
            verdict.append("healthy: " + ("quiet" if quiet else "TREND OR WARNING"))
            # nor flagged: a type model that left a leak out must not judge the healthy ones too strictly
            unflagged = not set(JUDGED_FLAGS) & set(r["flags"])
            tally["healthy_unflagged"][0] += unflagged
            tally["healthy_unflagged"][1] += 1
            if not unflagged:
                verdict.append("FLAGGED " + ",".join(r["flags"]))
        if not leak and not fails:
            h = r.get("monitoring_from_h")
            learned = h is not None and h <= LEARNED_WITHIN_H
            tally["healthy_learned_50h"][0] += learned
            tally["healthy_learned_50h"][1] += 1
            verdict.append(f"monitoring from {'-' if h is None else f'{h:.0f}'} h" + ("" if learned else " (LATE)"))
        if leak:
            flagged = bool({"baseline_suspect", "left_out_of_type"} & set(r["flags"])) or r["warning_level"] == "low"
            tally["leaks_flagged"][0] += flagged
            tally["leaks_flagged"][1] += 1
            verdict.append("arrives leaking: " + ("flagged" if flagged else "NOT FLAGGED"))
        eol = "/".join("-" if h is None else f"{h:.0f}" for h in r["to_eol_h"])
        lines.append(
            f"  {r['rank']:>2} {name} {m['type']:<7} {r['group']:<12} {r['warning_level']:<5} "
            f"{r['baseline_state']:<16} "
            f"{r['prognosis_state']:<8} EOL {eol:<12} p50 {'-' if p50 is None else f'{p50:.0f}':>4} "
            f"truth {'-' if math.isinf(fail_h) else f'{fail_h:.0f}'} h  {'; '.join(verdict)}"
        )
    named = {t: tr["train"].get("unit_spread", {}).get("outliers", []) for t, tr in trained.items()}
    leaks = {m["machine"] for m in truth["machines"] if m.get("unit", {}).get("arriving_leak_lpm", 0.0) > 0}
    out_named = {o["machine"] if isinstance(o, dict) else o for os_ in named.values() for o in os_}
    tally["train_named_leaks"] = [len(leaks & out_named), len(leaks)]
    return lines, tally


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=12)
    ap.add_argument("--hours", type=float, default=150.0)
    ap.add_argument("--log-hours", type=float, default=10.0, help="operating hours per log (the cut falls between)")
    ap.add_argument("--cut-h", type=float, default=100.0, help="the plan at this operating hour")
    ap.add_argument("--within-h", type=float, default=60.0, help="machines failing this soon after the cut")
    ap.add_argument("--seeds", default="41,42")
    ap.add_argument("--spreads", default="1,1.5")
    ap.add_argument("--work", type=Path, default=Path("/tmp/cmcan-bench-fleet-plan"))
    ap.add_argument("--quick", action="store_true", help="6 machines, 80 h, cut at 50 h, one seed and spread")
    ap.add_argument("--json", type=Path, help="write the rows and totals here")
    args = ap.parse_args(argv)
    if args.quick:
        args.machines, args.hours, args.cut_h, args.seeds, args.spreads = 6, 80.0, 50.0, args.seeds.split(",")[0], "1"
    t_all = time.perf_counter()
    overall: dict[str, list[int]] = {}
    doc = []
    for seed in (int(s) for s in str(args.seeds).split(",")):
        for spread in (float(s) for s in str(args.spreads).split(",")):
            work = args.work / f"s{seed}-x{spread:g}"
            work.mkdir(parents=True, exist_ok=True)
            t0 = time.perf_counter()
            sim = simulate(work, args, seed, spread)
            trained = train_types(work, sim, args)
            rows = plan_at_cut(work, sim, trained, args.cut_h)
            truth = json.loads((sim / "truth.json").read_text())
            lines, tally = judge(truth, rows, trained, args.cut_h, args.within_h)
            print(f"fleet seed {seed}, unit spread x{spread:g}: {args.machines} machines x {args.hours:g} h, plan at "
                  f"{args.cut_h:g} h ({time.perf_counter() - t0:.0f} s)")  # fmt: skip
            print("\n".join(lines))
            print("  " + ", ".join(f"{k} {a}/{b}" for k, (a, b) in tally.items()))
            for k, (a, b) in tally.items():
                o = overall.setdefault(k, [0, 0])
                o[0] += a
                o[1] += b
            doc.append({"seed": seed, "spread": spread, "rows": rows, "totals": tally})
    print("overall: " + ", ".join(f"{k} {a}/{b}" for k, (a, b) in overall.items()))
    print(f"wall time {time.perf_counter() - t_all:.0f} s")
    if args.json:
        args.json.write_text(json.dumps({"fleets": doc, "overall": overall}, indent=1) + "\n")
    return 0 if all(a == b for a, b in overall.values()) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
