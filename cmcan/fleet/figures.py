"""The fleet report's figures (matplotlib, PNG bytes): every machine's ratio over its life, one chart
per machine, drawn with the one ratio drawing of :mod:`cmcan.plots` (its axis shows a ratio at 43 % or
139 %, not clipped), and the overview's machine names in a column beside the plot, spread so that none
overlaps another, each joined to the end of its line. The service plan has a small chart per machine
with estimates, and each machine's chart a panel under its ratio: its hours to end of life (p50 in
its p10-p90 band) over its operating hours.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from cmcan.plots import LEVEL_COLORS, draw_ratio, png_bytes, pyplot, ratio_limits

PAD_FRACTION = 0.06  # of the sparkline's range, above


def spread(y: Sequence[float], min_gap: float, lo: float, hi: float) -> list[float]:
    """Label positions near ``y`` (any order) at least ``min_gap`` apart, inside [lo, hi] where they
    fit: sorted, pushed up where too close, then the whole column moved back down from ``hi``."""
    order = np.argsort(np.asarray(y, dtype=float), kind="stable")
    pos = np.asarray(y, dtype=float)[order].copy()
    for i in range(1, len(pos)):
        pos[i] = max(pos[i], pos[i - 1] + min_gap)
    over = pos[-1] - hi if len(pos) else 0.0
    if over > 0:
        pos[-1] -= over
        for i in range(len(pos) - 2, -1, -1):
            pos[i] = min(pos[i], pos[i + 1] - min_gap)
    if len(pos) and pos[0] < lo:  # more labels than fit: spread them evenly instead
        pos = np.linspace(lo, hi, len(pos))
    out = np.empty_like(pos)
    out[order] = pos
    return out.tolist()


def plot_overview(lines: list[tuple[str, Any, Any, str]], low_pct: float, high_pct: float) -> bytes:
    """Every machine's filtered CM ratio over its operating hours, coloured by its state (``lines``:
    machine, hours, ratio, state in ok/low/high/fault/misfit); every machine named at the right."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 4.0))
    ends = []
    drawn = []
    for name, h, r, state in sorted(lines, key=lambda x: x[3] != "ok"):  # machines needing a look on top
        h, r = np.asarray(h, dtype=float), np.asarray(r, dtype=float)
        ok = np.isfinite(r) & np.isfinite(h)
        if not ok.any():
            continue
        color = LEVEL_COLORS.get(state, "tab:gray") if state != "ok" else "0.6"
        ls = "--" if state == "misfit" else "-"
        ax.plot(h[ok], r[ok], ls, lw=1.0 if state == "ok" else 1.6, color=color, alpha=0.85)
        ends.append((name, float(h[ok][-1]), float(r[ok][-1]), color))
        drawn.append(r[ok])
    ax.axhline(low_pct, color="tab:orange", ls="--", lw=1)
    ax.axhline(high_pct, color="tab:purple", ls="--", lw=1)
    lo, hi = ratio_limits(drawn, low_pct, high_pct)
    ax.set_ylim(lo, hi)
    ax.set_xlabel("operating hours (h)")
    ax.set_ylabel("filtered CM ratio (%)")
    ax.set_title(
        "Fleet: filtered CM ratio of every machine (grey: ok; coloured: warning or fault; dashed: does not fit)",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0, 0.88, 1))
    if ends:
        # names in a column right of the axes, one text line apart at least (in data units)
        fig.canvas.draw()
        px_per_unit = ax.get_window_extent().height / (hi - lo)
        gap = 10.0 / px_per_unit  # 10 px between label centres (7 pt text at 90 dpi is about 9 px high)
        ys = spread([e[2] for e in ends], gap, lo + gap / 2, hi - gap / 2)
        x_right = ax.get_xlim()[1]
        for (name, x, y, color), y_label in zip(ends, ys, strict=True):
            ax.annotate(
                name,
                xy=(x, y),
                xytext=(1.02, (y_label - lo) / (hi - lo)),
                textcoords="axes fraction",
                fontsize=7,
                color=color,
                va="center",
                annotation_clip=False,
                arrowprops={"arrowstyle": "-", "color": color, "lw": 0.5, "alpha": 0.6, "shrinkA": 0, "shrinkB": 1},
            )
        ax.set_xlim(right=x_right)
    out = png_bytes(fig)
    plt.close(fig)
    return out


def plot_machine(
    hours: Any,
    raw_pct: Any,
    filt_pct: Any,
    low_pct: float,
    high_pct: float,
    events: list[tuple[float, str]],
    log_starts_h: list[float],
    title: str,
    learning: tuple[Any, float, float] | None = None,
    prognosis: tuple[Any, Any, Any, Any] | None = None,
) -> bytes:
    """One machine: the CM ratio over its operating hours (means of the timeline), the thresholds
    that judged each stretch (``learning``: a mask per point and the learning band, see
    :func:`cmcan.plots.draw_ratio`), each warning where it was raised and the start of each log; under
    it, where ``prognosis`` (hours, p10, p50, p90) has estimates, the hours to end of life over the
    same operating hours (p50 in its p10-p90 band); PNG bytes."""
    plt = pyplot()
    if prognosis is not None and len(prognosis[0]):
        fig, (ax, bx) = plt.subplots(2, 1, figsize=(10, 5.2), sharex=True, height_ratios=(3.4, 1.8))
    else:
        fig, ax = plt.subplots(figsize=(10, 3.4))
        bx = None
    draw_ratio(
        ax,
        hours,
        raw_pct,
        filt_pct,
        low_pct,
        high_pct,
        events=events,
        log_starts_h=log_starts_h,
        raw_label="raw (mean)",
        learning=learning,
    )
    ax.set_title(title, fontsize=10)
    if bx is not None:
        assert prognosis is not None
        draw_eol_band(bx, *prognosis, fit_x=False)  # under the ratio, on the machine's whole life
        bx.set_ylabel("to end of life (h)")
        bx.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)
        ax.set_xlabel("")
        bx.set_xlabel("operating hours (h, logged time of this machine)")
    else:
        ax.set_xlabel("operating hours (h, logged time of this machine)")
    fig.tight_layout()
    out = png_bytes(fig)
    plt.close(fig)
    return out


def draw_eol_band(ax: Any, hours: Any, p10_h: Any, p50_h: Any, p90_h: Any, fit_x: bool = True) -> float:
    """The hours to end of life over operating hours: the p50 as a line in its p10-p90 band. An
    infinite hour (the estimate never gets there) runs off the top, which the finite values set;
    returns that top. ``fit_x``: the x axis spans the estimates (a chart of its own)."""
    h, lo, mid, hi = (np.asarray(x, dtype=float) for x in (hours, p10_h, p50_h, p90_h))
    finite = np.concatenate([v[np.isfinite(v)] for v in (lo, mid, hi)])
    top_h = max(float(finite.max()) if finite.size else 1.0, 1.0) * (1 + 2 * PAD_FRACTION)
    lo, mid, hi = (np.minimum(v, top_h) for v in (lo, mid, hi))  # inf to the top edge
    ax.fill_between(h, lo, hi, color="tab:blue", alpha=0.25, lw=0, label="p10-p90")
    ax.plot(h, mid, "-", lw=1.0, color="tab:blue", label="p50")
    ax.set_ylim(0.0, top_h)
    if fit_x and len(h) > 1 and h[-1] > h[0]:
        ax.set_xlim(h[0], h[-1])
    return top_h


def plot_service_spark(hours: Any, p10_h: Any, p50_h: Any, p90_h: Any) -> bytes:
    """A small chart of one machine's operating hours to end of life over its operating hours: the
    p50 as a line in its p10-p90 band (no truth: in the field it is not known), with numbered axes
    (x: operating hours, y: hours to end of life)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(3.0, 1.25))
    draw_eol_band(ax, hours, p10_h, p50_h, p90_h)
    ax.tick_params(labelsize=6, length=2, pad=1)
    ax.locator_params(nbins=3)
    ax.set_xlabel("operating h", fontsize=6, labelpad=1)
    ax.set_ylabel("to EOL h", fontsize=6, labelpad=1)
    fig.subplots_adjust(0.2, 0.27, 0.97, 0.95)
    out = png_bytes(fig)
    plt.close(fig)
    return out
