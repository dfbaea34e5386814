"""The diagnosis written out: report.json, report.md and the plots, all from the typed Diagnosis."""

from __future__ import annotations

import json
from pathlib import Path

from cmcan.gap.data import GapData
from cmcan.gap.diagnose import REGION_VARS
from cmcan.gap.result import Arrays, Diagnosis, Regions
from cmcan.roles import DP, PUMP_DISP, PUMP_SPEED, TEMP

LABELS = {
    DP: "delta pressure (bar)",
    TEMP: "oil temperature (C)",
    PUMP_SPEED: "pump speed (rpm)",
    PUMP_DISP: "pump displacement (cm3/rev)",
}


def to_json(diag: Diagnosis) -> str:
    return json.dumps(diag.to_dict(), indent=2)


def write(out: Path, diag: Diagnosis, d: GapData, arrays: Arrays, plots: bool = True) -> list[Path]:
    """Each file is written to a temporary name and renamed, so a report is never left half-written."""
    out.mkdir(parents=True, exist_ok=True)
    written = [_atomic(out / "report.json", to_json(diag) + "\n")]
    figs: list[str] = []
    if plots:
        try:
            from cmcan.plots import plot_gap

            figs = plot_gap(out, diag, d, arrays, REGION_VARS, LABELS)
        except ImportError:  # no matplotlib: the report without figures
            figs = []
    written.append(_atomic(out / "report.md", markdown(diag, figs)))
    written += [out / f for f in figs]
    return written


def _atomic(path: Path, text: str) -> Path:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return path


def _answer(diag: Diagnosis) -> str:
    if not diag.groups:
        return "none"
    return "; ".join(" or ".join(g) if len(g) > 1 else g[0] for g in diag.groups)


def markdown(r: Diagnosis, figs: list[str]) -> str:
    u = r.unit
    gb, ga = r.before, r.after
    conf = r.confidence
    lines = [
        f"# Sim-to-real gap: {r.source}",
        "",
        f"**Verdict: {r.verdict}.** Effect(s): {_answer(r)}" + (f"; confidence **{conf.level}**." if conf else "."),
        "",
    ]
    if conf and conf.reasons:
        lines += ["Not higher because: " + "; ".join(conf.reasons) + ".", ""]
    for f in r.flags:
        lines += [f"- **Flag ({f.code}):** {f.message}"]
    if r.flags:
        lines.append("")
    kind = "0.1 s block means" if r.data_kind == "series" else "operating points (one per row)"
    lines += [
        f"- Output quantity: `{r.quantity}` ({u}); {r.points} points ({kind}); noise level {r.noise_level:.3g} {u}",
    ]
    if r.refused_points:
        lines.append(f"- Left out as implausible (the monitor's gate): {r.refused_points} points; {r.refused_why}")
    lines += [
        f"- Withheld for judging: `{r.holdout.spec}` ({r.holdout.points} points, {r.holdout.judged_points} judged "
        f"on {r.holdout.judged_on})",
        f"- Gap before: RMSE {gb.rmse:.3g} {u} ({gb.rmse_pct:.2f} %), mean {gb.mean:+.3g} {u}; withheld "
        f"{gb.heldout_rmse:.3g} {u}",
        f"- Gap after: RMSE {ga.rmse:.3g} {u} ({ga.rmse_pct:.2f} %); withheld {ga.heldout_rmse:.3g} {u} "
        f"({100 * ga.heldout_reduction:.0f} % less)",
    ]
    if r.fitted:
        par = "; ".join(
            f"{f.name}.{q.name} = {q.value:.4g} ± {q.uncertainty:.2g} {q.unit}" for f in r.fitted for q in f.params
        )
        lines.append(f"- Fitted: {par}")
    lines += ["", "## Where", ""]
    dom, lag = r.where.dominant, r.where.time_lag
    if dom is not None:
        lines.append(
            f"Most of the gap lies at {dom.variable} {dom.lo:.4g} .. {dom.hi:.4g} "
            f"({100 * dom.share:.0f} % of the squared gap at judged points)."
        )
    if lag is not None:
        lines.append(f"Time lag of measured behind simulated: {lag.lag_s:.2f} s.")
    lines += ["", "| variable | quartile | points | mean gap | RMSE | share |", "|---|---|---|---|---|---|"]
    lines += _region_rows(r.where.regions)
    lines += [
        "",
        "## Which",
        "",
        "| effect | fitted parameter | plausible range | withheld gap reduction | significant |",
        "|---|---|---|---|---|",
    ]
    for e in sorted(r.candidates, key=lambda e: -e.heldout_reduction):
        par = "; ".join(
            f"{q.name} = {q.value:.4g} ± {q.uncertainty:.2g} {q.unit}" + (" (on bound)" if q.at_bound else "")
            for q in e.params
        )
        rng = "; ".join(f"{q.plausible[0]:.4g} .. {q.plausible[1]:.4g}" for q in e.params)
        lines.append(
            f"| {e.name} | {par} | {rng} | {100 * e.heldout_reduction:.0f} % | {'yes' if e.significant else 'no'} |"
        )
    if r.ambiguous:
        lines += [
            "",
            "Cannot be told apart on these data: "
            + "; ".join(" and ".join(g) for g in r.ambiguous)
            + ". Data with a wider spread of the variable that separates them would decide.",
        ]
    if r.robustness:
        lines += [
            "",
            "Withheld-region robustness of the selection (refitted with each region withheld): "
            + ", ".join(f"{k} {100 * v:.0f} %" for k, v in r.robustness.items())
            + ".",
        ]
    if conf:
        lines += ["", "Confidence figures: " + ", ".join(f"{k} {v:.3g}" for k, v in conf.checks.items()) + "."]
    lines += ["", "## How far", "", "| region (withheld part) | RMSE before | RMSE after |", "|---|---|---|"]
    before, after = r.holdout.regions_before, r.after.regions_heldout
    for var in REGION_VARS:
        for b0, b1 in zip(before.bins.get(var, ()), after.bins.get(var, ()), strict=False):
            lines.append(f"| {var} {b0.lo:.4g} .. {b0.hi:.4g} | {b0.rmse:.3g} | {b1.rmse:.3g} |")
    for f in figs:
        lines += ["", f"![{f}]({f})"]
    return "\n".join(lines) + "\n"


def _region_rows(reg: Regions) -> list[str]:
    rows = []
    for var in REGION_VARS:
        for b in reg.bins.get(var, ()):
            rows.append(
                f"| {var} | {b.lo:.4g} .. {b.hi:.4g} | {b.points} | {b.mean_gap:+.3g} | {b.rmse:.3g} | "
                f"{100 * b.share:.0f} % |"
            )
    for name, part in (("steady", reg.steady), ("transient", reg.transient)):
        if part.points:
            rows.append(f"| {name} | | {part.points} | | {part.rmse:.3g} | {100 * part.share:.0f} % |")
    return rows
