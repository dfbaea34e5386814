"""The fitted gray box as one ONNX graph (float64, opset 17), built node by node with onnx.helper.

Input ``x`` [N, 4] (pump speed, pump displacement, dp, oil temperature); outputs ``predicted``,
``physics`` and ``whitebox`` [N, 1] in the quantity's unit. It computes what the Python reference in
:mod:`cmcan.model.train` does, in float64, rearranged to few nodes (onnxruntime costs about 0.35 us
per node on a single-sample call): constant factors are folded into the fitted weights, affine maps
are single Gemm nodes, and the correction's fade enters the exponent of its basis functions.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from cmcan.model.metadata import INPUT_NAME, OUTPUT_PHYSICS, OUTPUT_PRED, OUTPUT_WHITEBOX

OPSET = 17
LANES = 16  # doubles per row handed to Log and Exp: a multiple of any x86 SIMD width (AVX-512: 8)


def _padded(centers: Any, weights: Any) -> tuple[Any, Any]:
    """Centres and weights padded with copies of the first centre at weight 0 to a multiple of LANES."""
    n = len(centers)
    extra = (-n) % LANES
    if not extra:
        return centers, weights
    return (
        np.concatenate([centers, np.repeat(centers[:1], extra, axis=0)]),
        np.concatenate([weights, np.zeros(extra)]),
    )


def build(model: Any) -> Any:
    """An ``onnx.ModelProto`` for a :class:`cmcan.model.train.TrainedModel` (metadata added by the caller)."""
    from onnx import TensorProto, helper, numpy_helper

    nodes: list[Any] = []
    inits: list[Any] = []

    def const(name: str, value: Any, dtype: Any = np.float64) -> str:
        inits.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def node(op: str, inputs: list[str], output: str, **attrs: Any) -> str:
        nodes.append(helper.make_node(op, inputs, [output], name=output, **attrs))
        return output

    n_in = 4
    a, b = model.oil.walther_ab
    k = 1.0 / model.quantity.lpm_per_unit  # l/min -> the quantity's unit, folded into every weight
    corr = model.correction

    nodes.append(
        helper.make_node(
            "Split", [INPUT_NAME, const("split4", [1, 1, 1, 1], np.int64)], ["n_p", "v_p", "dp", "temp"], axis=1
        )
    )
    # |n_P V_P| in cm3/min (the 1/1000 to l/min is folded into the coefficients).
    nv = node("Abs", [node("Mul", ["n_p", "v_p"], "nv_signed")], "nv")
    # ASTM D341: nu + 0.7 = 10^(10^(A - B log10 T_K)) = exp(exp(A ln10 + ln ln10 - B ln T_K)).
    # Log and Exp run on LANES copies of the temperature and one column is kept: onnxruntime computes
    # a transcendental function in its vectorized loop and a remainder elementwise, with other
    # rounding; with whole vectors per row a row gets the same bits alone or in a batch.
    t_lanes = node("Expand", ["temp", const("lanes", [1, LANES], np.int64)], "temp_lanes")
    ln_tk = node("Log", [node("Add", [t_lanes, const("kelvin", [273.15])], "t_k")], "ln_tk")
    walther_a = const("walther_a", [a * math.log(10.0) + math.log(math.log(10.0))])
    u = node("Add", [node("Mul", [ln_tk, const("walther_b", [-b])], "walther_bu"), walther_a], "walther_u")
    e2 = node("Exp", [node("Exp", [u], "walther_e1")], "walther_e2")
    col = [const("col0", [0], np.int64), const("col1", [1], np.int64), const("axis1", [1], np.int64)]
    nu = node("Sub", [node("Slice", [e2, *col], "walther_col"), const("k_0_7", [0.7])], "nu_cst")
    lam = node("Div", ["dp", nu], "dp_over_nu")
    turb = node(
        "Mul", [node("Sign", ["dp"], "dp_sign"), node("Sqrt", [node("Abs", ["dp"], "dp_abs")], "dp_sqrt")], "sqrt_dp"
    )
    comp = node("Mul", [nv, "dp"], "nv_dp")
    terms = node("Concat", [nv, lam, turb, comp], "terms", axis=1)
    c = model.coef
    coef = k * np.array([[c[0] * 1e-3], [-c[1]], [-c[2]], [-c[3] * 1e-6]])
    phys = node("MatMul", [terms, const("physics_coef", coef)], OUTPUT_PHYSICS)

    # Correction. Scaled normalized coordinates zs = sqrt(s) (x - lo) / span on the inputs that vary,
    # with s = 1 / (2 width^2), so that -s |z - c|^2 = 2 zs.(sqrt(s) c) - |zs|^2 - s |c|^2.
    s = 1.0 / (2.0 * model.width**2)
    active = np.flatnonzero(corr.active)
    sel = np.zeros((n_in, len(active)))
    for j, i in enumerate(active):
        sel[i, j] = math.sqrt(s) / corr.span[i]
    zs = node("Gemm", [INPUT_NAME, const("rbf_select", sel), const("rbf_shift", -(corr.lo @ sel))], "rbf_z")
    # Distance beyond the envelope in fade units: relu(|x - mid| - half) / (fade_span * span).
    inv = 1.0 / (model.fade_span * corr.span)
    mid = corr.lo + corr.span / 2.0
    uf = node("Gemm", [INPUT_NAME, const("fade_scale", np.diag(inv)), const("fade_shift", -mid * inv)], "fade_u")
    beyond = node(
        "Relu",
        [node("Sub", [node("Abs", [uf], "fade_abs"), const("fade_half", corr.span / 2.0 * inv)], "fade_d0")],
        "fade_d",
    )
    # |zs|^2 + |d|^2 in one reduction; the fade's exp(-|d|^2) multiplies every basis function.
    sq = node("ReduceSumSquare", [node("Concat", [zs, beyond], "rbf_fade", axis=1)], "sq", axes=[1], keepdims=1)
    # Centres padded to whole vectors (see LANES) with weight 0.
    centers, weights = _padded(corr.centers, corr.weights)
    arg = node("Gemm", [zs, const("rbf_centers", 2.0 * math.sqrt(s) * centers.T), sq], "rbf_arg", beta=-1.0)
    w = k * weights * np.exp(-s * np.sum(centers * centers, axis=1))
    raw = node("MatMul", [node("Exp", [arg], "rbf"), const("rbf_w", w[:, None])], "corr_faded")
    bound = k * corr.bound_lpm
    bounded = node("Clip", [raw, const("corr_lo", -bound), const("corr_hi", bound)], "correction")
    node("Add", [phys, bounded], OUTPUT_PRED)
    node("Mul", [nv, const("wb_gain", [model.eta_vol * 1e-3 * k])], OUTPUT_WHITEBOX)

    vi = helper.make_tensor_value_info
    graph = helper.make_graph(
        nodes,
        "cmcan_graybox",
        [vi(INPUT_NAME, TensorProto.DOUBLE, [None, n_in])],
        [vi(name, TensorProto.DOUBLE, [None, 1]) for name in (OUTPUT_PRED, OUTPUT_PHYSICS, OUTPUT_WHITEBOX)],
        inits,
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], ir_version=8)
