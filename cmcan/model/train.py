"""Training the gray-box model and exporting it as one ONNX graph (needs ``cmcan[train]``).

The network learns the residual between measured motor speed and the fitted white-box law, on steady
healthy points only; scikit-learn fits it, skl2onnx converts scaler and network, and the white-box
nodes and the output scaling are added around them, so one graph maps the four inputs to the predicted
motor speed and to the white-box speed alone.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan import __version__
from cmcan.model.metadata import FORMAT, INPUT_NAME, OUTPUT_PRED, OUTPUT_WHITEBOX, ModelMeta
from cmcan.model.whitebox import fit_eta_vol, ideal_motor_speed_rpm, whitebox_rpm
from cmcan.signals import MODEL_INPUTS, MODEL_UNITS

HIDDEN = (24, 24)


def _require_train_extra() -> None:
    try:
        import onnx  # noqa: F401
        import skl2onnx  # noqa: F401
        import sklearn  # noqa: F401
    except ImportError as exc:
        raise ImportError(
            f"training needs the 'train' extra (pip install 'cmcan[train]'): {exc.name} is missing"
        ) from None


@dataclass
class TrainedModel:
    pipeline: Any  # sklearn Pipeline(StandardScaler, MLPRegressor) predicting residual / residual_scale
    eta_vol: float
    motor_disp_cc: float
    residual_scale: float
    envelope: dict[str, list[float]]

    def whitebox(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return whitebox_rpm(x, self.motor_disp_cc, self.eta_vol)

    def predict(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Python (float64) reference of what the ONNX graph computes."""
        return self.whitebox(x) + self.pipeline.predict(x) * self.residual_scale


def fingerprint(x: NDArray[np.float64], y: NDArray[np.float64]) -> str:
    h = hashlib.sha256()
    h.update(np.round(np.ascontiguousarray(x, dtype=float), 6).tobytes())
    h.update(np.round(np.ascontiguousarray(y, dtype=float), 6).tobytes())
    return h.hexdigest()


def fit(
    x: NDArray[np.float64],
    y_rpm: NDArray[np.float64],
    motor_disp_cc: float,
    seed: int = 0,
    hidden: tuple[int, ...] = HIDDEN,
) -> TrainedModel:
    """Fit the white-box efficiency, then the network on the residual. ``x``: steady healthy points."""
    _require_train_extra()
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    if len(x) < 50:
        raise ValueError(f"only {len(x)} steady operating points to train on; need at least 50")
    eta = fit_eta_vol(ideal_motor_speed_rpm(x[:, 0], x[:, 1], motor_disp_cc), y_rpm)
    residual = y_rpm - whitebox_rpm(x, motor_disp_cc, eta)
    scale = float(np.std(residual)) or 1.0
    net = MLPRegressor(
        hidden_layer_sizes=hidden,
        activation="tanh",
        solver="lbfgs",
        max_iter=3000,
        tol=1e-9,
        alpha=1e-5,
        random_state=seed,
    )
    pipe = make_pipeline(StandardScaler(), net)
    pipe.fit(x, residual / scale)
    envelope = {name: [float(x[:, i].min()), float(x[:, i].max())] for i, name in enumerate(MODEL_INPUTS)}
    return TrainedModel(pipe, eta, motor_disp_cc, scale, envelope)


def to_onnx(model: TrainedModel, residual_stats: dict[str, float], training: dict[str, Any]) -> bytes:
    """One ONNX graph: scaling + network (skl2onnx) with the white-box law and output scaling around it."""
    _require_train_extra()
    import onnx
    from onnx import TensorProto, helper, numpy_helper
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    n_in = len(MODEL_INPUTS)
    onx = convert_sklearn(
        model.pipeline,
        initial_types=[(INPUT_NAME, FloatTensorType([None, n_in]))],
        target_opset={"": 17, "ai.onnx.ml": 3},
    )
    g = onx.graph
    nn_out = g.output[0].name

    def const(name: str, value: Any, dtype: Any = np.float32) -> None:
        g.initializer.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))

    const("wb_gain", [model.eta_vol / model.motor_disp_cc])
    const("res_scale", [model.residual_scale])
    for name, val in (("s0", [0]), ("e1", [1]), ("s1", [1]), ("e2", [2]), ("ax1", [1])):
        const(name, val, np.int64)
    g.node.extend(
        [
            helper.make_node("Slice", [INPUT_NAME, "s0", "e1", "ax1"], ["n_pump"], name="pump_speed"),
            helper.make_node("Slice", [INPUT_NAME, "s1", "e2", "ax1"], ["v_pump_signed"], name="pump_disp"),
            helper.make_node("Abs", ["n_pump"], ["n_pump_abs"], name="abs_speed"),
            helper.make_node("Abs", ["v_pump_signed"], ["v_pump"], name="abs_disp"),
            helper.make_node("Mul", ["n_pump_abs", "v_pump"], ["ideal_flow"], name="pump_flow"),
            helper.make_node("Mul", ["ideal_flow", "wb_gain"], [OUTPUT_WHITEBOX], name="whitebox"),
            helper.make_node("Reshape", [nn_out, "nn_shape"], ["nn_col"], name="nn_column"),
            helper.make_node("Mul", ["nn_col", "res_scale"], ["correction"], name="correction_rpm"),
            helper.make_node("Add", [OUTPUT_WHITEBOX, "correction"], [OUTPUT_PRED], name="graybox"),
        ]
    )
    const("nn_shape", [-1, 1], np.int64)
    del g.output[:]
    g.output.extend(
        [
            helper.make_tensor_value_info(OUTPUT_PRED, TensorProto.FLOAT, [None, 1]),
            helper.make_tensor_value_info(OUTPUT_WHITEBOX, TensorProto.FLOAT, [None, 1]),
        ]
    )
    g.name = "cmcan_graybox"
    meta = ModelMeta(
        format=FORMAT,
        model_version=f"{__version__}+{training['fingerprint'][:12]}",
        inputs=[{"name": n, "unit": MODEL_UNITS[n], "index": i} for i, n in enumerate(MODEL_INPUTS)],
        outputs=[{"name": OUTPUT_PRED, "unit": "rpm"}, {"name": OUTPUT_WHITEBOX, "unit": "rpm"}],
        motor_disp_cc=model.motor_disp_cc,
        eta_vol=model.eta_vol,
        envelope=model.envelope,
        residual_stats=residual_stats,
        training=training,
    )
    del onx.metadata_props[:]
    for k, v in meta.to_props().items():
        onx.metadata_props.append(onnx.StringStringEntryProto(key=k, value=v))
    onx.producer_name = "cmcan"
    onx.producer_version = __version__
    onnx.checker.check_model(onx)
    return onx.SerializeToString()


def train_on_points(
    op: Any,
    t_trn_h: float,
    motor_disp_cc: float,
    source: str,
    seed: int = 0,
    t_start_h: float = 0.0,
    extra_training_info: dict[str, Any] | None = None,
) -> tuple[bytes, TrainedModel, dict[str, Any]]:
    """The protocol's training step on operating points: fit on D_trn = steady points in
    [t_start_h, t_trn_h), residual statistics on D_tst = steady points after t_trn_h."""
    hours = op.hours
    trn = op.steady & (hours >= t_start_h) & (hours < t_trn_h)
    tst = op.steady & (hours >= t_trn_h)
    if trn.sum() < 50:
        raise ValueError(
            f"{source}: only {int(trn.sum())} steady points before t_trn = {t_trn_h} h; "
            "train on a longer stretch of healthy data"
        )
    model = fit(op.x[trn], op.motor_speed_rpm[trn], motor_disp_cc, seed=seed)
    check = tst if tst.sum() >= 10 else trn
    y = op.motor_speed_rpm[check]
    pred = model.predict(op.x[check])
    ratio = y / pred * 100.0
    stats = {
        "set": "D_tst" if check is tst else "D_trn",
        "points": int(check.sum()),
        "rmse_rpm": float(np.sqrt(np.mean((pred - y) ** 2))),
        "mean_rpm": float(np.mean(y - pred)),
        "ratio_p1_pct": float(np.percentile(ratio, 1)),
        "ratio_p99_pct": float(np.percentile(ratio, 99)),
    }
    training = {
        "fingerprint": fingerprint(op.x[trn], op.motor_speed_rpm[trn]),
        "source": source,
        "t_start_h": t_start_h,
        "t_trn_h": t_trn_h,
        "points_trn": int(trn.sum()),
        "points_tst": int(tst.sum()),
        "eta_vol": model.eta_vol,
        "hidden": list(HIDDEN),
        "seed": seed,
        **(extra_training_info or {}),
    }
    return to_onnx(model, stats, training), model, stats
