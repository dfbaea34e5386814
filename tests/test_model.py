"""The gray-box model: training, the one-graph ONNX export, metadata, and the runtime's checks."""

import json

import numpy as np
import onnx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan import config as cfgmod
from cmcan.model import ModelError, digest, load_model
from cmcan.model.features import operating_points, series_from_columns
from cmcan.model.train import train_on_points
from cmcan.roles import MODEL_INPUTS
from cmcan.sim import scenario as scn
from cmcan.sim.run import simulate


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    cfg = cfgmod.load()
    run = simulate(scn.load(scn.shipped("training_healthy")).with_overrides(duration_h=0.6))
    series, truth = series_from_columns(run.columns)
    op = operating_points(series, cfg.gate_limits, 10.0, truth=truth)
    blob, model, stats = train_on_points(op, 0.4, cfg.motor_disp_cc, "test")
    path = tmp_path_factory.mktemp("model") / "m.onnx"
    path.write_bytes(blob)
    return path, model, stats, op


def envelope_samples(model, n=4000, seed=1, widen=0.0):
    rng = np.random.default_rng(seed)
    lo = np.array([model.envelope[k][0] for k in MODEL_INPUTS])
    hi = np.array([model.envelope[k][1] for k in MODEL_INPUTS])
    lo, hi = lo - widen * (hi - lo), hi + widen * (hi - lo)
    lo[3] = max(lo[3], -30.0)  # the viscosity law holds above the pour point
    return lo + rng.random((n, len(MODEL_INPUTS))) * (hi - lo)


def test_onnx_equals_python_reference_over_the_envelope_and_beyond(trained):
    path, model, _, _ = trained
    x = envelope_samples(model)
    wide = envelope_samples(model, n=2000, seed=2, widen=0.5)  # half a span beyond on every side
    m = load_model(path)
    for xs in (x, wide):
        parts = m.predict_parts(xs)
        # float64 graph against the float64 reference: rounding only
        np.testing.assert_allclose(parts["predicted"], model.predict(xs), rtol=1e-11)
        np.testing.assert_allclose(parts["physics"], model.physics(xs), rtol=1e-11)
        np.testing.assert_allclose(parts["whitebox"], model.whitebox(xs), rtol=1e-12)


def test_a_row_gives_the_same_bits_alone_or_anywhere_in_a_batch(trained):
    """The columnar replay evaluates ticks in batches, the daemon one by one: their outputs must be
    equal to the last bit, so the graph must not round a row differently by its place in a batch."""
    m = load_model(trained[0])
    x = np.concatenate([envelope_samples(trained[1], n=600), envelope_samples(trained[1], n=300, seed=3, widen=0.6)])
    pred, wb = m.predict(x)
    single = np.array([m.predict_one(*row) for row in x])
    assert np.array_equal(single[:, 0], pred) and np.array_equal(single[:, 1], wb)
    rng = np.random.default_rng(5)
    for _ in range(20):
        a = int(rng.integers(0, len(x) - 1))
        b = int(rng.integers(a + 1, len(x) + 1))
        assert np.array_equal(m.predict(x[a:b])[0], pred[a:b])


def test_one_graph_holds_physics_correction_and_whitebox(trained):
    g = onnx.load(str(trained[0])).graph
    ops = {n.op_type for n in g.node}
    assert {"Log", "Exp", "Sqrt", "Gemm", "MatMul", "Clip", "ReduceSumSquare"} <= ops
    assert [o.name for o in g.output] == ["predicted", "physics", "whitebox"]
    assert [i.name for i in g.input] == ["x"]
    assert g.input[0].type.tensor_type.elem_type == onnx.TensorProto.DOUBLE
    assert len(g.node) <= 34  # about 0.35 us per node on a single-sample call


def test_physics_coefficients_are_non_negative_and_carry_the_model(trained):
    model = trained[1]
    assert np.all(model.coef >= 0) and model.coef[0] > 0.9  # ideal flow nearly all delivered
    x = envelope_samples(model)
    # the learned correction is a small share of the prediction and never beyond its bound
    corr = model.predict(x) - model.physics(x)
    assert np.max(np.abs(corr)) <= model.correction.bound_lpm / model.quantity.lpm_per_unit * (1 + 1e-12)
    assert np.max(np.abs(corr) / model.predict(x)) < 0.01


def test_correction_fades_outside_the_envelope(trained):
    model = trained[1]
    x = envelope_samples(model, n=200)
    far = x.copy()
    far[:, 2] = model.envelope["dp_bar"][1] + 2.0 * np.ptp(model.envelope["dp_bar"])  # far above the pressures seen
    np.testing.assert_allclose(model.predict(far), model.physics(far), rtol=1e-12)
    m = load_model(trained[0])
    np.testing.assert_allclose(m.predict_parts(far)["predicted"], m.predict_parts(far)["physics"], rtol=1e-12)


def test_metadata_names_inputs_units_envelope_and_training(trained):
    path, _model, _stats, op = trained
    props = {p.key: json.loads(p.value) for p in onnx.load(str(path)).metadata_props}
    assert props["cmcan.inputs"] == [
        {"name": "pump_speed_rpm", "unit": "rpm", "index": 0},
        {"name": "pump_disp_cc", "unit": "cm3/rev", "index": 1},
        {"name": "dp_bar", "unit": "bar", "index": 2},
        {"name": "temp_c", "unit": "degC", "index": 3},
    ]
    assert props["cmcan.motor_disp_cc"] == 44.0
    env = props["cmcan.envelope"]
    trn = op.steady & (op.hours < 0.4)
    assert env["dp_bar"] == [pytest.approx(op.x[trn, 2].min()), pytest.approx(op.x[trn, 2].max())]
    assert props["cmcan.residual_stats"]["set"] == "D_tst" and props["cmcan.residual_stats"]["rmse"] > 0
    assert props["cmcan.quantity"] == {"role": "motor_speed_rpm", "unit": "rpm"}
    assert props["cmcan.oil"] == {"nu40_cst": 46.0, "nu100_cst": 6.8}
    assert set(props["cmcan.physics"]["coefficients"]) == {"ideal_flow", "laminar", "turbulent", "compressibility"}
    assert len(props["cmcan.training"]["fingerprint"]) == 64
    assert props["cmcan.model_version"].endswith(props["cmcan.training"]["fingerprint"][:12])


def test_graybox_beats_whitebox_on_held_out_points(trained):
    path, _, _stats, op = trained
    tst = op.steady & (op.hours >= 0.4)
    pred, wb = load_model(path).predict(op.x[tst])
    y = op.measured[tst]
    assert np.sqrt(np.mean((pred - y) ** 2)) < np.sqrt(np.mean((wb - y) ** 2)) / 3


def test_refuses_a_model_for_another_motor_displacement(trained):
    with pytest.raises(ModelError, match="motor displacement of 44 cm3/rev, the configuration says 55"):
        load_model(trained[0], motor_disp_cc=55.0)


def test_refuses_inputs_in_other_units(trained):
    expected = {"pump_speed_rpm": "rpm", "pump_disp_cc": "%", "dp_bar": "bar", "temp_c": "degC"}
    with pytest.raises(ModelError, match="'pump_disp_cc' is in 'cm3/rev', the configuration gives '%'"):
        load_model(trained[0], expected_inputs=expected)


def test_refuses_other_inputs(trained):
    with pytest.raises(ModelError, match="model inputs are"):
        load_model(trained[0], expected_inputs={"pump_speed_rpm": "rpm", "dp_bar": "bar"})


def _with_meta(src, dst, **changes):
    """A copy with metadata changed and sealed again: as a writer would have written it (the digest
    of an edited file is tests/test_model_digest.py's subject)."""
    m = onnx.load(str(src))
    for p in m.metadata_props:
        key = p.key.removeprefix("cmcan.")
        if key in changes:
            p.value = changes[key]
    dst.write_bytes(digest.seal(m.SerializeToString()))
    return dst


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"format": json.dumps("cmcan-graybox/1")}, "model format 'cmcan-graybox/1', this cmcan reads"),
        ({"inputs": json.dumps([{"name": "pump_speed_rpm", "index": 0}])}, r"cmcan.inputs\[0\]"),
        ({"inputs": "[1, 2"}, "cmcan.inputs is not valid JSON"),
        ({"envelope": json.dumps({"dp_bar": [300, 20]})}, "cmcan.envelope.dp_bar: expected"),
        ({"motor_disp_cc": "null"}, "cmcan.motor_disp_cc: expected a positive number"),
        ({"quantity": json.dumps({"role": "torque_nm", "unit": "Nm"})}, "cmcan.quantity: expected"),
    ],
)
def test_refuses_wrong_metadata_naming_the_field(trained, tmp_path, changes, message):
    bad = _with_meta(trained[0], tmp_path / "bad.onnx", **changes)
    with pytest.raises(ModelError, match=message):
        load_model(bad)


def test_refuses_a_foreign_onnx_file(tmp_path):
    from onnx import TensorProto, helper

    g = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [None, 4])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, 4])],
    )
    p = tmp_path / "foreign.onnx"
    onnx.save(helper.make_model(g), str(p))
    with pytest.raises(ModelError, match="not a cmcan model"):
        load_model(p)


def test_refuses_garbage_and_missing_files(tmp_path):
    p = tmp_path / "garbage.onnx"
    p.write_bytes(b"not onnx at all")
    with pytest.raises(ModelError, match="not a loadable ONNX model"):
        load_model(p)
    with pytest.raises(ModelError, match="not found"):
        load_model(tmp_path / "missing.onnx")


def test_too_little_training_data_is_refused(trained):
    op = trained[3]
    with pytest.raises(ValueError, match="steady points before t_trn"):
        train_on_points(op, 0.001, 44.0, "tiny")


@settings(max_examples=150, deadline=None)
@given(
    healthy=st.lists(st.integers(90, 110), min_size=1, max_size=60),
    faulty=st.lists(st.integers(85, 105), min_size=1, max_size=60),
)
def test_auc_matches_scikit_learn(healthy, faulty):
    """cmcan's AUC (Mann-Whitney on sorted arrays, ties one half) against scikit-learn's ROC AUC, on
    integer ratios so that ties happen often."""
    from sklearn.metrics import roc_auc_score

    from cmcan.model.evaluate import auc_lower

    h, f = np.array(healthy, dtype=float), np.array(faulty, dtype=float)
    y = np.r_[np.zeros(h.size), np.ones(f.size)]
    if len(set(y)) == 2:
        assert auc_lower(h, f) == pytest.approx(roc_auc_score(y, -np.r_[h, f]), abs=1e-12)
