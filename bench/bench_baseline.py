"""Benchmark: the on-board baseline against the engineer's per-machine model and the type model alone.

Issue 29's scenario, a simulated fleet of one type (``mid``) with unit-to-unit variation
(:class:`cmcan.sim.fleet.UnitSpread`, its datasheet defaults times ``--spread-scale``): ``--machines``
machines (21), each ``--hours`` of operation (150) with mixed duty (wheel loader or excavator, drawn)
and oil from cold to hot (each machine's mean drawn in 40..55 C, swinging +-15..20 C over 10 h: 20 to
75 C); a third of them develop wear of the pump or the motor, none starting before ``--onset-min-h``
(25 h, meant to be after their learning), failing in the last third of their hours; two healthy ones arrive with a
leak (4..8 % of rated flow at 480 bar). Written once by :func:`cmcan.fleet.simfleet.write_fleet` to
``--cache`` (keyed by the spec), with its truth sidecar.

Each machine's whole log (its logs in order, through one monitor: the columnar engine) three ways:

- type: the type's configuration and model as ``write_fleet`` trains them (a healthy test-rig sweep of
  the nominal drive), nothing learned on the machine;
- engineer: ``cmcan train`` on the first ``--train-h`` operating hours (10) of the machine's own log,
  the type's configuration otherwise, replayed with that model: the per-machine model an engineer makes
  (an arriving leak is in its training data: it learns the leak as healthy);
- onboard: the type's configuration and model with a ``baseline:`` section (``enabled: true``, every
  other key the configuration's default but ``min_hours``, see below; ``--set KEY=VALUE`` for a
  what-if): the gateway learns the machine itself.

Printed side by side: false low and high warnings per 100 h on the healthy machines (arriving leaks
apart), counted after the engineer's training stretch (engineer), after the learning ended (onboard;
also while learning, against its wider thresholds) and over the whole log (type); hours of operation to
leave ``learning`` (median, max); the lead of the first low warning before each worn machine's failure
(the first tick at or after the fault's onset with the level low; a low already raised before the onset
is marked: it is no lead), and onboard's lead against the engineer's (goal: within 10 %); the arriving
leaks flagged ``baseline_suspect`` (goal 2 of 2) and whether the other two arms raised a low warning on
them at all. Per machine also the share of the envelope's bins its learnable ticks visit at all and
fill with ``min_points`` each over its whole log: the most coverage that log could give.

Time-lapse: the fleet is sampled in bursts (``--burst-s`` 10 s every ``--every-min`` 20 min, 1/120 of
the operation). The section's ``min_hours`` is ``--min-hours`` (2.0, the configuration's default)
as it is: operating hours, which the operating clock counts across the gaps between bursts as on a
gateway. ``min_points`` (ticks per bin) is left as configured, so the coverage needs the same number of
sampled ticks per bin, i.e. up to 120 times the operating hours a gateway would need: the hours to
leave learning here are an upper bound (which bins a machine visits at all does not change).

On-board fit cost, on one healthy machine (``--cost-machine``, default the first healthy one): the
learning stage alone (the configuration's baseline parameters, with the gateway's own ``min_hours``),
fed that machine's evaluated ticks (operating point, measured and type prediction, as the type arm
computed them) one at a time as the gateway's receive path does (:meth:`Baseline.learn`), cycled until
the learning ends or ``--cost-ticks`` ticks, and the same ticks as columns
(:meth:`Baseline.run_columns`, the replay's path): CPU seconds, microseconds per tick, what that
makes for ``min_hours`` of a gateway's learned ticks, peak memory (tracemalloc) and the state's size.
Then the receive path: the first ``--cost-frames`` frames of that machine's first log frame by frame
(``Monitor.feed``, the daemon's path) with and without the baseline configured (the section above: it
learns over these frames), in rounds (``--rounds``) of plain, with, plain: CPU per frame of each (the
best of the rounds), the ratio with / without (the median of the rounds' ratios) and the noise (the
median of |plain / plain - 1|).

    python bench/bench_baseline.py [--machines 21] [--hours 150] [--seed 29] [--jobs 2] [--cache DIR]
    python bench/bench_baseline.py --quick      # 4 machines x 20 h, well under a minute
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import math
import os
import shutil
import statistics
import tempfile
import time
import tracemalloc
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ARMS = ("type", "engineer", "onboard")
LEARNING, MONITORING, SUSPECT = 1, 2, 3  # baseline_state codes of a tick (0: no baseline configured)
STATE_NAMES = {0: "-", LEARNING: "learning", MONITORING: "monitoring", SUSPECT: "baseline_suspect"}
LOW, HIGH = 1, 2  # cmcan.monitor.warnings.Level
LEAD_TOLERANCE = 0.10


# -- the fleet ---------------------------------------------------------------------------------------


def fleet_spec(args: argparse.Namespace) -> Any:
    from cmcan.sim.fleet import FleetSpec, UnitSpread

    return FleetSpec(
        machines=args.machines,
        hours=args.hours,
        seed=args.seed,
        degrading_share=1.0 / 3.0,
        burst_s=args.burst_s,
        every_min=args.every_min,
        types=("mid",),
        oil_temp_c=(40.0, 55.0),
        oil_swing_c=(15.0, 20.0),
        spread=UnitSpread().scaled(args.spread_scale),
        arriving_leaks=args.arriving_leaks,
        degradations=("motor_wear", "pump_wear"),
        onset_min_h=args.onset_min_h,
    )


def fleet(cache: Path, spec: Any) -> Path:
    """The fleet of ``spec`` under ``cache`` (written once: a folder per spec and per shipped DBC and
    configuration, which the fleet copies, renamed into place)."""
    from cmcan import __version__
    from cmcan.can.dbc import default_dbc_path
    from cmcan.config import default_config_path
    from cmcan.fleet.simfleet import write_fleet
    from cmcan.sim.fleet import spec_record

    h = hashlib.sha256(json.dumps(spec_record(spec), sort_keys=True, default=str).encode())
    h.update(__version__.encode())
    for shipped in (default_dbc_path(), default_config_path()):
        h.update(shipped.read_bytes())
    key = h.hexdigest()[:10]
    out = cache / f"baseline-{spec.machines}x{spec.hours:g}h-s{spec.seed}-{key}"
    if (out / "truth.json").exists():
        return out
    tmp = out.with_name(out.name + f".tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    t = time.perf_counter()
    s = write_fleet(spec, tmp)
    os.replace(tmp, out)
    print(f"fleet written to {out}: {s['machines']} machines, {s['frames'] / 1e6:.1f} M frames in "
          f"{time.perf_counter() - t:.0f} s")  # fmt: skip
    return out


def type_raw(root: Path, type_name: str = "mid") -> dict[str, Any]:
    from cmcan.schema import load_yaml

    return load_yaml(root / "types" / type_name / "cmcan.yaml")


def load_cfg(root: Path, baseline: dict[str, Any] | None, type_name: str = "mid") -> Any:
    """The type's configuration, with a ``baseline`` section when given."""
    from cmcan import config as cfgmod

    d = root / "types" / type_name
    if baseline is None:
        return cfgmod.load(d / "cmcan.yaml")
    raw = {**type_raw(root, type_name), "baseline": baseline}
    return cfgmod.from_dict(raw, f"{d / 'cmcan.yaml'} + baseline section", d)


# -- one machine, three arms ---------------------------------------------------------------------------


class TickSink:
    """Keeps what the metrics need of every tick: time, level, gate, baseline state; and, when
    ``points``, the operating point, measured and predicted value of each tick the gate passed inside
    the envelope (``EVALUATING``: what the baseline learns from)."""

    wants_ticks = True
    wants_frames = False

    def __init__(self, points: bool = False) -> None:
        self.points = points
        self.parts: list[dict[str, np.ndarray]] = []

    def start(self, t0: float) -> None:
        pass

    def ticks(self, c: Any) -> None:
        part = {"t": c.t_run_s.copy(), "level": c.level.copy(), "gate": c.gate.copy()}
        state = getattr(c, "baseline_state", None)
        part["state"] = np.zeros(len(c), np.int8) if state is None else np.asarray(state, np.int8).copy()
        if self.points:  # the ticks the baseline learns from: those the gate passed inside the envelope
            from cmcan.monitor.gating import Gate
            from cmcan.roles import MODEL_INPUTS

            ev = c.gate == int(Gate.EVALUATING)
            part["ev_t"] = c.t_s[ev]
            part["ev_x"] = np.column_stack([getattr(c, r)[ev] for r in MODEL_INPUTS])
            part["ev_measured"] = c.measured[ev]
            part["ev_predicted"] = c.predicted[ev]
        self.parts.append(part)

    def frames(self, frames: Any) -> None:
        pass

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass

    def arrays(self) -> dict[str, np.ndarray]:
        keys = self.parts[0].keys() if self.parts else ("t", "level", "gate", "state")
        return {k: np.concatenate([p[k] for p in self.parts]) if self.parts else np.empty(0) for k in keys}


def replay_machine(logs: list[Path], cfg: Any, model: Path | None, points: bool = False) -> tuple[dict, Any, float]:
    """The machine's logs in order through one monitor: (tick arrays, the monitor, CPU seconds)."""
    from cmcan.assemble import assemble
    from cmcan.io.columns import column_chunks
    from cmcan.replay import replay_columns

    mon = assemble(cfg, model).monitor
    sink = TickSink(points)
    cpu = time.process_time()
    replay_columns(mon, itertools.chain.from_iterable(column_chunks(p) for p in logs), [sink])
    return sink.arrays(), mon, time.process_time() - cpu


def train_engineer(root: Path, machine: dict[str, Any], train_h: float, out: Path) -> Path:
    """``cmcan train`` on the first ``train_h`` hours of the machine's first log, as an engineer runs it
    (its command line, in this process: no interpreter to start per machine)."""
    import contextlib
    import io

    from cmcan.cli import main as cmcan_main

    model = out / f"{machine['machine']}-{train_h:g}h.onnx"
    if model.exists():
        return model
    out.mkdir(parents=True, exist_ok=True)
    cfg = root / "types" / machine["type"] / "cmcan.yaml"
    tmp = model.with_name(model.name + f".tmp{os.getpid()}")
    argv = ["train", str(root / machine["logs"][0]["log"]), "--config", str(cfg), "--t-trn-h", f"{train_h:g}",
            "--out", str(tmp), "--force", "--json"]  # fmt: skip
    said, errs = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(said), contextlib.redirect_stderr(errs):
        code = cmcan_main(argv)
    if code != 0:
        raise RuntimeError(f"cmcan {' '.join(argv)} failed ({code}): {errs.getvalue().strip()[-400:]}")
    os.replace(tmp, model)
    return model


@dataclass
class ArmResult:
    from_h: float | None  # warnings counted from this operating hour (None: never, e.g. still learning)
    hours_counted: float
    lows: int  # warnings raised after from_h
    highs: int
    lows_before: int  # raised before from_h (the training stretch, or while learning)
    highs_before: int
    any_low: bool  # a low warning at any time
    lead_h: float | None = None  # failure hour less the first tick at or after onset with the level low
    low_at_onset: bool = False  # the level was already low at the onset (raised before it: no lead)
    cpu_s: float = 0.0
    learned_end_h: float | None = None  # onboard: operating hour the learning ended
    final_state: str = "-"
    describe: dict[str, Any] = field(default_factory=dict)


def arm_result(a: dict[str, np.ndarray], start_s: float, hours: float, from_h: float | None, m: dict) -> ArmResult:
    h = (a["t"] - start_s) / 3600.0
    lv = a["level"].astype(np.int64)
    prev = np.concatenate([[0], lv[:-1]])
    raised = lv != prev
    low_up, high_up = raised & (lv == LOW), raised & (lv == HIGH)
    after = h >= from_h if from_h is not None else np.zeros(len(h), bool)
    r = ArmResult(
        from_h=from_h,
        hours_counted=max(0.0, hours - from_h) if from_h is not None else 0.0,
        lows=int((low_up & after).sum()),
        highs=int((high_up & after).sum()),
        lows_before=int((low_up & ~after).sum()),
        highs_before=int((high_up & ~after).sum()),
        any_low=bool((lv == LOW).any()),
    )
    for f in m["failures"][:1]:
        onset, fail = f["onset_h"], f["fail_h"]
        at = np.flatnonzero((h >= onset) & (h < fail))
        if len(at):
            r.low_at_onset = bool(lv[at[0]] == LOW)
            low = at[lv[at] == LOW]
            if len(low):
                r.lead_h = fail - float(h[low[0]])
    return r


def run_machine(job: dict[str, Any]) -> dict[str, Any]:
    """The three arms on one machine (a process of the pool)."""
    root, m = Path(job["root"]), job["machine"]
    logs = [root / lg["log"] for lg in m["logs"]]
    start_s, hours = m["start_epoch_s"], m["hours"]
    t0 = time.perf_counter()
    out: dict[str, Any] = {"machine": m["machine"]}
    a, _mon, cpu = replay_machine(logs, load_cfg(root, None), None, points=True)
    out["type"] = arm_result(a, start_s, hours, 0.0, m)
    out["type"].cpu_s = cpu
    out["reachable"] = reachable(job["params"], a)
    model = train_engineer(root, m, job["train_h"], Path(job["models"]))
    a, _mon, cpu = replay_machine(logs, load_cfg(root, None), model)
    out["engineer"] = arm_result(a, start_s, hours, job["train_h"], m)
    out["engineer"].cpu_s = cpu
    if job["baseline"] is not None:
        a, mon, cpu = replay_machine(logs, load_cfg(root, job["baseline"]), None)
        h = (a["t"] - start_s) / 3600.0
        done = np.flatnonzero(np.isin(a["state"], (MONITORING, SUSPECT)))
        end_h = float(h[done[0]]) if len(done) else None
        r = arm_result(a, start_s, hours, end_h, m)
        r.cpu_s, r.learned_end_h = cpu, end_h
        r.final_state = STATE_NAMES.get(int(a["state"][-1]) if len(a["state"]) else 0, "?")
        bl = getattr(mon, "baseline", None)
        r.describe = _plain(bl.describe()) if bl is not None else {}
        out["onboard"] = r
    out["seconds"] = time.perf_counter() - t0
    return out


def reachable(params: Any, a: dict[str, np.ndarray]) -> dict[str, float]:
    """What this log's learnable ticks could give the baseline at most: the share of the envelope's bins
    they visit at all, and the share they fill with ``min_points`` each over the whole log."""
    from cmcan.monitor.baseline import bin_index

    b = bin_index(params, a["ev_x"])
    n = np.bincount(b[b >= 0], minlength=params.n_bins)
    return {
        "visited_pct": 100.0 * float(np.count_nonzero(n)) / params.n_bins,
        "filled_pct": 100.0 * float(np.count_nonzero(n >= params.min_points)) / params.n_bins,
        "needed_pct": 100.0 * params.bins_needed / params.n_bins,
    }


def _plain(d: dict[str, Any]) -> dict[str, Any]:
    keep = ("state", "learned_h", "coverage_pct", "bins_covered", "bins", "bins_needed", "theta", "distance_lpm",
            "suspect_lpm")  # fmt: skip
    return {k: d[k] for k in keep if k in d}


# -- the fit's cost --------------------------------------------------------------------------------------


def learning_cost(params: Any, ev: dict[str, np.ndarray], max_ticks: int) -> dict[str, Any]:
    """The learning stage fed ``ev``'s ticks one at a time (cycled until it ends, at most ``max_ticks``)
    and the same ticks as columns: CPU, peak memory, the state's size."""
    from cmcan.monitor.baseline import Baseline

    n = len(ev["t"])
    out: dict[str, Any] = {"ticks_available": n}
    if n == 0:
        return out
    period = params.period_s
    # the ticks on a gateway's time base: one after another, each a tick period on (cycles follow on)
    rows = [
        (tuple(float(v) for v in ev["x"][i]), float(ev["measured"][i]), float(ev["predicted"][i])) for i in range(n)
    ]

    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    cpu = time.process_time()
    bl = Baseline(params)
    k = 0
    ended = False
    while k < max_ticks and not ended:  # as the daemon's core: the tick's start, then its point
        x, mv, pv = rows[k % n]
        ended = bl.tick(k, k * period, k * period, True)
        if not ended:
            bl.add(k * period, x, mv, pv)
            k += 1
    per_tick_cpu = time.process_time() - cpu
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    state = bl.n.nbytes + bl.sxx.nbytes + bl.sxy.nbytes + bl.sy.nbytes
    out.update(ticks=k, ended=ended, mode=bl.describe()["state"], cpu_s=per_tick_cpu, peak_b=peak, state_b=state,
               learned_h=bl.learned_h, coverage_pct=bl.coverage_pct)  # fmt: skip
    # the fit that ends the learning, on the statistics as they stand (covered bins only), on its own
    from cmcan.monitor.baseline import fit

    reps_fit = 200
    cpu = time.process_time()
    for _ in range(reps_fit):
        fit(params, bl.n, bl.sxx, bl.sxy, bl.sy)
    out["fit_us"] = 1e6 * (time.process_time() - cpu) / reps_fit

    reps = max(1, math.ceil(k / n))
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    cpu = time.process_time()
    bc = Baseline(params)
    t = np.arange(reps * n) * period
    x = np.tile(ev["x"], (reps, 1))
    ks = np.arange(k + 1, dtype=np.int64)  # and the tick that checks the last block
    t = np.append(t[:k], k * period)
    split, _, _ = bc.run_columns(
        ks,
        t,
        t,
        np.ones(len(ks), bool),
        np.arange(k),
        x[:k],
        np.tile(ev["measured"], reps)[:k],
        np.tile(ev["predicted"], reps)[:k],
    )
    end = split if split <= k else -1
    out["columns_cpu_s"] = time.process_time() - cpu
    out["columns_peak_b"] = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    out["columns_same"] = bool(bc.theta == bl.theta and bc.mode == bl.mode and (end == k) == ended)
    return out


def receive_cost(cfg_plain: Any, cfg_bl: Any, log: Path, frames: int, rounds: int) -> dict[str, Any]:
    """CPU per frame of the daemon's path (Monitor.feed) without and with the baseline, alternating."""
    from cmcan.assemble import assemble
    from cmcan.io.candump import iter_frames

    fs = list(itertools.islice(iter_frames(log), frames))

    def once(cfg: Any) -> tuple[float, Any]:
        mon = assemble(cfg).monitor
        cpu = time.process_time()
        for f in fs:
            mon.feed(f)
        mon.flush()
        return (time.process_time() - cpu) / len(fs), mon

    plain, withbl, ratio, noise = [], [], [], []
    mon_bl = None
    for _ in range(rounds):
        a, _ = once(cfg_plain)
        b, mon_bl = once(cfg_bl)
        a2, _ = once(cfg_plain)
        plain += [a, a2]
        withbl.append(b)
        ratio.append(b / min(a, a2))
        noise.append(abs(a2 / a - 1.0))
    bl = getattr(mon_bl, "baseline", None)
    return {
        "frames": len(fs),
        "plain_us": 1e6 * min(plain),
        "baseline_us": 1e6 * min(withbl),
        "ratio": statistics.median(ratio),
        "noise": statistics.median(noise),
        "state_at_end": bl.describe()["state"] if bl is not None else "?",
        "learned_h_at_end": bl.learned_h if bl is not None else math.nan,
    }


# -- the report ------------------------------------------------------------------------------------------


def overrides(pairs: list[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` pairs as section keys (values read as YAML)."""
    import yaml

    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise SystemExit(f"--set {pair!r}: expected KEY=VALUE")
        out[key] = yaml.safe_load(value)
    return out


def fate(m: dict[str, Any]) -> str:
    if m["degrading"]:
        f = m["failures"][0]
        return f"{m['degradation']} {f['onset_h']:.0f}->{f['fail_h']:.0f}h"
    leak = m.get("unit", {}).get("arriving_leak_lpm", 0.0)
    return f"arrives leaking {leak:g} l/min" if leak else "healthy"


def _h(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def report(truth: dict[str, Any], results: list[dict[str, Any]], arms: tuple[str, ...]) -> dict[str, Any]:
    by = {m["machine"]: m for m in truth["machines"]}
    print()
    head = f"{'machine':7} {'fate':28} {'duty':12} {'oil C':>9}"
    for arm in arms:
        head += f" | {arm + ' lo/hi':>14} {'lead':>6}"
    if "onboard" in arms:
        head += f" | {'learned@h':>9} {'state':>16} {'cov %':>5} {'vis/fill %':>10} {'dist l/min':>10}"
    print(head)
    for r in results:
        m = by[r["machine"]]
        oil = f"{m['oil_temp_c']:.0f}+-{m['oil_swing_c']:.0f}"
        line = f"{m['machine']:7} {fate(m):28} {m['duty']:12} {oil:>9}"
        for arm in arms:
            a = r[arm]
            counts = f"{a.lows_before}+{a.lows}/{a.highs_before}+{a.highs}"
            lead = _h(a.lead_h) + ("!" if a.low_at_onset else "")
            line += f" | {counts:>14} {lead:>6}"
        if "onboard" in arms:
            o, d = r["onboard"], r["onboard"].describe
            cov, dist = d.get("coverage_pct", math.nan), d.get("distance_lpm", math.nan)
            reach = r["reachable"]
            vis = f"{reach['visited_pct']:.0f}/{reach['filled_pct']:.0f}"
            line += f" | {_h(o.learned_end_h):>9} {o.final_state:>16} {cov:5.0f} {vis:>10} {dist:10.2f}"
        print(line)
    print("lo/hi: low/high warnings raised before + after the counting starts (type: from 0 h; engineer: from")
    print("its training stretch's end; onboard: from the end of learning); lead: failure hour less the first")
    print("tick at or after the onset with the level low ('!': already low at the onset, raised before it);")
    print("cov %: the baseline's coverage at the end; vis/fill %: the envelope's bins this log's learnable ticks")
    print("visit at all / fill with min_points each over the whole log (the most coverage it could give)")

    healthy = [r for r in results if not by[r["machine"]]["degrading"] and not _leak(by[r["machine"]])]
    worn = [r for r in results if by[r["machine"]]["degrading"]]
    leaking = [r for r in results if _leak(by[r["machine"]])]
    summary: dict[str, Any] = {}
    rows: list[tuple[str, dict[str, str], str]] = []

    def per100(arm: str, what: str) -> str:
        n = sum(getattr(r[arm], what) for r in healthy)
        hrs = sum(r[arm].hours_counted for r in healthy)
        summary[f"{arm}_{what}_per100h"] = 100.0 * n / hrs if hrs else None
        return f"{100.0 * n / hrs:.2f} ({n} in {hrs:.0f} h)" if hrs else "- (0 h)"

    rows.append(("false low warnings /100 h, healthy", {a: per100(a, "lows") for a in arms}, "0 after learning"))
    rows.append(("false high warnings /100 h, healthy", {a: per100(a, "highs") for a in arms}, "0 after learning"))
    before = {a: f"{sum(r[a].lows_before for r in healthy)}/{sum(r[a].highs_before for r in healthy)}" for a in arms}
    before["type"] = "-"
    rows.append(("lo/hi raised while training/learning", before, ""))
    learn = {a: "-" for a in arms}
    learn["engineer"] = "(trains offline)"
    if "onboard" in arms:
        ends = [r["onboard"].learned_end_h for r in results]
        done = [e for e in ends if e is not None]
        learn["onboard"] = (f"median {statistics.median(done):.1f}, max {max(done):.1f}" if done else "never") + (
            f"; {len(ends) - len(done)} never" if done and len(done) < len(ends) else ""
        )
        summary["learning_end_h"] = ends
    rows.append(("hours to leave learning", learn, "as few as coverage allows"))
    leads = {a: [r[a].lead_h for r in worn] for a in arms}
    rows.append((
        "lead of the first low before failure, median h",
        {a: _median(v) + f" ({sum(x is not None for x in v)}/{len(v)} warned)" for a, v in leads.items()},
        "",
    ))  # fmt: skip
    early = {a: f"{sum(r[a].low_at_onset for r in worn)}/{len(worn)}" for a in arms}
    rows.append(("worn machines already low at the onset", early, "0"))
    if "onboard" in arms:
        ratios = [
            (o / e) if (o is not None and e is not None and e > 0) else None
            for o, e in zip(leads["onboard"], leads["engineer"], strict=True)
        ]
        ok = sum(1 for x in ratios if x is not None and abs(x - 1.0) <= LEAD_TOLERANCE)
        shown = ", ".join("-" if x is None else f"{x:.2f}" for x in ratios)
        rows.append((
            "lead onboard / engineer (each)", {"onboard": f"{ok}/{len(worn)} within 10 %: {shown}"}, "all within 10 %"
        ))  # fmt: skip
        summary["lead_ratio_onboard_engineer"] = ratios
    flagged = {a: f"low {sum(r[a].any_low for r in leaking)}/{len(leaking)}" for a in arms}
    if "onboard" in arms:
        sus = sum(r["onboard"].final_state == "baseline_suspect" for r in leaking)
        flagged["onboard"] = f"suspect {sus}/{len(leaking)}, " + flagged["onboard"]
        summary["arriving_suspect"] = sus
    flagged["engineer"] += " (learned it)"
    rows.append(("arriving leaks flagged", flagged, f"suspect {len(leaking)}/{len(leaking)}"))
    summary["leads"] = leads

    print()
    print(f"{len(healthy)} healthy, {len(worn)} worn, {len(leaking)} arriving with a leak")
    w = 46
    print(f"{'':{w}} " + " ".join(f"{a:>30}" for a in arms) + f"  {'goal':>18}")
    for name, vals, goal in rows:
        print(f"{name:{w}} " + " ".join(f"{vals.get(a, ''):>30}" for a in arms) + f"  {goal:>18}")
    return summary


def _leak(m: dict[str, Any]) -> bool:
    return bool(m.get("unit", {}).get("arriving_leak_lpm", 0.0)) and not m["degrading"]


def _median(v: list[float | None]) -> str:
    x = [a for a in v if a is not None]
    return f"{statistics.median(x):.1f}" if x else "-"


def print_cost(lc: dict[str, Any], rc: dict[str, Any] | None, params_note: str) -> None:
    print()
    print(f"on-board fit cost ({params_note}):")
    if not lc.get("ticks"):
        print("  no evaluated ticks to learn from")
    else:
        print(
            f"  learning, tick by tick (Baseline.learn): {lc['ticks']} ticks ({lc['learned_h']:.2f} h learned, "
            f"coverage {lc['coverage_pct']:.0f} %, {'ended: ' + lc['mode'] if lc['ended'] else 'not ended'}), "
            f"{lc['cpu_s']:.2f} CPU s ({1e6 * lc['cpu_s'] / lc['ticks']:.1f} us/tick), "
            f"peak {lc['peak_b'] / 1e6:.2f} MB (state {lc['state_b'] / 1e3:.1f} kB)   goal < 5 s, < 20 MB"
        )
        print(f"  the fit itself (closed form over the covered bins): {lc['fit_us']:.0f} us")
        print(
            f"  at that rate, min_hours of a gateway's ticks ({lc['gateway_ticks']} learned ticks): "
            f"{lc['gateway_ticks'] * lc['cpu_s'] / lc['ticks']:.1f} CPU s"
        )
        print(
            f"  the same as columns (Baseline.run_columns): {lc['columns_cpu_s']:.3f} CPU s, "
            f"peak {lc['columns_peak_b'] / 1e6:.2f} MB, same result: {lc['columns_same']}"
        )
    if rc is not None:
        print(
            f"  receive path (Monitor.feed, {rc['frames']} frames, baseline {rc['state_at_end']} at the end, "
            f"{rc['learned_h_at_end']:.2f} h learned): {rc['plain_us']:.2f} us/frame without, "
            f"{rc['baseline_us']:.2f} with; ratio {rc['ratio']:.3f} (noise +-{rc['noise']:.3f})   goal: unchanged"
        )


# -- main ------------------------------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--machines", type=int, help="machines of the fleet (default 21; --quick 4)")
    ap.add_argument("--hours", type=float, help="operating hours of each (default 150; --quick 20)")
    ap.add_argument("--seed", type=int, default=29, help="draws the fleet")
    ap.add_argument("--spread-scale", type=float, default=1.0, help="unit-to-unit tolerances times this")
    ap.add_argument("--arriving-leaks", type=int, default=2, help="healthy machines arriving with a leak")
    ap.add_argument("--onset-min-h", type=float, help="no wear starts before this hour (default 25; --quick 6)")
    ap.add_argument("--train-h", type=float, help="the engineer's training stretch, h (default 10; --quick 4)")
    ap.add_argument("--min-hours", type=float, default=2.0, help="the baseline's min_hours on a gateway (h)")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="what-if: another value for a key of the baseline section (YAML, e.g. coverage_pct=50); "
        "the defaults are the configuration's",
    )
    ap.add_argument("--burst-s", type=float, default=10.0, help="time-lapse: a burst of this many seconds ...")
    ap.add_argument("--every-min", type=float, default=20.0, help="... every this many minutes of operation")
    ap.add_argument("--jobs", type=int, default=2, help="processes")
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "cmcan-bench-baseline")
    ap.add_argument("--cost-machine", help="the machine whose learning is costed (default: the first healthy)")
    ap.add_argument(
        "--cost-ticks",
        type=int,
        help="learn at most this many ticks (default: 1.25 x min_hours of ticks; --quick 5000)",
    )
    ap.add_argument("--cost-frames", type=int, help="frames of the receive-path comparison (default 200000)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of the receive-path comparison")
    ap.add_argument("--quick", action="store_true", help="a small fleet (4 machines x 20 h) for a check")
    ap.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = ap.parse_args()
    quick = {"machines": 4, "hours": 20.0, "onset_min_h": 6.0, "train_h": 4.0, "cost_frames": 20000}
    full = {"machines": 21, "hours": 150.0, "onset_min_h": 25.0, "train_h": 10.0, "cost_frames": 200000}
    for k, v in (quick if args.quick else full).items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    if args.quick:
        args.rounds = min(args.rounds, 1)
        args.cost_ticks = args.cost_ticks or 5000

    t_all = time.perf_counter()
    spec = fleet_spec(args)
    args.cache.mkdir(parents=True, exist_ok=True)
    root = fleet(args.cache, spec)
    truth = json.loads((root / "truth.json").read_text())
    share = args.burst_s / (args.every_min * 60.0)
    section = {"enabled": True, "min_hours": args.min_hours, **overrides(args.set)}
    gateway_section = {**section, "min_hours": args.min_hours}
    arms = ARMS
    from cmcan.assemble import assemble
    from cmcan.monitor.baseline import BIN_ROLES

    params = assemble(load_cfg(root, section)).monitor.baseline.p
    n_worn = sum(m["degrading"] for m in truth["machines"])
    print(
        f"fleet: {spec.machines} mid machines x {spec.hours:g} h, seed {spec.seed}, "
        f"unit spread x{args.spread_scale:g}, "
        f"oil {spec.oil_temp_c[0]:g}..{spec.oil_temp_c[1]:g} C +-{spec.oil_swing_c[0]:g}..{spec.oil_swing_c[1]:g}, "
        f"{n_worn} wearing (onset >= {spec.onset_min_h:g} h), {spec.arriving_leaks} arriving with a leak; "
        f"time-lapse {args.burst_s:g} s every {args.every_min:g} min (1/{1 / share:g} of the operation)"
    )
    print(f"engineer: cmcan train on the first {args.train_h:g} h of each machine's own log")
    print(
        f"onboard: baseline section {section} (min_hours: {args.min_hours:g} operating hours"
        + (", WHAT-IF: " + ", ".join(args.set) if args.set else ", every other key the configuration's default")
        + f"): {'x'.join(str(len(e) - 1) for e in params.edges)} bins over "
        + ", ".join(f"{r} {e[0]:g}..{e[-1]:g}" for r, e in zip(BIN_ROLES, params.edges, strict=True))
        + f", {params.bins_needed} of them with {params.min_points} ticks each, "
        + f"suspect beyond {params.suspect_lpm:.3g} l/min"
    )

    jobs = [
        {
            "root": str(root),
            "machine": m,
            "train_h": args.train_h,
            "models": str(root / "engineer"),
            "baseline": section,
            "params": params,
        }
        for m in truth["machines"]
    ]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        results = list(ex.map(run_machine, jobs))
    wall = time.perf_counter() - t0
    summary = report(truth, results, arms)
    cpu = {a: sum(r[a].cpu_s for r in results) for a in arms}
    print("replay CPU per arm: " + ", ".join(f"{a} {s:.0f} s" for a, s in cpu.items()) + f"; arms' wall {wall:.0f} s")

    # the fit's cost, in this process alone (the pool is done)
    by = {m["machine"]: m for m in truth["machines"]}
    healthy = [m["machine"] for m in truth["machines"] if not m["degrading"] and not _leak(m)]
    name = args.cost_machine or (healthy[0] if healthy else truth["machines"][0]["machine"])
    m = by[name]
    logs = [root / lg["log"] for lg in m["logs"]]
    cfg_plain = load_cfg(root, None)
    a, _mon, _cpu = replay_machine(logs, cfg_plain, None, points=True)
    ev = {"t": a["ev_t"], "x": a["ev_x"], "measured": a["ev_measured"], "predicted": a["ev_predicted"]}
    params = assemble(load_cfg(root, gateway_section)).monitor.baseline.p
    note = f"machine {name}, the section above with a gateway's min_hours {args.min_hours:g}"
    rc = receive_cost(cfg_plain, load_cfg(root, section), logs[0], args.cost_frames, args.rounds)
    gateway_ticks = math.ceil(params.min_hours * 3600.0 / params.period_s)
    lc = learning_cost(params, ev, args.cost_ticks or math.ceil(1.25 * gateway_ticks))
    lc["gateway_ticks"] = gateway_ticks
    print_cost(lc, rc, note)
    total = time.perf_counter() - t_all
    print(f"wall time {total:.0f} s")
    if args.json:
        doc = {
            "spec": truth["spec"],
            "arms": list(arms),
            "summary": summary,
            "machines": [{k: (v.__dict__ if hasattr(v, "__dict__") else v) for k, v in r.items()} for r in results],
            "learning_cost": lc,
            "receive_cost": rc,
            "wall_s": total,
        }
        args.json.write_text(json.dumps(doc, indent=2, default=float) + "\n")


if __name__ == "__main__":
    main()
