"""The paper's protocol: D_trn (start of a healthy run), D_tst (its rest), D_val (another run that
degrades after t_dam), plus any further healthy runs; the figures that say whether a model is good."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cmcan.model.features import OperatingPoints
from cmcan.roles import UNITS


class Predictor(Protocol):
    def predict(self, x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...


@dataclass(frozen=True)
class SetResult:
    """One set's points: the output quantity measured and predicted, in ``unit`` (rpm or l/min)."""

    name: str
    hours: NDArray[np.float64]
    measured: NDArray[np.float64]
    pred: NDArray[np.float64]
    whitebox: NDArray[np.float64]
    unit: str = "rpm"

    @property
    def ratio(self) -> NDArray[np.float64]:
        return self.measured / self.pred

    def figures(self) -> dict[str, Any]:
        if len(self.hours) == 0:
            return {"points": 0}
        r = self.ratio * 100.0
        return {
            "points": len(self.hours),
            "unit": self.unit,
            "rmse_graybox": _rmse(self.pred - self.measured),
            "rmse_whitebox": _rmse(self.whitebox - self.measured),
            "ratio_mean_pct": float(np.mean(r)),
            "ratio_p1_pct": float(np.percentile(r, 1)),
            "ratio_p99_pct": float(np.percentile(r, 99)),
            "ratio_halfwidth_pct": float((np.percentile(r, 99) - np.percentile(r, 1)) / 2),
        }


# Where the CM ratio of healthy points lies (1st..99th percentile) with a model that fits them: the
# warning thresholds (98, 102 %) sit outside it.
HEALTHY_RATIO_BAND_PCT = (99.0, 101.0)


def _rmse(e: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


def run_set(model: Predictor, op: OperatingPoints, mask: NDArray[np.bool_], name: str) -> SetResult:
    sub = op.select(mask & op.steady)
    unit = UNITS[op.quantity]
    if len(sub.t_s) == 0:
        return SetResult(name, np.empty(0), np.empty(0), np.empty(0), np.empty(0), unit)
    pred, wb = model.predict(sub.x)
    return SetResult(name, sub.hours, sub.measured, pred, wb, unit)


def protocol(
    model: Predictor,
    train_op: OperatingPoints,
    t_trn_h: float,
    val_op: OperatingPoints | None = None,
    t_dam_h: float | None = None,
    healthy: dict[str, OperatingPoints] | None = None,
) -> tuple[dict[str, Any], list[SetResult]]:
    """Figures of every set, and the sets themselves for plotting."""
    sets = [
        run_set(model, train_op, train_op.hours < t_trn_h, "D_trn"),
        run_set(model, train_op, train_op.hours >= t_trn_h, "D_tst"),
    ]
    report: dict[str, Any] = {"t_trn_h": t_trn_h}
    for name, op in (healthy or {}).items():
        sets.append(run_set(model, op, np.ones(len(op.t_s), dtype=bool), name))
    if val_op is not None:
        if t_dam_h is None:
            raise ValueError("D_val needs its damage onset t_dam")
        report["t_dam_h"] = t_dam_h
        sets.append(run_set(model, val_op, val_op.hours < t_dam_h, "D_val_healthy"))
        sets.append(run_set(model, val_op, val_op.hours >= t_dam_h, "D_val_damaged"))
    report["sets"] = {s.name: s.figures() for s in sets}
    by = {s.name: s for s in sets}
    checks: dict[str, Any] = {}
    for s in sets:
        f = report["sets"][s.name]
        if s.name in ("D_trn", "D_val_damaged") or f["points"] == 0:
            continue
        checks[f"{s.name}: graybox_rmse <= whitebox_rmse / 3"] = bool(f["rmse_graybox"] <= f["rmse_whitebox"] / 3)
        lo, hi = HEALTHY_RATIO_BAND_PCT
        checks[f"{s.name}: ratio p1..p99 within {lo:g}..{hi:g} %"] = bool(
            f["ratio_p1_pct"] >= lo and f["ratio_p99_pct"] <= hi
        )
    if val_op is not None and by["D_val_healthy"].hours.size and by["D_val_damaged"].hours.size:
        h, d = report["sets"]["D_val_healthy"], report["sets"]["D_val_damaged"]
        shift = d["ratio_mean_pct"] - h["ratio_mean_pct"]
        report["damage_shift_pct"] = shift
        report["damage_shift_in_halfwidths"] = abs(shift) / h["ratio_halfwidth_pct"]
        checks["D_val: |shift after t_dam| >= 3 healthy p1..p99 half-widths"] = bool(
            report["damage_shift_in_halfwidths"] >= 3.0
        )
    if not checks:  # every set to check is empty (e.g. t_trn_h at or past the run's end): nothing passed
        checks["a set with steady points to check (D_tst, D_val_healthy or a healthy run)"] = False
    report["checks"] = checks
    report["passed"] = all(checks.values())
    return report, sets


def format_report(report: dict[str, Any]) -> str:
    units = {f["unit"] for f in report["sets"].values() if f["points"]}
    unit = f" ({units.pop()})" if len(units) == 1 else ""
    lines = [f"{'set':<16}{'points':>8}{'RMSE gray':>11}{'RMSE white':>12}{'ratio mean':>12}{'p1':>9}{'p99':>9}{unit}"]
    for name, f in report["sets"].items():
        if f["points"] == 0:
            lines.append(f"{name:<16}{0:>8}  (no steady points)")
            continue
        lines.append(
            f"{name:<16}{f['points']:>8}{f['rmse_graybox']:>10.4g} {f['rmse_whitebox']:>11.4g} "
            f"{f['ratio_mean_pct']:>11.3f}%{f['ratio_p1_pct']:>8.3f}%{f['ratio_p99_pct']:>8.3f}%"
        )
    if "damage_shift_pct" in report:
        lines.append(
            f"damage shift after t_dam: {report['damage_shift_pct']:+.3f} %-points "
            f"= {report['damage_shift_in_halfwidths']:.1f} healthy half-widths"
        )
    for name, ok in report["checks"].items():
        lines.append(f"  [{'ok' if ok else 'FAIL'}] {name}")
    return "\n".join(lines)


def auc_lower(healthy: NDArray[np.float64], faulty: NDArray[np.float64]) -> float:
    """Area under the ROC curve of "a lower value means a fault": the probability that a faulty
    point's value is below a healthy one's, ties counting one half (Mann-Whitney U / (n_h n_f))."""
    h = np.sort(np.asarray(healthy, dtype=np.float64))
    f = np.asarray(faulty, dtype=np.float64)
    if h.size == 0 or f.size == 0:
        return float("nan")
    below = np.searchsorted(h, f, side="left")  # healthy values below each faulty one
    not_above = np.searchsorted(h, f, side="right")
    greater = h.size - not_above  # healthy values above each faulty one
    ties = not_above - below
    return float((np.sum(greater) + 0.5 * np.sum(ties)) / (h.size * f.size))
