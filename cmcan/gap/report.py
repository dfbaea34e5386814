"""The diagnosis written out: report.json, report.md and the plots it shows."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.gap.data import GapData
from cmcan.gap.diagnose import REGION_VARS

LABELS = {
    "dp_bar": "delta pressure (bar)",
    "temp_c": "oil temperature (C)",
    "pump_speed_rpm": "pump speed (rpm)",
    "pump_disp_cc": "pump displacement (cm3/rev)",
}


def write(
    out: Path, report: dict[str, Any], d: GapData, arrays: dict[str, NDArray[np.float64]], plots: bool = True
) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    written = [_atomic(out / "report.json", json.dumps(report, indent=2))]
    figs: list[str] = []
    if plots:
        try:
            figs = _plots(out, report, d, arrays)
        except ImportError:
            figs = []
    written.append(_atomic(out / "report.md", markdown(report, figs)))
    written += [out / f for f in figs]
    return written


def _atomic(path: Path, text: str) -> Path:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return path


def _plots(out: Path, report: dict[str, Any], d: GapData, arrays: dict[str, NDArray[np.float64]]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    unit = report["unit"]
    g0 = d.y - arrays["y_before"]
    g1 = d.y - arrays["y_after"]
    hold = arrays["holdout"]
    names = []
    # Heat map: mean gap over delta pressure x oil temperature.
    fig, ax = plt.subplots(figsize=(6.5, 4.8))
    xe = np.quantile(d.x.dp_bar, np.linspace(0, 1, 9))
    ye = np.quantile(d.x.temp_c, np.linspace(0, 1, 9))
    sums, _, _ = np.histogram2d(d.x.dp_bar, d.x.temp_c, bins=[xe, ye], weights=g0)
    counts, _, _ = np.histogram2d(d.x.dp_bar, d.x.temp_c, bins=[xe, ye])
    with np.errstate(invalid="ignore"):
        mean = sums / counts
    lim = np.nanmax(np.abs(mean)) if np.isfinite(mean).any() else 1.0
    im = ax.pcolormesh(xe, ye, mean.T, cmap="RdBu", vmin=-lim, vmax=lim, shading="flat")
    fig.colorbar(im, ax=ax, label=f"mean gap, measured - simulated ({unit})")
    ax.set_xlabel(LABELS["dp_bar"])
    ax.set_ylabel(LABELS["temp_c"])
    ax.set_title("gap by operating region")
    fig.tight_layout()
    fig.savefig(out / "gap_heatmap.png", dpi=100)
    plt.close(fig)
    names.append("gap_heatmap.png")
    # Gap against each variable, before and after, fit and withheld points apart.
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5))
    for ax, var in zip(axes.ravel(), REGION_VARS, strict=True):
        v = getattr(d.x, var)
        ax.plot(v[~hold], g0[~hold], ".", ms=1, alpha=0.25, color="tab:red", label="before (fit part)")
        ax.plot(v[hold], g0[hold], ".", ms=1, alpha=0.25, color="tab:orange", label="before (withheld)")
        ax.plot(v[hold], g1[hold], ".", ms=1, alpha=0.4, color="tab:blue", label="after (withheld)")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(LABELS[var])
        ax.set_ylabel(f"gap ({unit})")
    axes[0, 0].legend(markerscale=8, fontsize=8)
    fig.suptitle("measured minus simulated, before and after adding " + (", ".join(report["selected"]) or "nothing"))
    fig.tight_layout()
    fig.savefig(out / "gap_vs_variables.png", dpi=100)
    plt.close(fig)
    names.append("gap_vs_variables.png")
    return names


def markdown(r: dict[str, Any], figs: list[str]) -> str:
    u = r["unit"]
    gb, ga = r["gap_before"], r["gap_after"]
    lines = [
        f"# Sim-to-real gap: {r['source']}",
        "",
        f"**Verdict: {r['verdict']}.** Selected: {', '.join(r['selected']) or 'none'}.",
        "",
        f"- Output quantity: `{r['quantity']}` ({u}); {r['points']} points (0.1 s block means); noise level "
        f"{r['noise_level']:.2f} {u}",
        f"- Withheld for judging: `{r['holdout']['spec']}` ({r['holdout']['points']} points)",
        f"- Gap before: RMSE {gb['rmse']:.2f} {u} ({gb['rmse_pct']:.2f} %), mean {gb['mean']:+.2f} {u}; "
        f"withheld {gb['heldout_rmse']:.2f} {u}",
        f"- Gap after: RMSE {ga['rmse']:.2f} {u} ({ga['rmse_pct']:.2f} %); withheld {ga['heldout_rmse']:.2f} {u} "
        f"({100 * ga['heldout_reduction']:.0f} % less)",
        "",
        "## Where",
        "",
    ]
    dom = r["where"]["dominant_region"]
    lines.append(
        f"Most of the gap lies at {dom['variable']} {dom['range'][0]:.1f} .. {dom['range'][1]:.1f} "
        f"({100 * dom['share']:.0f} % of the squared gap). Time lag of measured behind simulated: "
        f"{r['where']['time_lag']['lag_s']:.2f} s."
    )
    lines += ["", "| variable | quartile | points | mean gap | RMSE | share |", "|---|---|---|---|---|---|"]
    for var in REGION_VARS:
        for b in r["where"]["regions"][var]:
            lines.append(
                f"| {var} | {b['range'][0]:.1f} .. {b['range'][1]:.1f} | {b['points']} | "
                f"{b['mean_gap']:+.2f} | {b['rmse']:.2f} | {100 * b['share']:.0f} % |"
            )
    for k in ("steady", "transient"):
        b = r["where"]["regions"][k]
        lines.append(f"| {k} | | {b['points']} | | {b['rmse']:.2f} | {100 * b['share']:.0f} % |")
    lines += [
        "",
        "## Which",
        "",
        "| effect | fitted parameter | withheld gap reduction | plausible | significant |",
        "|---|---|---|---|---|",
    ]
    for e in sorted(r["effects"], key=lambda e: -e["heldout_gap_reduction"]):
        par = "; ".join(
            f"{k} = {v['value']:.4g} ± {v['uncertainty']:.2g} {v['unit']}" for k, v in e["parameters"].items()
        )
        lines.append(
            f"| {e['name']} | {par} | {100 * e['heldout_gap_reduction']:.0f} % | {'yes' if e['plausible'] else 'no'} "
            f"| {'yes' if e['significant'] else 'no'} |"
        )
    if r["ambiguous"]:
        lines += [
            "",
            "Cannot be told apart on these data: "
            + "; ".join(" and ".join(g) for g in r["ambiguous"])
            + ". Data with a wider spread of the variable that separates them would decide.",
        ]
    if r["robustness"]:
        lines += [
            "",
            "Withheld-region robustness of the selection (refitted with each region withheld): "
            + ", ".join(f"{k} {100 * v:.0f} %" for k, v in r["robustness"].items())
            + ".",
        ]
    lines += ["", "## How far", "", "| region (withheld part) | RMSE before | RMSE after |", "|---|---|---|"]
    before, after = r["holdout"]["regions_before"], ga["regions_heldout"]
    for var in REGION_VARS:
        for b0, b1 in zip(before[var], after[var], strict=False):
            lines.append(
                f"| {var} {b0['range'][0]:.1f} .. {b0['range'][1]:.1f} | {b0['rmse']:.2f} | {b1['rmse']:.2f} |"
            )
    for f in figs:
        lines += ["", f"![{f}]({f})"]
    return "\n".join(lines) + "\n"
