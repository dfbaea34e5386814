"""Training the gray-box model and exporting it as one ONNX graph (needs ``cmcan[train]``).

Two fits, both convex with one solution, so the same data give the same model on any machine:
the physics law by non-negative least squares (:mod:`cmcan.model.physics`), then the correction of
its residual by ridge regression (:mod:`cmcan.model.correction`), on steady healthy points only.
:class:`TrainedModel` is the float64 Python reference of what the exported graph computes.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan import __version__
from cmcan.model import correction, digest, physics
from cmcan.model.metadata import FORMAT, OUTPUT_PHYSICS, OUTPUT_PRED, OUTPUT_WHITEBOX, QUANTITY_UNITS, ModelMeta
from cmcan.model.physics import Quantity
from cmcan.oil import VG46, Oil
from cmcan.roles import MODEL_INPUTS, MODEL_UNITS

MIN_POINTS = 50


def _require_train_extra() -> None:
    try:
        import onnx  # noqa: F401
        import scipy  # noqa: F401
    except ImportError as exc:
        raise ImportError(
            f"training needs the 'train' extra (pip install 'cmcan[train]'): {exc.name} is missing"
        ) from None


@dataclass(frozen=True)
class TrainedModel:
    quantity: Quantity
    oil: Oil
    coef: NDArray[np.float64]  # physics coefficients, in the order of physics.TERMS, all >= 0
    correction: correction.Correction
    eta_vol: float  # the plain white-box law's efficiency, for comparison
    envelope: dict[str, list[float]]
    width: float = correction.WIDTH
    fade_span: float = correction.FADE_SPAN
    doubts: tuple[str, ...] = ()  # what looks wrong in the fit (physics.prior_doubts), for the user

    def physics(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return physics.flow_lpm(x, self.coef, self.oil) / self.quantity.lpm_per_unit

    def whitebox(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.eta_vol * physics.ideal_flow_lpm(x) / self.quantity.lpm_per_unit

    def predict(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Python (float64) reference of what the ONNX graph computes."""
        flow = physics.flow_lpm(x, self.coef, self.oil) + self.correction(x)
        return flow / self.quantity.lpm_per_unit


def fingerprint(x: NDArray[np.float64], y: NDArray[np.float64]) -> str:
    h = hashlib.sha256()
    h.update(np.round(np.ascontiguousarray(x, dtype=float), 6).tobytes())
    h.update(np.round(np.ascontiguousarray(y, dtype=float), 6).tobytes())
    return h.hexdigest()


def fit(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    motor_disp_cc: float | None,
    quantity: str = "motor_speed_rpm",
    oil: Oil = VG46,
) -> TrainedModel:
    """Fit physics and correction on steady healthy points ``x`` (n, 4) with the measured quantity ``y``."""
    _require_train_extra()
    if quantity not in QUANTITY_UNITS:
        raise ValueError(f"output quantity {quantity!r} is not one of {', '.join(QUANTITY_UNITS)}")
    if len(x) < MIN_POINTS:
        raise ValueError(f"only {len(x)} steady operating points to train on; need at least {MIN_POINTS}")
    x = np.ascontiguousarray(x, dtype=np.float64)
    q = Quantity(quantity, motor_disp_cc if quantity == "motor_speed_rpm" else None)
    flow = np.asarray(y, dtype=np.float64) * q.lpm_per_unit
    _, _, active = correction.envelope_box(x)
    if not active.any():
        raise ValueError("the training points do not vary in any input: record a run over the machine's duty")
    if not np.ptp(flow) > 1e-9 * float(np.max(np.abs(flow))):  # also all zero
        raise ValueError(
            f"the measured {quantity} is {float(y[0]):g} at every training point while the inputs vary: "
            "a stuck sensor or a constant column, nothing to learn the drive from"
        )
    try:
        coef = physics.fit_coefficients(x, flow, oil)
    except RuntimeError as exc:  # scipy's NNLS gives up only on degenerate data
        raise ValueError(f"the physics fit did not converge: {exc}") from None
    corr = correction.fit(x, flow - physics.flow_lpm(x, coef, oil))
    envelope = {name: [float(x[:, i].min()), float(x[:, i].max())] for i, name in enumerate(MODEL_INPUTS)}
    doubts = tuple(physics.prior_doubts(x, flow, coef, oil))
    return TrainedModel(q, oil, coef, corr, physics.fit_eta_vol(x, flow), envelope, doubts=doubts)


def to_onnx(model: TrainedModel, residual_stats: dict[str, Any], training: dict[str, Any]) -> bytes:
    """One ONNX graph for the model, its metadata attached, the graph checked, the file sealed with its digest."""
    _require_train_extra()
    import onnx

    from cmcan.model import graph

    onx = graph.build(model)
    q = model.quantity
    meta = ModelMeta(
        format=FORMAT,
        model_version=f"{__version__}+{training['fingerprint'][:12]}",
        inputs=[{"name": n, "unit": MODEL_UNITS[n], "index": i} for i, n in enumerate(MODEL_INPUTS)],
        quantity={"role": q.role, "unit": q.unit},
        outputs=[{"name": n, "unit": q.unit} for n in (OUTPUT_PRED, OUTPUT_PHYSICS, OUTPUT_WHITEBOX)],
        motor_disp_cc=q.motor_disp_cc,
        oil={"nu40_cst": model.oil.nu40_cst, "nu100_cst": model.oil.nu100_cst},
        physics={
            "coefficients": {t: float(c) for t, c in zip(physics.TERMS, model.coef, strict=True)},
            "eta_vol": model.eta_vol,
            "priors": {
                "ideal_flow": list(physics.IDEAL_FLOW_PRIOR),
                "leak_share": physics.LEAK_SHARE,
                "bulk_modulus_bar": physics.BULK_MODULUS_BAR,
            },
        },
        correction={
            "basis": f"{len(model.correction.centers)} Gaussian RBFs on a {len(correction.LEVELS)}-level grid",
            "ridge": correction.RIDGE,
            "bound_lpm": model.correction.bound_lpm,
            "fade_span": model.fade_span,
        },
        envelope=model.envelope,
        residual_stats=residual_stats,
        training=training,
    )
    for k, v in meta.to_props().items():
        onx.metadata_props.append(onnx.StringStringEntryProto(key=k, value=v))
    onx.producer_name = "cmcan"
    onx.producer_version = __version__
    onnx.checker.check_model(onx, full_check=True)
    return digest.seal(onx.SerializeToString())


def residual_figures(model: TrainedModel, x: NDArray[np.float64], y: NDArray[np.float64], name: str) -> dict[str, Any]:
    pred = model.predict(x)
    ratio = y / pred * 100.0
    unit = model.quantity.unit
    return {
        "set": name,
        "points": len(y),
        "unit": unit,
        "rmse": float(np.sqrt(np.mean((pred - y) ** 2))),
        "mean": float(np.mean(y - pred)),
        "ratio_p1_pct": float(np.percentile(ratio, 1)),
        "ratio_p99_pct": float(np.percentile(ratio, 99)),
    }


def train_on_points(
    op: Any,
    t_trn_h: float,
    motor_disp_cc: float | None,
    source: str,
    t_start_h: float = 0.0,
    extra_training_info: dict[str, Any] | None = None,
    quantity: str | None = None,
    oil: Oil = VG46,
    select: NDArray[np.bool_] | None = None,
) -> tuple[bytes, TrainedModel, dict[str, Any]]:
    """The protocol's training step on operating points: fit on D_trn = steady points in
    [t_start_h, t_trn_h), residual statistics on D_tst = steady points after t_trn_h; both only
    among the points ``select`` keeps (``--where``). ``quantity`` defaults to the points' own."""
    quantity = quantity or op.quantity
    hours = op.hours
    chosen = np.ones(len(hours), dtype=bool) if select is None else select
    trn = op.steady & chosen & (hours >= t_start_h) & (hours < t_trn_h)
    tst = op.steady & chosen & (hours >= t_trn_h)
    if trn.sum() < MIN_POINTS:
        span = "" if math.isinf(t_trn_h) else f" before t_trn = {t_trn_h} h"
        raise ValueError(
            f"{source}: only {int(trn.sum())} steady points{span}; need at least {MIN_POINTS}: "
            "train on a longer stretch of healthy data, or see which gate refused the points"
        )
    y = op.measured
    model = fit(op.x[trn], y[trn], motor_disp_cc, quantity, oil)
    check = tst if tst.sum() >= 10 else trn
    stats = residual_figures(model, op.x[check], y[check], "D_tst" if check is tst else "D_trn")
    training = {
        "fingerprint": fingerprint(op.x[trn], y[trn]),
        "source": source,
        "t_start_h": t_start_h,
        "t_trn_h": None if math.isinf(t_trn_h) else t_trn_h,
        "points_trn": int(trn.sum()),
        "points_tst": int(tst.sum()),
        **(extra_training_info or {}),
    }
    return to_onnx(model, stats, training), model, stats
