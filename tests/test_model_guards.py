"""A model file's digest says it is intact, not that it is harmless: a file with a valid digest and a
slow ``Loop`` hung ``check`` and blocked a reload. The loader refuses what cmcan's exporter never
writes (read from the bytes, before onnxruntime), makes the session without running any of the graph,
and probes it bounded in time and memory. Hostile models here are built with the onnx package from
the shipped model, with its metadata, and sealed with a valid digest."""

from __future__ import annotations

import os
import re

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from cmcan.cli.errors import EX_CONFIG
from cmcan.model import ModelError, digest, load_model
from cmcan.model import runtime as rt
from tests.conftest import ROOT, run_cli
from tests.test_bad_inputs import refused
from tests.test_cli_run import config_copy

DEFAULT_MODEL = ROOT / "cmcan" / "model" / "default.onnx"
RIG_MODEL = ROOT / "examples" / "zema-rig" / "rig.onnx"


def hostile(path, extra_nodes, inits=(), functions=(), rename="predicted"):
    """The shipped model with the node writing ``rename`` made to write ``core`` and ``extra_nodes``
    computing ``rename`` from it (so they lie on the prediction's path), sealed with a valid digest."""
    m = onnx.load(str(DEFAULT_MODEL))
    for n in m.graph.node:
        n.output[:] = ["core" if o == rename else o for o in n.output]
    m.graph.node.extend(extra_nodes)
    m.graph.initializer.extend(inits)
    m.functions.extend(functions)
    path.write_bytes(digest.seal(m.SerializeToString()))
    assert digest.recorded_and_actual(path.read_bytes())[0] == digest.recorded_and_actual(path.read_bytes())[1]
    return path


def loop_model(path):
    """``predicted`` through a Loop of 10^12 iterations that adds 0: as right as the original, for ever."""
    vi = helper.make_tensor_value_info
    body = helper.make_graph(
        [helper.make_node("Identity", ["c_in"], ["c_out"]), helper.make_node("Add", ["v_in", "zero"], ["v_out"])],
        "body",
        [vi("i", TensorProto.INT64, []), vi("c_in", TensorProto.BOOL, []), vi("v_in", TensorProto.DOUBLE, None)],
        [vi("c_out", TensorProto.BOOL, []), vi("v_out", TensorProto.DOUBLE, None)],
        [numpy_helper.from_array(np.array(0.0), "zero")],
    )
    inits = [
        numpy_helper.from_array(np.array(10**12, np.int64), "trips"),
        numpy_helper.from_array(np.array(True), "go"),
    ]
    return hostile(path, [helper.make_node("Loop", ["trips", "go", "core"], ["predicted"], body=body)], inits)


def slow_chain_model(path, links=400):
    """Only operators cmcan uses, on constants: 400 products of 512 x 512 matrices (about 100 GFLOP)
    added times 0 to the prediction. Constant folding would compute it while the session is made."""
    a = numpy_helper.from_array(np.full((512, 512), 1e-3), "chain_a")
    nodes = [helper.make_node("MatMul", ["chain_a", "chain_a"], ["chain_1"])]
    nodes += [helper.make_node("MatMul", [f"chain_{i}", "chain_a"], [f"chain_{i + 1}"]) for i in range(1, links)]
    nodes += [
        helper.make_node("ReduceSumSquare", [f"chain_{links}"], ["chain_sum"], keepdims=1),
        helper.make_node("Mul", ["chain_sum", "chain_zero"], ["chain_0"]),
        helper.make_node("Add", ["core", "chain_0"], ["predicted"]),
    ]
    return hostile(path, nodes, [a, numpy_helper.from_array(np.zeros((1, 1)), "chain_zero")])


def memory_model(path):
    """Only operators cmcan uses: each row expanded to 2 * 10^8 doubles (1.6 GB a row), summed times 0."""
    shape = numpy_helper.from_array(np.array([1, 200_000_000], np.int64), "huge")
    nodes = [
        helper.make_node("Expand", ["core", "huge"], ["big"]),
        helper.make_node("ReduceSumSquare", ["big"], ["big_sum"], axes=[1], keepdims=1),
        helper.make_node("Mul", ["big_sum", "big_zero"], ["big_0"]),
        helper.make_node("Add", ["core", "big_0"], ["predicted"]),
    ]
    return hostile(path, nodes, [shape, numpy_helper.from_array(np.zeros((1, 1)), "big_zero")])


def test_check_refuses_a_sealed_model_with_a_loop(tmp_path):
    bad = loop_model(tmp_path / "looping.onnx")
    cfg = config_copy(tmp_path, model=str(bad))
    refused(run_cli("check", "--config", str(cfg), timeout=120), EX_CONFIG, "looping.onnx", "'Loop'", "refused")
    with pytest.raises(ModelError, match="control flow"):
        load_model(bad)


def test_the_probe_cancels_a_loop_the_operator_check_would_let_through(tmp_path, monkeypatch):
    """The second line: with Loop allowed, the probe's RunOptions.terminate ends the loop."""
    bad = loop_model(tmp_path / "looping.onnx")
    monkeypatch.setattr(rt, "OPERATORS", rt.OPERATORS | {"Loop", "Identity"})
    monkeypatch.setattr(rt, "check_operators", lambda blob, src: None)  # subgraphs too
    with pytest.raises(ModelError, match=r"did not finish within 0.3 s"):
        load_model(bad, budget_s=0.3)


def test_a_slow_graph_of_cmcan_operators_is_refused_by_the_probe_not_computed_at_load(tmp_path, monkeypatch):
    """Every session is made with constant folding off: with it, onnxruntime computed the whole chain
    while making the session, where no time limit reaches."""
    import onnxruntime

    made = []
    real = onnxruntime.InferenceSession

    def recording(*args, **kwargs):
        made.append(kwargs.get("disabled_optimizers"))
        return real(*args, **kwargs)

    monkeypatch.setattr(onnxruntime, "InferenceSession", recording)
    bad = slow_chain_model(tmp_path / "slow.onnx")
    with pytest.raises(ModelError, match=r"slow.onnx: a prediction did not finish within 0.3 s"):
        load_model(bad, budget_s=0.3)
    assert made and all(d is not None and "ConstantFolding" in d for d in made), made


def test_a_graph_that_asks_for_gigabytes_is_refused_by_the_probe(tmp_path):
    import resource

    bad = memory_model(tmp_path / "greedy.onnx")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ModelError, match=r"greedy.onnx: a prediction of 9 rows needs more than 64 MiB"):
        load_model(bad)
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert grown_mb < 200, grown_mb  # nothing like the 14 GB it asked for was touched


@pytest.mark.parametrize(
    "case, why",
    [
        ("domain", "'com.example:Mul'"),
        ("function", "model-local functions"),
        ("subgraph", "subgraphs"),
        ("unknown", "'Identity'"),
    ],
)
def test_other_things_a_cmcan_model_never_holds_are_refused_before_onnxruntime(tmp_path, case, why, monkeypatch):
    if case == "domain":
        bad = hostile(
            tmp_path / "m.onnx", [helper.make_node("Mul", ["core", "core"], ["predicted"], domain="com.example")]
        )
    elif case == "function":
        f = helper.make_function("local", "Twice", ["a"], ["b"], [helper.make_node("Add", ["a", "a"], ["b"])],
                                 [helper.make_opsetid("", 17)])  # fmt: skip
        bad = hostile(tmp_path / "m.onnx", [helper.make_node("Abs", ["core"], ["predicted"])], functions=[f])
    elif case == "subgraph":
        g = helper.make_graph([], "inner", [], [])
        bad = hostile(tmp_path / "m.onnx", [helper.make_node("Abs", ["core"], ["predicted"], hidden=g)])
    else:
        bad = hostile(tmp_path / "m.onnx", [helper.make_node("Identity", ["core"], ["predicted"])])

    def no_session(*_a, **_k):
        raise AssertionError("onnxruntime saw the file")

    import onnxruntime

    monkeypatch.setattr(onnxruntime, "InferenceSession", no_session)
    with pytest.raises(ModelError, match=re.escape(why)):
        load_model(bad)


def test_files_that_are_not_regular_files_are_refused_without_reading(tmp_path):
    fifo = tmp_path / "model.onnx"
    os.mkfifo(fifo)
    with pytest.raises(ModelError, match="not a regular file"):
        load_model(fifo)
    big = tmp_path / "big.onnx"
    with open(big, "wb") as f:
        f.truncate(rt.MAX_MODEL_BYTES + 1)
    with pytest.raises(ModelError, match="more than a cmcan model holds"):
        load_model(big)


def test_the_operator_list_is_what_the_exporter_writes():
    """OPERATORS equals the operators cmcan.model.graph builds, and the shipped models use no other."""
    source = (ROOT / "cmcan" / "model" / "graph.py").read_text()
    written = set(re.findall(r'node\(\s*"(\w+)"', source)) | set(re.findall(r'make_node\(\s*"(\w+)"', source))
    assert written == rt.OPERATORS
    for path in (DEFAULT_MODEL, RIG_MODEL):
        g = digest.graph_content(path.read_bytes())
        assert {op for _, op in g.ops} <= rt.OPERATORS and {d for d, _ in g.ops} == {""}
        assert (g.subgraphs, g.functions, g.training_info) == (0, 0, 0)
        assert [op for _, op in g.ops] == [n.op_type for n in onnx.load(str(path)).graph.node]


def test_the_shipped_models_pass_every_guard_and_predict_as_before():
    m = load_model(DEFAULT_MODEL)
    rows = m.probe_rows()
    assert rows.shape == (9, 4)
    import onnxruntime as ort

    plain = ort.InferenceSession(str(DEFAULT_MODEL), providers=["CPUExecutionProvider"])
    want = plain.run(["predicted"], {"x": rows})[0][:, 0]
    assert np.array_equal(m.predict(rows)[0], want)  # constant folding off changes no bit
