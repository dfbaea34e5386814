"""Every plot cmcan draws (matplotlib, the ``plot`` extra), in one style: the CM ratio over operating
hours is drawn by :func:`draw_ratio` alone, for a replay (:func:`plot_ratio`) and for each machine of a
fleet report (:mod:`cmcan.fleet.figures` lays out the report's figures with it), on the axis of
:func:`ratio_limits`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cmcan.monitor.prognosis import IMMINENT, TREND
from cmcan.monitor.tick import LEVEL_NAMES
from cmcan.monitor.warnings import Level, Thresholds


def pyplot() -> Any:
    """matplotlib without a display (raises ImportError when the extra is missing)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


LEVEL_COLORS = {"low": "tab:orange", "high": "tab:purple", "fault": "tab:red", "ok": "tab:green", "misfit": "0.35"}


def ratio_limits(values: Any, low_pct: float, high_pct: float) -> tuple[float, float]:
    """A ratio axis that shows every finite ratio in ``values`` (an array, or a sequence of arrays: a
    failure falls to about 40 %) and the thresholds with room around them, within the span a CM frame
    carries (0-200 %)."""
    parts = [np.asarray(v, dtype=float).ravel() for v in (values if isinstance(values, list | tuple) else [values])]
    finite = np.concatenate([p[np.isfinite(p)] for p in parts]) if parts else np.empty(0)
    lo, hi = low_pct - 3.0, high_pct + 3.0
    if finite.size:
        lo = min(lo, float(finite.min()) - 2.0)
        hi = max(hi, float(finite.max()) + 2.0)
    return max(lo, 0.0), min(hi, 200.0)


def draw_ratio(
    ax: Any,
    hours: Any,
    raw_pct: Any,
    filt_pct: Any,
    low_pct: float,
    high_pct: float,
    *,
    levels: Any = None,
    events: Sequence[tuple[float, str]] = (),
    failures_h: Sequence[float] = (),
    log_starts_h: Sequence[float] = (),
    raw_label: str = "raw",
    learning: tuple[Any, float, float] | None = None,
) -> None:
    """The CM ratio over operating hours as every cmcan figure shows it (the paper's Figure 9): the
    raw ratios as grey dots, the filtered ratio as a line, marked by level where ``levels`` (one
    :class:`Level` per point) says a warning was active, the thresholds, a dotted line where each
    warning was raised (``events``: hour, level name), failures in red, the start of each log in light
    grey; NaN is a point not drawn; the axis from :func:`ratio_limits`. ``learning`` (a mask per
    point, its low and high thresholds) draws the thresholds that judged each stretch: the learning
    band where the on-board baseline was learning, the configured ones elsewhere."""
    h, raw, filt = (np.asarray(x, dtype=float) for x in (hours, raw_pct, filt_pct))
    for i, x in enumerate(log_starts_h):
        ax.axvline(x, color="0.85", lw=0.6, zorder=0, label="start of a log" if i == 0 else None)
    ok, okf = np.isfinite(raw), np.isfinite(filt)
    if ok.any():
        ax.plot(h[ok], raw[ok], ".", ms=1.5, alpha=0.35, color="tab:gray", label=raw_label)
    if okf.any():
        ax.plot(h[okf], filt[okf], "-", lw=1.2, color="tab:blue", label="filtered")
    if levels is not None and okf.any():
        lv = np.asarray(levels)[okf]
        for level in (Level.LOW, Level.HIGH, Level.FAULT):
            on = lv == int(level)
            if on.any():
                name = LEVEL_NAMES[level]
                ax.plot(h[okf][on], filt[okf][on], "o", ms=2, color=LEVEL_COLORS[name], label=f"warning {name}")
    if learning is not None and len(h) and np.asarray(learning[0], dtype=bool).any():
        on = np.asarray(learning[0], dtype=bool)
        for name, conf, learn in (("low", low_pct, learning[1]), ("high", high_pct, learning[2])):
            label = f"{name} threshold {conf:g} % ({learn:g} % while learning)"
            ax.step(h, np.where(on, learn, conf), where="mid", color=LEVEL_COLORS[name], ls="--", lw=1, label=label)
    else:
        ax.axhline(low_pct, color=LEVEL_COLORS["low"], ls="--", lw=1, label=f"low threshold {low_pct:g} %")
        ax.axhline(high_pct, color=LEVEL_COLORS["high"], ls="--", lw=1, label=f"high threshold {high_pct:g} %")
        learning = None
    seen: set[str] = set()
    for x, level in events:
        label = None if level in seen else f"{level} raised" if level != "fault" else "fault"
        ax.axvline(x, color=LEVEL_COLORS.get(level, "k"), lw=1.2, ls=":", label=label)
        seen.add(level)
    for i, x in enumerate(failures_h):
        ax.axvline(x, color="tab:red", lw=1, alpha=0.6, label="failure" if i == 0 else None)
    lo_pct, hi_pct = (
        (low_pct, high_pct) if learning is None else (min(low_pct, learning[1]), max(high_pct, learning[2]))
    )
    ax.set_ylim(*ratio_limits([raw[ok], filt[okf]], lo_pct, hi_pct))
    ax.set_xlabel("operating hours (h)")
    ax.set_ylabel("CM ratio (%)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, markerscale=3, frameon=False)


def plot_ratio(
    tl: Any,
    t0: float,
    low_pct: float,
    high_pct: float,
    path: str | Path,
    failures_h: list[float] | None = None,
    title: str = "CM ratio",
) -> None:
    """A replay's CM ratio over operating hours (:func:`draw_ratio`); ``tl`` is a
    :class:`cmcan.replay.TickColumns`."""
    plt = pyplot()
    hours = (tl.t_run_s - t0) / 3600.0  # operating hours: the wall clock's steps undone
    raw = np.where(tl.ratio_raw_pct > 0, tl.ratio_raw_pct, np.nan)  # 0: the tick was not evaluated
    filt = np.where(tl.filt_valid, tl.ratio_filt_pct, np.nan)
    fig, ax = plt.subplots(figsize=(11, 4.2))
    draw_ratio(ax, hours, raw, filt, low_pct, high_pct, levels=tl.level, failures_h=failures_h or ())
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@dataclass(frozen=True)
class LeadLabel:
    """A lead time drawn as an arrow from the first warning to the failure, its text beside it."""

    warning_h: float
    fail_h: float
    y: float  # the arrow's height: above the ok band for a low warning, below it for a high one
    text: str
    level: str  # low or high
    text_x: float  # where the text is anchored ...
    ha: str  # ... and how: it ends at the warning line, on the side away from the failure line


@dataclass(frozen=True)
class DemoFigure:
    """What the demo's figure shows, computed apart from drawing it (``demo_figure``)."""

    ylim: tuple[float, float]  # covers every ratio sent, the thresholds and the lead arrows
    band: tuple[float, float]  # the ok band between the thresholds, shaded
    failures: tuple[tuple[float, str], ...]  # (operating h, label above the plot)
    warnings: tuple[tuple[float, str], ...]  # (operating h of the first warning, level)
    leads: tuple[LeadLabel, ...]
    legend: tuple[str, ...]  # one entry per kind of line, in drawing order
    title: str
    learning: tuple[float, float] | None = None  # the on-board baseline's learning phase (operating h)
    # the panel below the ratio where the prognosis is configured: the estimate over each failing stretch
    prognosis: tuple[PrognosisStretch, ...] = ()
    prognosis_ylim: tuple[float, float] | None = None  # None: no CM_PROGNOSIS seen, no panel
    prognosis_legend: tuple[str, ...] = ()


# (operating h, p10, p50, p90 h to end of life) of one estimate drawn
BandPoint = tuple[float, float, float, float]


@dataclass(frozen=True)
class PrognosisStretch:
    """A failing stretch of the prognosis panel: from the first trend estimate or the first warning,
    whichever came first, to the failure. Its estimates in runs: an estimate of none (or a frame
    without finite hours) ends a run, and nothing is drawn there."""

    label: str  # component and kind of the failure
    start_h: float
    fail_h: float
    runs: tuple[tuple[BandPoint, ...], ...]

    @property
    def band_points(self) -> int:
        return sum(len(r) for r in self.runs)


_ESTIMATED = (TREND, IMMINENT)


def _estimated(x: Sequence[Any]) -> bool:
    """A decoded CM_PROGNOSIS (h, state, p10, p50, p90) that carries an estimate."""
    return x[1] in _ESTIMATED and all(math.isfinite(v) for v in x[2:5])


def prognosis_stretches(
    seen: Sequence[Sequence[Any]], failures: Sequence[dict[str, Any]]
) -> tuple[PrognosisStretch, ...]:
    """The failing stretches of ``seen`` (CM_PROGNOSIS as :func:`cmcan.demo.prognosis_at` decodes it,
    sorted by hour) before each failure: after the previous failure and the estimates still carried over
    from it (a replaced unit begins anew), from the first estimate or the first warning to the failure.
    A failure with neither has no stretch."""
    out = []
    previous_h = -math.inf
    for f in failures:
        fail_h = float(f["fail_h"])
        inside = [x for x in seen if previous_h < x[0] <= fail_h]
        if previous_h > -math.inf:  # the failed unit's estimate goes on until its replacement restarts it
            inside = inside[next((i for i, x in enumerate(inside) if not _estimated(x)), len(inside)) :]
        previous_h = fail_h
        first = next((float(x[0]) for x in inside if _estimated(x)), None)
        starts = [h for h in (first, f.get("first_warning_h")) if h is not None]
        if not starts:
            continue
        start_h = min(starts)
        runs: list[tuple[BandPoint, ...]] = []
        run: list[BandPoint] = []
        for x in inside:
            if _estimated(x):
                run.append((float(x[0]), float(x[2]), float(x[3]), float(x[4])))
            elif run:
                runs.append(tuple(run))
                run = []
        if run:
            runs.append(tuple(run))
        out.append(PrognosisStretch(f"{f['component']} {f['kind']}", start_h, fail_h, tuple(runs)))
    return tuple(out)


def prognosis_ylim(stretches: Sequence[PrognosisStretch]) -> tuple[float, float]:
    """Hours from 0 to above the longest true stretch and its band; a band far above the truth (an
    early estimate, or the frame's saturated 4000 h) is cut at twice it, the shape near the failure
    is what the panel is for."""
    truth_h = max((s.fail_h - s.start_h for s in stretches), default=0.0)
    p90_h = max((p[3] for s in stretches for r in s.runs for p in r), default=0.0)
    top_h = max(truth_h, min(p90_h, 2.0 * truth_h))
    return 0.0, (1.1 * top_h if top_h > 0 else 10.0)


def demo_figure(res: Any, thresholds: Thresholds, title: str) -> DemoFigure:
    """The demo's figure: the whole range of the ratio the bus carried (a wear failure falls to about
    40 %), the ok band, each failure and first warning, and each lead time as an arrow whose text sits
    on the side of the band the ratio is not on (a low warning's ratio is below the band, so its arrow
    goes above it) and left of the warning line, away from the failure line."""
    lo_t, hi_t = thresholds.low_pct, thresholds.high_pct
    y = np.asarray(res.ratio_pct, dtype=float) if len(res.ratio_pct) else np.array([100.0])
    above, below = hi_t + 4.0, lo_t - 4.0  # the lead arrows' heights
    lo = min(float(y.min()), below) - 3.0
    hi = max(float(y.max()), above) + 3.0
    failures, warnings, leads = [], [], []
    for f in res.failures:
        failures.append((float(f["fail_h"]), f"{f['component']} {f['kind']}\n{f['fail_h']:g} h"))
        if f["first_warning_h"] is None:
            continue
        level = f["level"]
        warnings.append((float(f["first_warning_h"]), level))
        leads.append(
            LeadLabel(
                float(f["first_warning_h"]),
                float(f["fail_h"]),
                above if level == "low" else below,
                f"lead {f['lead_h']:.0f} h",
                level,
                float(f["first_warning_h"]),
                "right",
            )
        )
    legend = [
        "filtered CM ratio (CM_RATIO frames)",
        f"ok band {lo_t:g}-{hi_t:g} % between the thresholds",
        f"low threshold {lo_t:g} % (wear, leakage)",
        f"high threshold {hi_t:g} % (misposition)",
        "scheduled failure (loss of function)",
    ]
    legend += [f"first {lv} warning (CM_WARNING)" for lv in ("low", "high") if any(w[1] == lv for w in warnings)]
    if leads:
        legend.append("lead time: first warning to failure")
    learning = getattr(res, "learning_h", None)
    if learning is not None:
        legend.append(f"learning its own baseline ({learning[1] - learning[0]:.0f} h, type model, wider margins)")
    seen = getattr(res, "prognosis", [])
    stretches = prognosis_stretches(seen, res.failures) if seen else ()
    return DemoFigure(
        (max(lo, 0.0), hi),
        (lo_t, hi_t),
        tuple(failures),
        tuple(warnings),
        tuple(leads),
        tuple(legend),
        title,
        learning,
        stretches,
        prognosis_ylim(stretches) if seen else None,
        _PROGNOSIS_LEGEND if seen else (),
    )


_PROGNOSIS_LEGEND = (
    "hours to end of life p50 (CM_PROGNOSIS)",
    "p10-p90",
    "true hours left (failure - hour)",
    "scheduled failure",
)


def plot_demo(res: Any, thresholds: Thresholds, path: str | Path, title: str) -> DemoFigure:
    """The demo's CM ratio as the bus carried it, thresholds, failures and lead times (the shape of the
    run-to-failure figure of the gray-box paper the scenario follows); returns what it drew."""
    plt = pyplot()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    spec = demo_figure(res, thresholds, title)
    if spec.prognosis_ylim is None:
        fig, ax = plt.subplots(figsize=(11, 5.2))
        bottom = ax
    else:  # the prognosis's panel below, on the same hours
        fig, (ax, bottom) = plt.subplots(2, 1, figsize=(11, 7.6), sharex=True, gridspec_kw={"height_ratios": (5, 2.4)})
    ax.axhspan(*spec.band, color="tab:green", alpha=0.12, lw=0, zorder=0)
    if spec.learning is not None:
        ax.axvspan(*spec.learning, color="0.6", alpha=0.25, lw=0, zorder=0)
    ax.axhline(spec.band[0], color="tab:orange", ls="--", lw=1)
    ax.axhline(spec.band[1], color="tab:purple", ls="--", lw=1)
    ax.plot(res.ratio_h, res.ratio_pct, ".", ms=1.5, color="tab:blue", zorder=3)
    for x, label in spec.failures:
        ax.axvline(x, color="tab:red", lw=1.2, zorder=2)
        ax.annotate(
            label,
            (x, 1.0),
            xycoords=("data", "axes fraction"),
            xytext=(0, 3),
            textcoords="offset points",
            color="tab:red",
            fontsize=8,
            ha="center",
            va="bottom",
        )
    for x, level in spec.warnings:
        ax.axvline(x, color=LEVEL_COLORS[level], lw=1.2, ls=":", zorder=2)
    for lead in spec.leads:
        ax.annotate(
            "",
            (lead.fail_h, lead.y),
            xytext=(lead.warning_h, lead.y),
            arrowprops={"arrowstyle": "->", "color": "0.25", "lw": 1},
        )
        ax.annotate(
            lead.text,
            (lead.text_x, lead.y),
            xytext=(-4 if lead.ha == "right" else 4, 0),
            textcoords="offset points",
            fontsize=8,
            ha=lead.ha,
            va="center",
            color="0.15",
        )
    ax.set_ylim(*spec.ylim)
    ax.set_xlim(left=min([0.0, *(res.ratio_h[:1] if len(res.ratio_h) else [])]))
    bottom.set_xlabel("operating hours (h)")
    ax.set_ylabel("CM ratio (%)")
    ax.set_title(spec.title, fontsize=10, pad=30)
    kinds = [
        Line2D([], [], ls="", marker=".", color="tab:blue"),
        Patch(color="tab:green", alpha=0.12),
        Line2D([], [], color="tab:orange", ls="--", lw=1),
        Line2D([], [], color="tab:purple", ls="--", lw=1),
        Line2D([], [], color="tab:red", lw=1.2),
    ]
    kinds += [
        Line2D([], [], color=LEVEL_COLORS[lv], ls=":", lw=1.2)
        for lv in ("low", "high")
        if any(w[1] == lv for w in spec.warnings)
    ]
    if spec.leads:
        kinds.append(Line2D([], [], color="0.25", lw=1, marker=">", ms=5))
    if spec.learning is not None:
        kinds.append(Patch(color="0.6", alpha=0.25))
    ax.legend(kinds, spec.legend, loc="lower left", fontsize=8, framealpha=0.9)
    if spec.prognosis_ylim is not None:
        _draw_prognosis(bottom, spec)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return spec


def _draw_prognosis(ax: Any, spec: DemoFigure) -> None:
    """The estimate's p50 and its p10-p90 band over each failing stretch, the truth dashed."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    for x, _ in spec.failures:
        ax.axvline(x, color="tab:red", lw=1.2, zorder=2)
    for s in spec.prognosis:
        ax.plot([s.start_h, s.fail_h], [s.fail_h - s.start_h, 0.0], "--", color="0.1", lw=1.1, zorder=5)
        for run in s.runs:
            h, p10, p50, p90 = np.asarray(run, dtype=float).T
            ax.fill_between(h, p10, p90, color="tab:cyan", alpha=0.3, lw=0, zorder=1)
            ax.plot(h, p50, "-", color="tab:blue", lw=1.2, zorder=4)
        if not s.runs:  # the truth alone would read as an estimate on the mark
            ax.annotate(
                "no estimate",
                (s.start_h, s.fail_h - s.start_h),
                xytext=(-4, 0),
                textcoords="offset points",
                fontsize=8,
                ha="right",
                va="center",
                color="0.3",
            )
    assert spec.prognosis_ylim is not None  # drawn only where CM_PROGNOSIS was seen
    ax.set_ylim(*spec.prognosis_ylim)
    ax.set_ylabel("hours to end of life (h)")
    kinds = [
        Line2D([], [], color="tab:blue", lw=1.2),
        Patch(color="tab:cyan", alpha=0.3),
        Line2D([], [], color="0.1", ls="--", lw=1.1),
        Line2D([], [], color="tab:red", lw=1.2),
    ]
    ax.legend(kinds, spec.prognosis_legend, loc="upper left", fontsize=8, framealpha=0.9)


@dataclass(frozen=True)
class ResidualSeries:
    """One kind of point in a residual panel: a set's gray-box or white-box residuals."""

    label: str
    hours: Any
    values: Any  # predicted - measured
    color: str
    whitebox: bool


@dataclass(frozen=True)
class ResidualPanel:
    title: str
    mark_h: float | None  # the end of training or the damage onset
    mark_label: str
    series: tuple[ResidualSeries, ...]
    unit: str


# What each set of the protocol is, in words: a point after the end of training is never "training".
SET_ROLES = {
    "D_trn": ("training", "tab:blue", "lightsteelblue"),
    "D_tst": ("after the end of training", "tab:green", "darkseagreen"),
    "D_val_healthy": ("before the damage onset", "tab:green", "darkseagreen"),
    "D_val_damaged": ("after the damage onset", "tab:red", "lightsalmon"),
}


def residual_panels(sets: list[Any], report: dict[str, Any]) -> list[ResidualPanel]:
    """The panels of ``cmcan evaluate --plot``: the training run (D_trn, D_tst), the validation run
    (before and after the damage onset) and each further healthy run, every set's gray-box and
    white-box residuals labelled and coloured by that set."""
    by = {s.name: s for s in sets}
    groups = [("training run", ["D_trn", "D_tst"], report.get("t_trn_h"), "end of training")]
    if "D_val_healthy" in by:
        groups.append(("validation run", ["D_val_healthy", "D_val_damaged"], report.get("t_dam_h"), "damage onset"))
    for name in (s.name for s in sets if s.name not in SET_ROLES):
        groups.append((f"healthy run {name}", [name], None, ""))
    panels = []
    for title, names, mark, mark_label in groups:
        series = []
        for n in names:
            s = by[n]
            role, color, light = SET_ROLES.get(n, ("healthy", "tab:gray", "0.75"))
            series.append(ResidualSeries(f"{n}, {role}: gray-box", s.hours, s.pred - s.measured, color, False))
            series.append(ResidualSeries(f"{n}, {role}: white-box", s.hours, s.whitebox - s.measured, light, True))
        panels.append(ResidualPanel(title, mark, mark_label, tuple(series), by[names[0]].unit))
    return panels


def plot_residuals(sets: list[Any], report: dict[str, Any], path: str | Path) -> list[ResidualPanel]:
    """Predicted minus actual output (motor speed or flow) over time, training end and damage onset
    marked (the protocol's figures): one panel for the training run, one for the validation run, one
    for each further healthy run. Returns what it drew."""
    plt = pyplot()

    panels = residual_panels(sets, report)
    fig, axes = plt.subplots(len(panels), 1, figsize=(13, 3.4 * len(panels)), squeeze=False)
    for ax, panel in zip(axes[:, 0], panels, strict=True):
        for sr in sorted(panel.series, key=lambda x: not x.whitebox):  # white-box behind
            ax.plot(
                sr.hours,
                sr.values,
                ".",
                ms=0.8 if sr.whitebox else 1.5,
                alpha=0.35 if sr.whitebox else 1.0,
                color=sr.color,
                label=sr.label,
            )
        if panel.mark_h is not None:
            ax.axvline(panel.mark_h, color="k", ls="--", lw=1)
            ax.annotate(
                f" {panel.mark_label} ({panel.mark_h:g} h)",
                (panel.mark_h, 1.0),
                xycoords=("data", "axes fraction"),
                xytext=(2, -2),
                textcoords="offset points",
                va="top",
                fontsize=8,
            )
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title(panel.title)
        ax.set_xlabel("time (h)")
        ax.set_ylabel(f"predicted - measured ({panel.unit})")
        legend = ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, markerscale=6, frameon=False)
        for h in legend.legend_handles:  # the white-box points are faint in the panel, not in the legend
            h.set_alpha(1.0)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return panels


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
    plt = pyplot()
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
    plt = pyplot()
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
    ax.axhline(low_pct, color=LEVEL_COLORS["low"], ls="--", lw=1, label=f"low {low_pct:g} %")
    ax.axhline(high_pct, color=LEVEL_COLORS["high"], ls="--", lw=1, label=f"high {high_pct:g} %")
    ax.set_ylim(*ratio_limits(ratio_pct, low_pct, high_pct))
    ax.set_xlabel(x_label)
    ax.set_ylabel("CM ratio (%)")
    ax.set_title(title + ("  (hollow: outside the training envelope)" if extrapolated.any() else ""), fontsize=10)
    ax.legend(loc="lower left", fontsize=8, markerscale=1.5)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def png_bytes(fig: Any, dpi: int = 90) -> bytes:
    """A figure as PNG bytes (the fleet report embeds them)."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()
