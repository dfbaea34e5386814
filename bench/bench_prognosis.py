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
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

ALPHA = 0.2
LAMBDAS = (0.5, 0.75)
FLOOR_H = 1.0  # alpha bounds never narrower than this (the history's resolution: 0.5 h bins + filter)
HEALTHY_H = 100.0


@dataclass
class Case:
    name: str
    doc: dict[str, Any]
    fail_h: float | None  # None: healthy
    describe: str = ""


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


def wear_cases(n: int, seed: int) -> list[Case]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        onset = float(rng.uniform(10, 120))
        span = float(rng.uniform(40, 140))
        k = float(rng.uniform(1.3, 5.0))
        fail_lpm = float(rng.uniform(25, 50))
        comp = str(rng.choice(["pump", "motor"]))
        mixed = rng.random() < 0.35
        if mixed:
            duty: dict[str, Any] = {"kind": str(rng.choice(["wheel_loader", "excavator"]))}
            dname = duty["kind"]
        else:
            duty = {
                "kind": "constant",
                "pump_speed_rpm": float(rng.uniform(2000, 3000)),
                "pump_disp_pct": float(rng.uniform(70, 100)),
                "dp_bar": float(rng.uniform(250, 480)),
            }
            dname = f"const {duty['pump_speed_rpm']:.0f}rpm {duty['dp_bar']:.0f}bar"
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
                }
            ],
            "sensors": {"noise": _noise(noise_x)},
        }
        desc = f"{comp} k={k:.1f} on {onset:.0f}h span {span:.0f}h F={fail_lpm:.0f} {dname}"
        desc += f" oil+-{swing:.0f} noise x{noise_x:.1f}"
        out.append(Case(doc["name"], doc, fail_h, desc))
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
    from cmcan.frame import FrameColumns
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
    oil = params.oil
    visc = float(oil.dynamic_viscosity_pa_s(ev["ref_temp_c"])) / float(oil.dynamic_viscosity_pa_s(params.temp_ref_c))
    return float(ev["fail_extra_lpm"] * params.dp_ref_bar / ev["ref_dp_bar"] * visc)


def eol_lpm_for(case: Case, ticks: dict[str, Any]) -> float:
    """Without normalization, the machine's end of life as the monitor sees it: F scaled by the mean
    ratio of the true leakage at the evaluated operating points (the monitor's ticks: its duty, its
    oil) to the leakage at the reference point, over the worn stretch."""
    ev = case.doc["events"][0]
    tick_h = ticks["h"]
    s = np.clip((tick_h - ev["start_h"]) / (ev["fail_h"] - ev["start_h"]), 0.0, 1.0)
    x_ref = ev["fail_extra_lpm"] * s ** ev["shape"]
    worn = (s >= 0.3) & (tick_h < ev["fail_h"])
    return float(ev["fail_extra_lpm"] * np.sum(ticks["true_leak"][worn]) / np.sum(x_ref[worn]))


# -- metrics -----------------------------------------------------------------------------------------


def within(est: float, truth: float) -> bool:
    return abs(est - truth) <= max(ALPHA * truth, FLOOR_H)


def metrics(r: Result) -> dict[str, Any]:
    fail = r.case.fail_h
    assert fail is not None
    est = [e for e in r.estimates if e[0] < fail]
    out: dict[str, Any] = {"n": len(est), "first_lead_h": None, "al": {}, "ph_h": 0.0, "ph_const_h": 0.0}
    out["cov"] = (0, 0)
    if not est:
        out["al"] = dict.fromkeys(LAMBDAS, False)
        return out
    t_p = est[0][0]
    out["first_lead_h"] = fail - t_p
    for lam in LAMBDAS:
        t_l = t_p + lam * (fail - t_p)
        cur = [e for e in est if e[0] <= t_l][-1]
        out["al"][lam] = within(cur[3], fail - cur[0])
    ok = [within(e[3], fail - e[0]) for e in est]
    i = len(ok)
    while i > 0 and ok[i - 1]:
        i -= 1
    out["ph_h"] = fail - est[i][0] if i < len(est) else 0.0
    # Saxena et al.'s horizon: constant bounds, +-alpha of the span from the first estimate to failure
    band = ALPHA * (fail - t_p)
    ok2 = [abs(e[3] - (fail - e[0])) <= band for e in est]
    j = len(ok2)
    while j > 0 and ok2[j - 1]:
        j -= 1
    out["ph_const_h"] = fail - est[j][0] if j < len(est) else 0.0
    cov = sum(1 for e in est if e[2] <= fail - e[0] <= e[4])
    out["cov"] = (cov, len(est))
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
    head = f"{'case':7} {'fail_h':>7} {'eol_lpm':>7} {'warn_lead':>9} {'1st_est_lead':>12} {'al@0.5':>6}"
    head += f" {'al@0.75':>7} {'PH_h':>6} {'PH_c':>6} {'cover':>9}  scenario"
    print(head)
    ms = []
    for r in wear:
        m = metrics(r)
        ms.append(m)
        fail = r.case.fail_h
        assert fail is not None
        warn = f"{fail - r.first_warning_h:9.1f}" if r.first_warning_h is not None else f"{'-':>9}"
        lead = f"{m['first_lead_h']:12.1f}" if m["first_lead_h"] is not None else f"{'none':>12}"
        al = {lam: ("hit" if m["al"][lam] else "miss") for lam in LAMBDAS}
        c, n = m["cov"]
        cover = f"{c:3d}/{n:<3d}" + (f"{c / n:4.0%}" if n else "  - ")
        print(
            f"{r.case.name:7} {fail:7.1f} {r.eol_lpm:7.1f} {warn} {lead} {al[0.5]:>6} {al[0.75]:>7} "
            f"{m['ph_h']:6.1f} {m['ph_const_h']:6.1f} {cover:>9}  {r.case.describe}"
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
    swing = [float(r.case.doc["oil"]["swing_c"]) for r in wear]
    groups.append(("oil swing <= 8 C", [x <= 8.0 for x in swing]))
    groups.append(("oil swing >= 15 C", [x >= 15.0 for x in swing]))
    print(
        f"{'run-to-failure':22} {'n':>3} {'al@0.5':>8} {'al@0.75':>8} {'median PH_h':>11} {'median PH_c':>11}"
        f" {'coverage':>9}"
    )
    for name, sel in groups:
        sub = [m for m, k in zip(ms, sel, strict=True) if k]
        if not sub:
            continue
        a5 = sum(m["al"][0.5] for m in sub) / len(sub)
        a75 = sum(m["al"][0.75] for m in sub) / len(sub)
        ph = statistics.median(m["ph_h"] for m in sub)
        phc = statistics.median(m["ph_const_h"] for m in sub)
        c_in, c_n = sum(m["cov"][0] for m in sub), sum(m["cov"][1] for m in sub)
        cov = c_in / c_n if c_n else math.nan
        print(f"{name:22} {len(sub):3d} {a5:8.1%} {a75:8.1%} {ph:11.1f} {phc:11.1f} {cov:9.1%}")
    print()
    a5 = sum(m["al"][0.5] for m in ms) / len(ms)
    med_ph = statistics.median(m["ph_h"] for m in ms)
    c_in, c_n = sum(m["cov"][0] for m in ms), sum(m["cov"][1] for m in ms)
    cov = c_in / c_n if c_n else math.nan
    rows = [
        ("alpha-lambda hit rate at lambda 0.5", f"{a5:.1%}", ">= 80 %", a5 >= 0.8),
        ("median prognostic horizon (PH_h)", f"{med_ph:.1f} h", ">= 20 h", med_ph >= 20.0),
        ("10-90 % interval coverage", f"{cov:.1%}", "70-95 %", 0.7 <= cov <= 0.95),
        (f"false trends on healthy 100 h runs (of {len(healthy)})", f"{false}", "0", false == 0),
    ]
    print(f"{'target':50} {'value':>8}  {'wanted':>8}")
    for name, v, target, met in rows:
        print(f"{name:50} {v:>8}  {target:>8}  {'met' if met else 'MISSED'}")
    print(f"wall time {wall:.0f} s")


if __name__ == "__main__":
    main()
