"""Scoring operating points with a model: the ratio of every point the gates pass, none dropped.

The same verdicts and arithmetic as the monitor's tick (:mod:`cmcan.monitor.core`), without the
filter and the warning machine: a point that passes the gates gets a prediction, a raw ratio and a
leakage estimate, and is ``evaluated`` inside the training envelope or ``extrapolated`` outside it;
any other point is ``gated`` with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cmcan.model.evaluate import auc_lower
from cmcan.model.features import OperatingPoints
from cmcan.monitor.gating import EVALUATED, Gate, GateLimits, prediction_ok


class Predictor(Protocol):
    def predict(self, x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...


@dataclass(frozen=True)
class Scores:
    gate: NDArray[np.int64]  # the verdict per point (MODEL_ERROR where the model gave no plausible prediction)
    ratio_pct: NDArray[np.float64]  # NaN where not evaluated
    predicted: NDArray[np.float64]
    extra_leak_lpm: NDArray[np.float64]

    @property
    def rated(self) -> NDArray[np.bool_]:
        return np.isin(self.gate, [int(g) for g in EVALUATED])

    @property
    def extrapolated(self) -> NDArray[np.bool_]:
        return self.gate == Gate.EXTRAPOLATED

    def status(self) -> list[str]:
        """evaluated, extrapolated or gated:<reason> per point."""
        names = {int(g): f"gated:{g.name.lower()}" for g in Gate}
        names[int(Gate.EVALUATING)] = "evaluated"
        names[int(Gate.EXTRAPOLATED)] = "extrapolated"
        return [names[int(g)] for g in self.gate]


def score(model: Predictor, op: OperatingPoints, lpm_per_unit: float, limits: GateLimits | None = None) -> Scores:
    """Predictions for every point the gates pass (``op`` gated with the model's envelope); a point
    the model gives no plausible prediction for is ``MODEL_ERROR``, as in the monitor (the output's
    plausible range from ``limits``; without them, any positive finite prediction passes)."""
    n = len(op)
    codes = op.gate.copy()
    ratio = np.full(n, np.nan)
    pred_all = np.full(n, np.nan)
    leak = np.full(n, np.nan)
    idx = np.flatnonzero(np.isin(codes, [int(g) for g in EVALUATED]))
    if idx.size:
        pred, _ = model.predict(op.x[idx])
        pred = np.asarray(pred, dtype=np.float64)
        ok = prediction_ok(pred, limits) if limits is not None else np.isfinite(pred) & (pred > 0.0)
        codes[idx[~ok]] = Gate.MODEL_ERROR
        good, p = idx[ok], pred[ok]
        meas = op.measured[good]
        pred_all[good] = p
        ratio[good] = meas / p * 100.0
        leak[good] = (p - meas) * lpm_per_unit
    return Scores(codes, ratio, pred_all, leak)


def _ratio_figures(r: NDArray[np.float64], low_pct: float, high_pct: float) -> dict[str, Any]:
    if r.size == 0:
        return {"points": 0}
    return {
        "points": int(r.size),
        "ratio_mean_pct": float(np.mean(r)),
        "ratio_p1_pct": float(np.percentile(r, 1)),
        "ratio_p50_pct": float(np.percentile(r, 50)),
        "ratio_p99_pct": float(np.percentile(r, 99)),
        "below_low_pct": float(np.mean(r < low_pct) * 100.0),
        "above_high_pct": float(np.mean(r > high_pct) * 100.0),
    }


def summary(
    s: Scores,
    low_pct: float,
    high_pct: float,
    labels: NDArray[np.float64] | None = None,
    healthy_label: float | None = None,
) -> dict[str, Any]:
    """Counts per status, the ratio's spread and the share of points beyond each threshold; with a
    label column, the same per label value and the AUC of each against the healthy label (how well
    a low ratio separates that condition from healthy points; 1 is perfect, 0.5 chance)."""
    status = s.status()
    counts: dict[str, Any] = {"evaluated": status.count("evaluated"), "extrapolated": status.count("extrapolated")}
    gated = {k.split(":", 1)[1]: status.count(k) for k in sorted(set(status)) if k.startswith("gated:")}
    out: dict[str, Any] = {
        "points": len(status),
        "status": {**counts, "gated": gated},
        "without_ratio": int(len(status) - s.rated.sum()),
        "thresholds_pct": [low_pct, high_pct],
        "ratio": _ratio_figures(s.ratio_pct[s.rated], low_pct, high_pct),
    }
    if labels is not None:
        by: dict[str, Any] = {}
        healthy = s.ratio_pct[s.rated & (labels == healthy_label)]
        for v in np.unique(labels[np.isfinite(labels)]):
            m = labels == v
            f = _ratio_figures(s.ratio_pct[s.rated & m], low_pct, high_pct)
            f["without_ratio"] = int(np.sum(m & ~s.rated))
            if v != healthy_label:  # None: no rated point on one side, nothing to separate
                auc = auc_lower(healthy, s.ratio_pct[s.rated & m])
                f["auc_vs_healthy"] = auc if np.isfinite(auc) else None
            by[f"{v:g}"] = f
        out["labels"] = by
    return out
