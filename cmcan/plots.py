"""Every plot cmcan draws (matplotlib, the ``plot`` extra), in one place and one style."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cmcan.monitor.tick import LEVEL_NAMES
from cmcan.monitor.warnings import Level, Thresholds


def _pyplot() -> Any:
    """matplotlib without a display (raises ImportError when the extra is missing)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_ratio(
    tl: Any,
    t0: float,
    low_pct: float,
    high_pct: float,
    path: str | Path,
    failures_h: list[float] | None = None,
    title: str = "CM ratio",
) -> None:
    """CM ratio over operating hours with the thresholds (the paper's Figure 9); ``tl`` is a
    :class:`cmcan.replay.TickColumns`."""
    plt = _pyplot()
    h_all = (tl.t_run_s - t0) / 3600.0  # operating hours: the wall clock's steps undone
    ev = tl.ratio_raw_pct > 0
    fv = tl.filt_valid
    fig, ax = plt.subplots(figsize=(11, 4.2))
    if ev.any():
        ax.plot(h_all[ev], tl.ratio_raw_pct[ev], ".", ms=1, alpha=0.3, color="tab:gray", label="raw")
    if fv.any():
        h, filt = h_all[fv], tl.ratio_filt_pct[fv]
        ax.plot(h, filt, "-", lw=1.2, color="tab:blue", label="filtered")
        for level, color in ((Level.LOW, "tab:orange"), (Level.HIGH, "tab:purple"), (Level.FAULT, "tab:red")):
            mask = tl.level[fv] == int(level)
            if mask.any():
                ax.plot(h[mask], filt[mask], "o", ms=2, color=color, label=f"warning {LEVEL_NAMES[level]}")
    ax.axhline(low_pct, color="tab:orange", ls="--", lw=1, label=f"low {low_pct:g} %")
    ax.axhline(high_pct, color="tab:purple", ls="--", lw=1, label=f"high {high_pct:g} %")
    for f in failures_h or []:
        ax.axvline(f, color="tab:red", lw=1, alpha=0.6)
    ax.set_xlabel("operating hours (h)")
    ax.set_ylabel("CM ratio (%)")
    filt_all = tl.ratio_filt_pct[fv]
    lo = min(low_pct - 3, float(filt_all.min())) if fv.any() else low_pct - 3
    hi = max(high_pct + 3, float(filt_all.max())) if fv.any() else high_pct + 3
    ax.set_ylim(max(lo, 50), min(hi, 150))
    ax.set_title(title)
    ax.legend(loc="lower left", fontsize=7, ncol=3, markerscale=3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_demo(res: Any, thresholds: Thresholds, path: str | Path) -> None:
    """The demo's CM ratio as the bus carried it, thresholds, failures and lead times (paper Figure 9)."""
    plt = _pyplot()

    fig, ax = plt.subplots(figsize=(11, 4.5))
    ax.plot(res.ratio_h, res.ratio_pct, ".", ms=1.5, color="tab:blue", label="filtered CM ratio (from CM_RATIO)")
    ax.axhline(thresholds.low_pct, color="tab:orange", ls="--", lw=1, label=f"low threshold {thresholds.low_pct:g} %")
    ax.axhline(
        thresholds.high_pct, color="tab:purple", ls="--", lw=1, label=f"high threshold {thresholds.high_pct:g} %"
    )
    for f in res.failures:
        ax.axvline(f["fail_h"], color="tab:red", lw=1.2)
        ax.annotate(
            f"{f['component']} {f['kind']}",
            (f["fail_h"], 1.0),
            xycoords=("data", "axes fraction"),
            color="tab:red",
            fontsize=8,
            rotation=90,
            va="top",
            ha="right",
        )
        if f["first_warning_h"] is not None:
            ax.axvline(f["first_warning_h"], color="tab:orange" if f["level"] == "low" else "tab:purple", lw=1, ls=":")
            ax.annotate(f"lead {f['lead_h']:.0f} h", (f["first_warning_h"], thresholds.low_pct - 4), fontsize=8)
    y = np.asarray(res.ratio_pct) if res.ratio_pct else np.array([100.0])
    ax.set_ylim(max(80.0, float(y.min()) - 1), min(115.0, float(y.max()) + 1))
    ax.set_xlabel("operating hours (h)")
    ax.set_ylabel("CM ratio (%)")
    ax.set_title("cmcan demo: run to failure on the test rig at 480 bar (paper Figure 9)")
    ax.legend(loc="lower left", fontsize=8)
    fig.subplots_adjust(left=0.07, right=0.98, top=0.92, bottom=0.11)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_residuals(sets: list[Any], report: dict[str, Any], path: str | Path) -> None:
    """Predicted minus actual output (motor speed or flow) over time, training end and damage onset
    marked (paper Figures 6 and 7): one panel for the training run, one for the validation run."""
    plt = _pyplot()

    by = {s.name: s for s in sets}
    panels = [("training run", ["D_trn", "D_tst"], report.get("t_trn_h"), "end of training")]
    if "D_val_healthy" in by:
        panels.append(("validation run", ["D_val_healthy", "D_val_damaged"], report.get("t_dam_h"), "damage onset"))
    extra = [s.name for s in sets if s.name not in ("D_trn", "D_tst", "D_val_healthy", "D_val_damaged")]
    for name in extra:
        panels.append((name, [name], None, ""))
    fig, axes = plt.subplots(len(panels), 1, figsize=(10, 3.2 * len(panels)), squeeze=False)
    colors = {"D_trn": "tab:blue", "D_tst": "tab:green", "D_val_healthy": "tab:green", "D_val_damaged": "tab:red"}
    for ax, (title, names, mark, label) in zip(axes[:, 0], panels, strict=True):
        for n in names:
            s = by[n]
            ax.plot(s.hours, s.pred - s.measured, ".", ms=1.5, color=colors.get(n, "tab:gray"), label=n)
            ax.plot(
                s.hours,
                s.whitebox - s.measured,
                ".",
                ms=0.8,
                alpha=0.25,
                color="tab:orange",
                label=f"{n} white-box" if n == names[0] else None,
            )
        if mark is not None:
            ax.axvline(mark, color="k", ls="--", lw=1)
            ax.text(mark, ax.get_ylim()[1], f" {label}", va="top", fontsize=8)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title(title)
        ax.set_xlabel("time (h)")
        ax.set_ylabel(f"predicted - measured ({by[names[0]].unit})")
        ax.legend(loc="lower left", fontsize=7, markerscale=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _save(fig: Any, path: Path) -> None:
    """Write a figure through a temporary file: a failed write leaves no half PNG."""
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=100)  # type: ignore[attr-defined]
    tmp.replace(path)


GAP_STYLE = {  # point kind of the gap figure -> colour, marker size, opacity, drawing order
    "not_judged": ("0.6", 1.0, 0.25, 1),
    "before_fit": ("tab:red", 1.0, 0.3, 2),
    "before_withheld": ("tab:orange", 1.2, 0.4, 3),
    "after_withheld": ("tab:blue", 1.2, 0.5, 4),
}
NO_DATA = {"facecolor": "0.88", "hatch": "////", "edgecolor": "0.6"}  # a cell without data: never "no gap"


def plot_gap(out: Path, variables: Any, heatmap: Any | None, labels: dict[str, str], unit: str) -> list[str]:
    """The gap diagnosis' figures in ``out`` from what ``cmcan.gap.figures`` computed: the gap against
    each input (judged points before and after the fitted effects, the unjudged ones in grey behind)
    and a heat map of the mean gap over delta pressure and oil temperature, empty cells hatched."""
    plt = _pyplot()
    from matplotlib.patches import Patch, Rectangle

    names = []
    if heatmap is not None:
        fig, ax = plt.subplots(figsize=(6.8, 5.0))
        xe, ye = heatmap.dp_edges, heatmap.temp_edges
        ax.add_patch(
            Rectangle((xe[0], ye[0]), xe[-1] - xe[0], ye[-1] - ye[0], zorder=0, lw=0, **NO_DATA)
        )  # shows through the cells that have no judged point (NaN is not drawn)
        mean = np.ma.masked_invalid(heatmap.mean.T)
        lim = heatmap.lim
        im = ax.pcolormesh(xe, ye, mean, cmap="RdBu", vmin=-lim, vmax=lim, shading="flat", zorder=1)
        fig.colorbar(im, ax=ax, label=f"mean gap, measured - simulated ({unit})")
        ax.set_xlim(xe[0], xe[-1])
        ax.set_ylim(ye[0], ye[-1])
        ax.set_xlabel(labels["dp_bar"])
        ax.set_ylabel(labels["temp_c"])
        ax.set_title(heatmap.title, fontsize=10)
        if heatmap.empty_cells:
            ax.legend(
                handles=[Patch(label=f"no judged point ({heatmap.empty_cells} cells)", **NO_DATA)],
                loc="upper center",
                bbox_to_anchor=(0.5, -0.12),
                fontsize=8,
                frameon=False,
            )
        fig.tight_layout()
        _save(fig, out / "gap_heatmap.png")
        plt.close(fig)
        names.append("gap_heatmap.png")
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.0))
    for ax, var in zip(axes.ravel(), variables.variables, strict=True):
        v = variables.x[var]
        for s in sorted(variables.sets, key=lambda s: GAP_STYLE[s.key][3]):
            color, ms, alpha, z = GAP_STYLE[s.key]
            ax.plot(v[s.mask], s.gap[s.mask], ".", ms=ms, alpha=alpha, color=color, label=s.label, zorder=z)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylim(*variables.ylim)
        ax.set_xlabel(labels[var])
        ax.set_ylabel(f"gap ({unit})")
    handles, texts = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, texts, loc="lower center", ncol=2, markerscale=8, fontsize=8, frameon=False)
    fig.suptitle(variables.title, fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    _save(fig, out / "gap_vs_variables.png")
    plt.close(fig)
    names.append("gap_vs_variables.png")
    return names


def plot_scores(
    x: np.ndarray,
    ratio_pct: np.ndarray,
    labels: np.ndarray | None,
    extrapolated: np.ndarray,
    low_pct: float,
    high_pct: float,
    path: str | Path,
    x_label: str,
    label_name: str = "",
    title: str = "CM ratio per operating point",
) -> None:
    """The ratio of each scored operating point (``cmcan score --plot``), coloured by a label column
    (e.g. the leakage label of a test rig), extrapolated points drawn hollow, thresholds dashed."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(11, 4.5))
    groups = [(None, np.ones(len(x), dtype=bool))]
    if labels is not None:
        groups = [(v, labels == v) for v in np.unique(labels[np.isfinite(labels)])]
    palette = ["tab:green", "tab:orange", "tab:red", "tab:purple", "tab:brown", "tab:blue", "tab:pink", "tab:olive"]
    for i, (value, m) in enumerate(groups):
        color = palette[i % len(palette)] if labels is not None else "tab:blue"
        name = f"{label_name} = {value:g}" if value is not None else "scored points"
        inside, outside = m & ~extrapolated, m & extrapolated
        if inside.any():
            ax.plot(x[inside], ratio_pct[inside], "o", ms=3, color=color, label=name)
        if outside.any():
            ax.plot(
                x[outside],
                ratio_pct[outside],
                "o",
                ms=3,
                mfc="none",
                color=color,
                label=f"{name}, extrapolated" if not inside.any() else None,
            )
    ax.axhline(low_pct, color="tab:orange", ls="--", lw=1, label=f"low {low_pct:g} %")
    ax.axhline(high_pct, color="tab:purple", ls="--", lw=1, label=f"high {high_pct:g} %")
    finite = ratio_pct[np.isfinite(ratio_pct)]
    if finite.size:
        ax.set_ylim(
            max(50.0, min(low_pct - 1, float(finite.min()) - 0.5)),
            min(150.0, max(high_pct + 1, float(finite.max()) + 0.5)),
        )
    ax.set_xlabel(x_label)
    ax.set_ylabel("CM ratio (%)")
    ax.set_title(title + ("  (hollow: outside the training envelope)" if extrapolated.any() else ""), fontsize=10)
    ax.legend(loc="lower left", fontsize=8, markerscale=1.5)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


LEVEL_COLORS = {"low": "tab:orange", "high": "tab:purple", "fault": "tab:red", "ok": "tab:green"}


def _png(fig: Any) -> bytes:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return buf.getvalue()


def plot_fleet_machine(
    hours: Any,
    raw_pct: Any,
    filt_pct: Any,
    low_pct: float,
    high_pct: float,
    events: list[tuple[float, str]],
    log_starts_h: list[float],
    title: str,
) -> bytes:
    """One machine of a fleet: the CM ratio over its operating hours (means of the timeline), the
    thresholds, each warning where it was raised and the start of each log; PNG bytes."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(10, 3.2))
    h, raw, filt = (np.asarray(x, dtype=float) for x in (hours, raw_pct, filt_pct))
    for x in log_starts_h:
        ax.axvline(x, color="0.85", lw=0.6, zorder=0)
    ok = np.isfinite(raw)
    if ok.any():
        ax.plot(h[ok], raw[ok], ".", ms=1.5, alpha=0.4, color="tab:gray", label="raw (mean)")
    okf = np.isfinite(filt)
    if okf.any():
        ax.plot(h[okf], filt[okf], "-", lw=1.2, color="tab:blue", label="filtered")
    ax.axhline(low_pct, color="tab:orange", ls="--", lw=1, label=f"low {low_pct:g} %")
    ax.axhline(high_pct, color="tab:purple", ls="--", lw=1, label=f"high {high_pct:g} %")
    seen = set()
    for x, level in events:
        ax.axvline(
            x, color=LEVEL_COLORS.get(level, "k"), lw=1.2, ls=":", label=None if level in seen else f"warning {level}"
        )
        seen.add(level)
    y = filt[okf] if okf.any() else np.array([100.0])
    ax.set_ylim(
        max(50.0, min(low_pct - 3, float(np.nanmin(y)) - 1)), min(150.0, max(high_pct + 3, float(np.nanmax(y)) + 1))
    )
    ax.set_xlabel("operating hours (h, logged time of this machine)")
    ax.set_ylabel("CM ratio (%)")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="lower left", fontsize=7, ncol=4, markerscale=4)
    fig.tight_layout()
    out = _png(fig)
    plt.close(fig)
    return out


def plot_fleet_overview(lines: list[tuple[str, Any, Any, str]], low_pct: float, high_pct: float) -> bytes:
    """Every machine's filtered CM ratio over its operating hours, coloured by its state (``lines``:
    machine, hours, ratio, state in ok/low/high/fault); PNG bytes."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(10, 3.6))
    order = sorted(lines, key=lambda x: x[3] != "ok")  # machines needing a look drawn on top
    for name, h, r, state in order:
        h, r = np.asarray(h, dtype=float), np.asarray(r, dtype=float)
        ok = np.isfinite(r)
        if not ok.any():
            continue
        color = LEVEL_COLORS.get(state, "tab:gray") if state != "ok" else "0.6"
        ax.plot(h[ok], r[ok], "-", lw=1.0 if state == "ok" else 1.6, color=color, alpha=0.8)
        if state != "ok":
            ax.annotate(
                name,
                (h[ok][-1], r[ok][-1]),
                fontsize=7,
                color=color,
                xytext=(3, 0),
                textcoords="offset points",
                va="center",
            )
    ax.axhline(low_pct, color="tab:orange", ls="--", lw=1)
    ax.axhline(high_pct, color="tab:purple", ls="--", lw=1)
    ax.set_xlabel("operating hours (h)")
    ax.set_ylabel("filtered CM ratio (%)")
    ax.set_title("Fleet: filtered CM ratio of every machine (grey: ok; coloured: warning or fault)", fontsize=10)
    fig.tight_layout()
    out = _png(fig)
    plt.close(fig)
    return out
