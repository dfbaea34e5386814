"""The diagnosis written out: report.json, report.md and the plots, all from the typed Diagnosis."""

from __future__ import annotations

import json
from pathlib import Path

from cmcan.gap.data import GapData
from cmcan.gap.diagnose import REGION_VARS
from cmcan.gap.figures import heatmap_figure, variables_figure
from cmcan.gap.result import Arrays, CandidateFit, Diagnosis, ParamFit, Regions
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

            figs = plot_gap(out, variables_figure(diag, d, arrays), heatmap_figure(d, arrays), LABELS, diag.unit)
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


def coverage_text(r: Diagnosis) -> str:
    """Which points the figures are over, e.g. ``2797 of 7198 points (steady points; not judged: 413
    near the relief valve, 3562 transient)``."""
    c = r.judged
    if c is None:
        return f"{r.points} points"
    if c.judged == c.total:
        return f"all {c.total} points ({c.on})"
    return f"{c.judged} of {c.total} points ({c.on}; not judged: {c.why()})"


def choice_text(r: Diagnosis) -> str | None:
    """What chose the answer where it was the pair search (None otherwise)."""
    ps = r.pair_search
    if ps is None or ps.chosen is None:
        return None
    pair = next((x for x in ps.pairs if x.names == ps.chosen), None)
    together = f" remove {100 * pair.heldout_reduction:.0f} % of the withheld gap together" if pair else ""
    alone = (
        f"{ps.best_single} alone {100 * ps.single_reduction:.0f} %" if ps.best_single else "alone, no effect qualified"
    )
    return (
        f"chosen by the pair search: {' + '.join(ps.chosen)}{together} ({alone}; a pair is named from "
        f"{100 * ps.needed:.0f} %)"
    )


def _pct(share: float) -> str:
    """A share in whole % (a tiny negative share is 0 %, not -0 %)."""
    return f"{round(100 * share) + 0:d} %"


def _param_text(q: ParamFit, significant: bool) -> str:
    """A fitted value as a finding, or, for one pinned on a bound without significance, as the bound it
    ran into (a value such as 1.5e-10 at the bound 0 is no finding)."""
    if q.at_bound and not significant:
        lo, hi = q.plausible
        edge = lo if abs(q.value - lo) <= abs(q.value - hi) else hi
        return f"{q.name} pinned at its bound {edge:.4g} {q.unit}: no finding"
    return f"{q.name} = {q.value:.4g} ± {q.uncertainty:.2g} {q.unit}" + (" (on bound)" if q.at_bound else "")


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
        f"- Judged: {coverage_text(r)}; the gaps and plots below are over the judged points (the table by "
        "region over every point the simulator can follow, steady and transient apart)",
        f"- Withheld for judging: `{r.holdout.spec}` ({r.holdout.points} points, {r.holdout.judged_points} judged "
        f"on {r.holdout.judged_on})",
    ]
    if r.holdout.degenerate:
        lines.append(f"- **Degenerate hold-out:** {r.holdout.degenerate}")
    lines += [
        f"- Gap before: RMSE {gb.rmse:.3g} {u} ({gb.rmse_pct:.2f} %), mean {gb.mean:+.3g} {u}; withheld "
        f"{gb.heldout_rmse:.3g} {u}",
        f"- Gap after: RMSE {ga.rmse:.3g} {u} ({ga.rmse_pct:.2f} %); withheld {ga.heldout_rmse:.3g} {u} "
        f"({100 * ga.heldout_reduction:.0f} % less)",
    ]
    if r.judged is not None and r.judged.unjudged:
        lines.append(
            f"- At every point, judged or not: RMSE {gb.all_rmse:.3g} {u} before, {ga.all_rmse:.3g} {u} after "
            f"(not judged: {r.judged.why()})"
        )
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
    lines += ["", "## Which", ""]
    lines += _which(r)
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


def _candidate_rows(cands: tuple[CandidateFit, ...]) -> list[str]:
    """Candidates that may be named first (then by withheld reduction); a fit pinned on a bound without
    significance shows as the bound it ran into, not as a value."""
    rows = [
        "| effect | fitted parameter | plausible range | withheld gap reduction | significant | may be named |",
        "|---|---|---|---|---|---|",
    ]
    for e in sorted(cands, key=lambda e: (not e.eligible, -e.heldout_reduction)):
        par = "; ".join(_param_text(q, e.significant) for q in e.params)
        rng = "; ".join(f"{q.plausible[0]:.4g} .. {q.plausible[1]:.4g}" for q in e.params)
        rows.append(
            f"| {e.name} | {par} | {rng} | {_pct(e.heldout_reduction)} | {'yes' if e.significant else 'no'} "
            f"| {'yes' if e.eligible else 'no'} |"
        )
    return rows


def _which(r: Diagnosis) -> list[str]:
    """How the answer was chosen: each effect alone, the pair search where it ran, a second effect on
    top of the first where one was sought."""
    lines: list[str] = []
    choice = choice_text(r)
    if choice:
        lines += [f"**The answer was {choice}.**", ""]
    for i, rnd in enumerate(r.rounds):
        head = (
            "Each effect alone"
            if not rnd.base
            else f"A second effect on top of {' + '.join(rnd.base)} (fitted jointly with it)"
        )
        lines += [f"### {head}", "", *_candidate_rows(rnd.candidates), ""]
        if i == 0 and r.pair_search is not None:
            lines += _pair_rows(r)
    lines.append(
        "An effect may be named when it removes at least 30 % of the withheld gap and its parameter lies 5 "
        "standard uncertainties from zero; a fit pinned on a bound is used only where nothing else qualifies."
    )
    return lines


def _pair_rows(r: Diagnosis) -> list[str]:
    ps = r.pair_search
    assert ps is not None
    single = (
        f"the best single effect ({ps.best_single}) removes {100 * ps.single_reduction:.0f} %"
        if ps.best_single
        else "no single effect may be named"
    )
    lines = [
        "### Pairs fitted jointly",
        "",
        f"No single effect leaves little but noise ({single}), so every pair was screened on the linearized "
        f"model and the most promising fitted jointly; a pair is named where it removes at least "
        f"{100 * ps.needed:.0f} % of the withheld gap and both its effects may be named.",
        "",
        "| pair | fitted parameters (each judged on top of the other) | withheld gap reduction | named |",
        "|---|---|---|---|",
    ]
    for pf in ps.pairs:
        par = "; ".join(
            f"{m.name}: "
            + ", ".join(_param_text(q, m.significant) for q in m.params)
            + ("" if m.eligible else " (may not be named)")
            for m in pf.members
        )
        lines.append(
            f"| {' + '.join(pf.names)} | {par} | {_pct(pf.heldout_reduction)} | "
            f"{'yes' if pf.names == ps.chosen else 'no'} |"
        )
    return [*lines, ""]


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
