"""Benchmark: the prognosis against the simulator's run-to-failure truth, and on healthy drives.

Run-to-failure scenarios are drawn from a seed (not the shipped ones): wear of the pump or the motor
with its onset, span (onset to failure), shape (the exponent k of x = F s^k) and leakage at failure
varied; constant duty at various operating points or mixed wheel-loader / excavator work; the oil
cycling by a few to 25 C; sensor noise scaled 0.5-2x. Each is simulated in bursts (10 s every 15 min
of operating time), replayed through the shipped monitor (columnar engine), and its evaluated ticks
(raw extra leakage (predicted - measured) * lpm_per_unit, raw ratio, dp and oil temperature, as the
ticks carry them) are fed to the prognosis, which refers the leakage to its reference conditions; an
estimate is taken every operating hour.

End of life is the machine's, as its configuration would give it: the leakage at loss of function
(the scenario's ``fail_extra_lpm``, stated at 480 bar and 60 C) referred to the stage's reference
conditions (the same by default). With ``--without-normalization`` (the comparison: every tick taken
as if at the reference conditions) it is that leakage as the monitor sees it on that machine's duty
and oil, i.e. scaled by the simulated truth's mean ratio of leakage at the evaluated operating points
to leakage at the reference point over the worn stretch (an oracle for the level, not for the time).
Truth is the scenario's failure hour.

Metrics (alpha = 20 %), over estimates from the first trend reported until failure:
- alpha-lambda: at lambda = 0.5 and 0.75 of the way from the first estimate to failure, the median
  estimate then in force within alpha of the true remaining hours;
- prognostic horizon: hours before failure from which every estimate stays within alpha of the truth
  (bounds never narrower than +-1 h, the history's resolution);
- coverage: share of estimates whose 10-90 % interval holds the truth (pooled; target 70-95 %);
- false trends: healthy 100 h runs (the shipped healthy_mixed_100h and variants) with any estimate
  other than ``none``.

    python bench/bench_prognosis.py [--scenarios 24] [--seed 7] [--jobs 2] [--without-normalization]
                                    [--only 0,3] [--cache DIR]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import prognostics_metrics as mx  # a sibling module: the metrics a test holds against progpy's

# The degradation families (issue 40): the simulator's own law (laminar power-law wear from an onset),
# orifice leaks (sqrt(dp), no viscosity), staged damage, and a duty change in mid-life that changes
# the wear's pace.
FAMILIES = ("power", "orifice", "steps", "duty_change")
ALPHA = 0.2
LAMBDAS = (0.5, 0.75)
LATE_AT_H = (20.0, 10.0)  # hours before end of life at which an estimate must not be late
LATE_SHARE = 0.2  # late: the p50 promises more than 120 % of the true hours left
FLOOR_H = 1.0  # alpha bounds never narrower than this (the history's resolution: 0.5 h bins + filter)
HEALTHY_H = 100.0


@dataclass
class Case:
    name: str
    doc: dict[str, Any]
    fail_h: float | None  # None: healthy
    describe: str = ""
    family: str = "healthy"


@dataclass
class Result:
    case: Case
    eol_lpm: float = math.nan
    estimates: list[tuple[float, str, float, float, float]] = field(default_factory=list)  # (h, state, p10, p50, p90)
    first_warning_h: float | None = None
    seconds: float = 0.0
    max_t: float = 0.0
    max_rise: float = 0.0
    max_t_high: float = 0.0
    max_rise_pct: float = 0.0


def _duty(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    """Constant work at an operating point (65 %) or a mixed wheel-loader / excavator cycle."""
    if rng.random() < 0.35:
        duty: dict[str, Any] = {"kind": str(rng.choice(["wheel_loader", "excavator"]))}
        return duty, duty["kind"]
    duty = {
        "kind": "constant",
        "pump_speed_rpm": float(rng.uniform(2000, 3000)),
        "pump_disp_pct": float(rng.uniform(70, 100)),
        "dp_bar": float(rng.uniform(250, 480)),
    }
    return duty, f"const {duty['pump_speed_rpm']:.0f}rpm {duty['dp_bar']:.0f}bar"


def wear_cases(n: int, seed: int, families: tuple[str, ...] = FAMILIES) -> list[Case]:
    """``n`` run-to-failure cases, the families in turn (case i is of family i mod their number)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        family = families[i % len(families)]
        onset = float(rng.uniform(10, 120))
        span = float(rng.uniform(40, 140))
        k = float(rng.uniform(1.3, 5.0))
        fail_lpm = float(rng.uniform(25, 50))
        comp = str(rng.choice(["pump", "motor"]))
        duty, dname = _duty(rng)
        law: dict[str, Any] = {}
        if family == "orifice":  # a crack or a torn seal: sqrt(dp), no viscosity term
            law = {"law": "orifice"}
        elif family == "steps":  # damage in stages: the curve reached in 2-6 jumps
            law = {"growth": "steps", "steps": int(rng.integers(2, 7))}
        elif family == "duty_change":  # moved to other work in mid-life: another duty, another pace
            at = float(rng.uniform(onset + 0.2 * span, onset + 0.7 * span))
            after, aname = _duty(rng)
            heavier = rng.random() < 0.6
            factor = float(rng.uniform(1.5, 3.0) if heavier else rng.uniform(0.4, 0.7))
            duty = {"kind": "change", "at_h": round(at, 2), "before": duty, "after": after}
            dname = f"{dname} -> {aname} at {at:.0f}h"
            law = {"rate_change_h": round(at, 2), "rate_factor": round(factor, 2)}
        swing = float(rng.choice([3.0, 8.0, 15.0, 25.0]))
        oil = {
            "model": "prescribed",
            "temp_c": float(rng.uniform(50, 65)),
            "swing_c": swing,
            "period_h": float(rng.uniform(8, 24)),
        }
        noise_x = float(rng.uniform(0.5, 2.0))
        fail_h = round(onset + span, 2)
        doc = {
            "name": f"wear{i:02d}",
            "seed": int(rng.integers(1, 2**31)),
            "duration_h": fail_h,
            "sampling": {"mode": "bursts", "burst_s": 10, "every_min": 15},
            "oil": oil,
            "duty": duty,
            "events": [
                {
                    "type": "wear",
                    "component": comp,
                    "start_h": round(onset, 2),
                    "fail_h": fail_h,
                    "fail_extra_lpm": round(fail_lpm, 1),
                    "shape": round(k, 2),
                    **law,
                }
            ],
            "sensors": {"noise": _noise(noise_x)},
        }
        desc = f"{comp} k={k:.1f} on {onset:.0f}h span {span:.0f}h F={fail_lpm:.0f} {dname}"
        desc += f" oil+-{swing:.0f} noise x{noise_x:.1f}"
        if "steps" in law:
            desc += f" {law['steps']} steps"
        if "rate_factor" in law:
            desc += f" pace x{law['rate_factor']}"
        out.append(Case(doc["name"], doc, fail_h, desc, family))
    return out


def _noise(x: float) -> dict[str, float]:
    base = {
        "pump_speed_rpm": 1.5,
        "pump_disp_cc": 0.15,
        "high_pressure_bar": 1.5,
        "low_pressure_bar": 0.3,
        "temp_c": 0.1,
        "motor_speed_rpm": 3.0,
    }
    return {k: v * x for k, v in base.items()}


def healthy_cases(seed: int) -> list[Case]:
    from cmcan.sim import scenario as scn

    shipped = dict(scn.load(scn.shipped("healthy_mixed_100h")).document)
    out = [Case("healthy_mixed_100h", shipped, None, "shipped: wheel loader, oil 30-90 C")]
    rng = np.random.default_rng(seed + 1)
    variants = [
        ({"kind": "excavator"}, 60.0, 25.0, 1.0),
        ({"kind": "wheel_loader"}, 55.0, 20.0, 2.0),
        ({"kind": "constant", "pump_speed_rpm": 2600.0, "pump_disp_pct": 90.0, "dp_bar": 420.0}, 55.0, 20.0, 1.0),
        ({"kind": "constant", "pump_speed_rpm": 3000.0, "pump_disp_pct": 100.0, "dp_bar": 480.0}, 60.0, 3.0, 2.0),
    ]
    for j, (duty, temp, swing, nx) in enumerate(variants):
        doc = {
            "name": f"healthy{j}",
            "seed": int(rng.integers(1, 2**31)),
            "duration_h": HEALTHY_H,
            "sampling": {"mode": "bursts", "burst_s": 10, "every_min": 15},
            "oil": {"model": "prescribed", "temp_c": temp, "swing_c": swing, "period_h": float(rng.uniform(8, 24))},
            "duty": duty,
            "sensors": {"noise": _noise(nx)},
        }
        out.append(Case(doc["name"], doc, None, f"{duty['kind']} oil {temp:.0f}+-{swing:.0f} noise x{nx:g}"))
    return out


def run_case(
    case: Case, normalized: bool = True, cache: str | None = None, overrides: dict[str, float] | None = None
) -> Result:
    from cmcan import config as cfgmod
    from cmcan.monitor.prognosis import Prognosis, PrognosisParams

    t_start = time.perf_counter()
    cfg = cfgmod.load()
    ticks = _cached_ticks(case, cfg, cache)
    h, leak, ratio, dp, temp = (ticks[k] for k in ("h", "leak", "ratio", "dp", "temp"))
    ok = np.ones(len(h), bool)
    params = PrognosisParams(low_pct=cfg.thresholds.low_pct, oil=cfg.oil)
    if not normalized:  # the comparison: every tick at the reference conditions, gain 1
        dp, temp = np.full(len(h), params.dp_ref_bar), np.full(len(h), params.temp_ref_c)

    res = Result(case)
    if case.fail_h is None:
        res.eol_lpm = 40.0
    elif normalized:
        res.eol_lpm = eol_ref_lpm(case, params)
    else:
        res.eol_lpm = eol_lpm_for(case, ticks)
    params = replace(params, eol_kind="leak_lpm", eol_value=res.eol_lpm, **(overrides or {}))
    prog = Prognosis(params)
    res.first_warning_h = float(ticks["first_low_h"]) if math.isfinite(ticks["first_low_h"]) else None
    # fed hour by hour, an estimate after each (the daemon would estimate as each bin closes)
    end = float(h[-1]) if len(h) else 0.0
    edges = np.searchsorted(h, np.arange(1.0, end + 1.0))
    a = 0
    for z in edges.tolist():
        prog.add_columns(h[a:z], leak[a:z], ratio[a:z], dp[a:z], temp[a:z], ok[a:z])
        a = z
        e = prog.estimate()
        if case.fail_h is not None and e.at_h >= case.fail_h:
            break
        res.max_t = max(res.max_t, e.t_stat)
        res.max_rise = max(res.max_rise, e.rise_lpm)
        res.max_t_high = max(res.max_t_high, e.t_stat_high)
        res.max_rise_pct = max(res.max_rise_pct, e.rise_pct)
        if e.state != "none":
            res.estimates.append((e.at_h, e.state, *e.to_eol_h))
    res.seconds = time.perf_counter() - t_start
    return res


def _cached_ticks(case: Case, cfg: Any, cache: str | None) -> dict[str, Any]:
    """The case's evaluated ticks (simulated and replayed through the shipped monitor), from ``cache``
    when it holds them: the prognosis can be iterated on without simulating again."""
    key = hashlib.sha256(json.dumps(case.doc, sort_keys=True).encode()).hexdigest()[:16]
    path = os.path.join(cache, f"{case.name}-{key}.npz") if cache else None
    if path and os.path.exists(path):
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    out = simulate_ticks(case, cfg)
    if path:
        os.makedirs(cache, exist_ok=True)
        np.savez(path + ".tmp.npz", **out)
        os.replace(path + ".tmp.npz", path)
    return out


def simulate_ticks(case: Case, cfg: Any) -> dict[str, Any]:
    """Simulate the case, replay it through the shipped monitor (columnar engine) and keep its
    evaluated ticks: hour, raw extra leakage ((predicted - measured) * lpm_per_unit), raw ratio, dp
    and oil temperature (the tick's window means), and, for the oracle end of life, the simulated
    truth's extra leakage at those hours."""
    from cmcan.assemble import assemble, dbc_for
    from cmcan.can.frame import FrameColumns
    from cmcan.replay import replay_columns
    from cmcan.sim import scenario as scn
    from cmcan.sim.frames import frames_from_run
    from cmcan.sim.run import simulate

    db = dbc_for(cfg)
    s = scn.from_dict(case.doc, source=case.name)
    run = simulate(s, db)
    fr = frames_from_run(run, db)
    n = len(fr)
    cols = FrameColumns(
        timestamp_s=fr.timestamp_s,
        channel=np.zeros(n, np.int16),
        channel_names=("can0",),
        arbitration_id=fr.arbitration_id.astype(np.uint32),
        extended=fr.is_extended(),
        remote=np.zeros(n, bool),
        error=np.zeros(n, bool),
        fd=np.zeros(n, bool),
        dlc=fr.dlc.astype(np.int16),
        data=fr.data,
    )
    sink = _Ticks(cfg.lpm_per_unit)
    mon = assemble(cfg).monitor
    step = 200_000
    summary = replay_columns(mon, (cols_slice(cols, a, a + step) for a in range(0, n, step)), [sink])
    out = sink.arrays(run.start_epoch_s)
    out["true_leak"] = np.interp(out["h"], run["operating_h"], run["true_extra_leak_lpm"])
    lows = [w["operating_h"] for w in summary.warnings if w["to"] == "low"]
    out["first_low_h"] = np.float64(lows[0] if lows else math.nan)
    return out


def cols_slice(c: Any, a: int, z: int) -> Any:
    from dataclasses import replace

    return replace(
        c,
        **{
            k: getattr(c, k)[a:z]
            for k in ("timestamp_s", "channel", "arbitration_id", "extended", "remote", "error", "fd", "dlc", "data")
        },
    )


class _Ticks:
    """Keeps the evaluated ticks' hour, raw leakage and ratio, dp and oil temperature."""

    wants_ticks = True
    wants_frames = False

    def __init__(self, lpm_per_unit: float) -> None:
        self.lpm_per_unit = lpm_per_unit
        self.parts: list[tuple[np.ndarray, ...]] = []

    def start(self, t0: float) -> None:
        pass

    def ticks(self, c: Any) -> None:
        from cmcan.monitor.gating import EVALUATED

        ev = np.isin(c.gate, np.array(sorted(int(g) for g in EVALUATED)))
        leak = (c.predicted[ev] - c.measured[ev]) * self.lpm_per_unit  # as the core's Point.leak_lpm
        self.parts.append((c.t_run_s[ev], leak, c.ratio_raw_pct[ev], c.dp_bar[ev], c.temp_c[ev]))

    def frames(self, frames: Any) -> None:
        pass

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass

    def arrays(self, start_epoch_s: float) -> dict[str, np.ndarray]:
        names = ("h", "leak", "ratio", "dp", "temp")
        if not self.parts:
            return {k: np.empty(0) for k in names}
        t, lk, r, dp, tc = (np.concatenate(x) for x in zip(*self.parts, strict=True))
        return dict(zip(names, ((t - start_epoch_s) / 3600.0, lk, r, dp, tc), strict=True))


def eol_ref_lpm(case: Case, params: Any) -> float:
    """The machine's end of life at the stage's reference conditions: the leakage at loss of function
    (stated at the scenario's reference point) referred to them by the laminar law, as a machine's
    configuration would state it from a rig test."""
    from cmcan.sim import scenario as scn

    ev = scn.from_dict(case.doc).document["events"][0]
    if ev.get("law") == "orifice":  # an orifice leaks with sqrt(dp), whatever the oil
        return float(ev["fail_extra_lpm"] * math.sqrt(params.dp_ref_bar / ev["ref_dp_bar"]))
    oil = params.oil
    visc = float(oil.dynamic_viscosity_pa_s(ev["ref_temp_c"])) / float(oil.dynamic_viscosity_pa_s(params.temp_ref_c))
    return float(ev["fail_extra_lpm"] * params.dp_ref_bar / ev["ref_dp_bar"] * visc)


def eol_lpm_for(case: Case, ticks: dict[str, Any]) -> float:
    """Without normalization, the machine's end of life as the monitor sees it: F scaled by the mean
    ratio of the true leakage at the evaluated operating points (the monitor's ticks: its duty, its
    oil) to the leakage at the reference point, over the worn stretch."""
    from cmcan.sim.degradation import wear_lpm, wear_progress

    ev = case.doc["events"][0]
    tick_h = ticks["h"]
    x_ref = wear_lpm(ev, tick_h)
    worn = (wear_progress(ev, tick_h) >= 0.3) & (tick_h < ev["fail_h"])
    return float(ev["fail_extra_lpm"] * np.sum(ticks["true_leak"][worn]) / np.sum(x_ref[worn]))


# -- metrics -----------------------------------------------------------------------------------------


def metrics(r: Result) -> dict[str, Any]:
    """One run's figures (bench/prognostics_metrics.py: Saxena et al.'s, as progpy computes them)."""
    fail = r.case.fail_h
    assert fail is not None
    est = [mx.Estimate(h, p10, p50, p90) for h, _state, p10, p50, p90 in r.estimates if h < fail]
    out: dict[str, Any] = {"n": len(est), "first_lead_h": fail - est[0].at_h if est else None}
    out["al"] = {lam: mx.alpha_lambda(est, fail, lam, ALPHA, FLOOR_H) for lam in LAMBDAS}
    out["ra"] = {}
    for lam in LAMBDAS:
        e = mx.at_lambda(est, fail, lam)
        out["ra"][lam] = mx.relative_accuracy(e, fail) if e is not None else math.nan
    out["ph_h"] = mx.horizon_stays(est, fail, ALPHA, FLOOR_H)
    out["ph_first_h"] = mx.horizon_first(est, fail, ALPHA, FLOOR_H)
    out["cov"] = mx.coverage(est, fail)
    out["late"] = {b: mx.lateness(est, fail, b, LATE_SHARE) for b in LATE_AT_H}
    out["p10_above"] = {}  # the estimate then in force has its p10 above the truth: even the early end is late
    for b in LATE_AT_H:
        e = mx.in_force(est, fail - b)
        out["p10_above"][b] = e is not None and e.p10 > fail - e.at_h
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", type=int, default=24, help="run-to-failure scenarios (at least 20 for the issue)")
    ap.add_argument("--seed", type=int, default=7, help="draws the scenarios")
    ap.add_argument("--jobs", type=int, default=2, help="processes")
    ap.add_argument("--no-healthy", action="store_true", help="skip the healthy 100 h runs")
    ap.add_argument("--dump", help="write every estimate to this JSON file")
    ap.add_argument(
        "--without-normalization",
        action="store_true",
        help="the comparison: every tick taken at the reference conditions (the leakage as measured, not "
        "referred to them), end of life as the monitor sees it at the machine's duty and oil",
    )
    ap.add_argument("--only", help="run only these wear scenarios, by index: 0,3,7 (iterating on a subset)")
    ap.add_argument("--cache", help="keep each case's evaluated ticks in this folder and reuse them")
    ap.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="a PrognosisParams field for a what-if"
    )
    args = ap.parse_args()
    wear = wear_cases(args.scenarios, args.seed)
    if args.only:
        wear = [wear[int(i)] for i in args.only.split(",")]
    cases = wear + ([] if args.no_healthy else healthy_cases(args.seed))
    t0 = time.perf_counter()
    n = len(cases)
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        sets = dict(_setting(kv) for kv in args.set)
        results = list(ex.map(run_case, cases, [not args.without_normalization] * n, [args.cache] * n, [sets] * n))
    wall = time.perf_counter() - t0
    if args.dump:
        with open(args.dump, "w", encoding="utf-8") as f:
            json.dump([{"case": r.case.name, "fail_h": r.case.fail_h, "estimates": r.estimates} for r in results], f)
    report([r for r in results if r.case.fail_h is not None], [r for r in results if r.case.fail_h is None], wall)


def _setting(kv: str) -> tuple[str, float]:
    key, _, value = kv.partition("=")
    return key.strip(), float(value)


def report(wear: list[Result], healthy: list[Result], wall: float) -> None:
    print(f"alpha {ALPHA:.0%}; estimates every operating hour from the first trend to failure; EOL p50 vs truth")
    print("PH_h: every estimate after it within +-alpha of the true hours left (at least +-1 h);")
    print("PH_c: the same with Saxena et al.'s constant bounds, +-alpha of the first estimate's hours left")
    head = f"{'case':7} {'family':11} {'fail_h':>7} {'eol_lpm':>7} {'warn_lead':>9} {'1st_est':>7} {'al@0.5':>6}"
    head += f" {'al@0.75':>7} {'RA@0.5':>6} {'PH_h':>6} {'PH_1st':>6} {'cover':>9} {'@20h':>4} {'@10h':>4}  scenario"
    print(head)
    ms = []
    for r in wear:
        m = metrics(r)
        ms.append(m)
        fail = r.case.fail_h
        assert fail is not None
        warn = f"{fail - r.first_warning_h:9.1f}" if r.first_warning_h is not None else f"{'-':>9}"
        lead = f"{m['first_lead_h']:7.1f}" if m["first_lead_h"] is not None else f"{'none':>7}"
        al = {lam: ("hit" if m["al"][lam] else "miss") for lam in LAMBDAS}
        c, n = m["cov"]
        cover = f"{c:3d}/{n:<3d}" + (f"{c / n:4.0%}" if n else "  - ")
        print(
            f"{r.case.name:7} {r.case.family:11} {fail:7.1f} {r.eol_lpm:7.1f} {warn} {lead} {al[0.5]:>6} "
            f"{al[0.75]:>7} {m['ra'][0.5]:6.2f} {m['ph_h']:6.1f} {m['ph_first_h']:6.1f} {cover:>9} "
            f"{m['late'][20.0]:>4} {m['late'][10.0]:>4}  {r.case.describe}"
        )
    print()
    print("healthy runs (100 h): state reported, largest rise and t of the rise tested, of the leakage (l/min)")
    print("and of the high side (the share of displacement the motor lacks, %)")
    false = 0
    for r in healthy:
        bad = len(r.estimates)
        false += bad > 0
        state = f"TREND x{bad}" if bad else "none"
        print(
            f"  {r.case.name:20} {state:>10}  rise {r.max_rise:5.2f}  t {r.max_t:5.1f}"
            f"  high: rise {r.max_rise_pct:5.2f}  t {r.max_t_high:5.1f}  {r.case.describe}"
        )
    print()
    groups = [("all", [True] * len(wear))]
    groups += [(f, [r.case.family == f for r in wear]) for f in FAMILIES]
    groups += [(c, [r.case.doc["events"][0]["component"] == c for r in wear]) for c in ("pump", "motor")]
    groups.append(("mixed duty", [r.case.doc["duty"]["kind"] != "constant" for r in wear]))
    swing = [float(r.case.doc["oil"]["swing_c"]) for r in wear]
    groups.append(("oil swing >= 15 C", [x >= 15.0 for x in swing]))
    print("late: the estimate in force 20 h (10 h) before end of life promises > 120 % of the hours left")
    print("(of the runs with an estimate then; 'none': runs without one); p10>: its p10 above the truth")
    print(
        f"{'run-to-failure':18} {'n':>3} {'al@0.5':>7} {'al@0.75':>7} {'RA@0.5':>6} {'PH_h':>6} {'PH_1st':>6}"
        f" {'coverage':>8} {'late@20h':>9} {'none':>4} {'late@10h':>9} {'none':>4} {'p10>@20':>7} {'p10>@10':>7}"
    )
    table = {}
    for name, sel in groups:
        sub = [m for m, k in zip(ms, sel, strict=True) if k]
        if not sub:
            continue
        row = _summary(sub)
        table[name] = row
        print(
            f"{name:18} {len(sub):3d} {row['al5']:7.0%} {row['al75']:7.0%} {row['ra5']:6.2f} {row['ph']:6.1f}"
            f" {row['ph1']:6.1f} {row['cov']:8.0%} {row['late20']:9.0%} {row['none20']:4d} {row['late10']:9.0%}"
            f" {row['none10']:4d} {row['p10_20']:7.0%} {row['p10_10']:7.0%}"
        )
    print()
    print(f"{'target':58} {'value':>8}  {'wanted':>8}")
    for name in ["all", *FAMILIES]:
        if name not in table:
            continue
        row = table[name]
        rows = [
            (f"{name}: alpha-lambda hit rate at lambda 0.5", f"{row['al5']:.0%}", ">= 80 %", row["al5"] >= 0.8),
            (f"{name}: median prognostic horizon (PH_h)", f"{row['ph']:.1f} h", ">= 20 h", row["ph"] >= 20.0),
            (f"{name}: 10-90 % interval coverage", f"{row['cov']:.0%}", "70-95 %", 0.7 <= row["cov"] <= 0.95),
            (f"{name}: late by > 20 % at 20 h / 10 h", f"{row['late20']:.0%}/{row['late10']:.0%}", "<= 5 %",
             max(row["late20"], row["late10"]) <= 0.05),
        ]  # fmt: skip
        for label, v, target, met in rows:
            print(f"{label:58} {v:>8}  {target:>8}  {'met' if met else 'MISSED'}")
    print(f"{f'false trends on healthy 100 h runs (of {len(healthy)})':58} {false:>8}  {'0':>8}  ", end="")
    print("met" if false == 0 else "MISSED")
    print(f"wall time {wall:.0f} s")


def _summary(sub: list[dict[str, Any]]) -> dict[str, Any]:
    def share(flags: list[bool]) -> float:
        return sum(flags) / len(flags) if flags else 0.0

    ras = [m["ra"][0.5] for m in sub if math.isfinite(m["ra"][0.5])]
    c_in, c_n = sum(m["cov"][0] for m in sub), sum(m["cov"][1] for m in sub)
    row: dict[str, Any] = {
        "al5": share([m["al"][0.5] for m in sub]),
        "al75": share([m["al"][0.75] for m in sub]),
        "ra5": statistics.median(ras) if ras else math.nan,
        "ph": statistics.median(m["ph_h"] for m in sub),
        "ph1": statistics.median(m["ph_first_h"] for m in sub),
        "cov": c_in / c_n if c_n else math.nan,
    }
    for b, key in ((20.0, "20"), (10.0, "10")):
        seen = [m for m in sub if m["late"][b] != "none"]
        row["late" + key] = share([m["late"][b] == "late" for m in seen])
        row["none" + key] = len(sub) - len(seen)
        row["p10_" + key] = share([m["p10_above"][b] for m in seen])
    return row


if __name__ == "__main__":
    main()
