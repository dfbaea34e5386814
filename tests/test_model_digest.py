"""A model file's digest (cmcan.content_sha256): written by every export, checked at every load.

A bit flipped in a weight (flash corruption, a bad copy) gives a model that loads and predicts
plausibly wrong values; the digest makes it a refused file instead."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import onnx
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from onnx import TensorProto, helper, numpy_helper

from cmcan.cli.errors import EX_CONFIG
from cmcan.model import ModelError, digest, load_model
from tests.conftest import ROOT, run_cli
from tests.test_bad_inputs import refused
from tests.test_cli_run import config_copy

DEFAULT_MODEL = ROOT / "cmcan" / "model" / "default.onnx"
RIG_MODEL = ROOT / "examples" / "zema-rig" / "rig.onnx"
MISMATCH = "do not match their recorded digest"


def flipped_weight(dst, name="physics_coef", bit=45):
    """The default model with one bit flipped in the raw data of initializer ``name`` (bit 45 of its
    first float64: 2^-7 of the ideal-flow coefficient), the metadata and the digest untouched."""
    blob = bytearray(DEFAULT_MODEL.read_bytes())
    raw = next(i.raw_data for i in onnx.load_from_string(bytes(blob)).graph.initializer if i.name == name)
    assert len(raw) >= 8 and bytes(blob).count(raw) == 1
    at = bytes(blob).find(raw) + bit // 8
    blob[at] ^= 1 << (bit % 8)
    dst.write_bytes(bytes(blob))
    return dst


def ort_predict(path, x):
    """The graph run by onnxruntime alone, without cmcan's checks."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return sess.run(["predicted"], {"x": x})[0][:, 0]


@pytest.mark.parametrize("path", [DEFAULT_MODEL, RIG_MODEL], ids=["default", "rig"])
def test_the_shipped_models_carry_a_matching_digest(path):
    blob = path.read_bytes()
    recorded, actual = digest.recorded_and_actual(blob)
    assert recorded == actual
    props = {p.key: p.value for p in onnx.load_from_string(blob).metadata_props}
    assert json.loads(props[digest.KEY]) == actual  # the entry as the onnx parser reads it
    load_model(path)


def test_a_weight_bit_flip_gives_a_plausible_model_that_check_and_run_refuse(tmp_path):
    bad = flipped_weight(tmp_path / "flipped.onnx")
    # What made it dangerous: onnxruntime runs it, and its predictions are off by under 1 %.
    x = np.array([[2000.0, 60.0, 250.0, 50.0], [2600.0, 40.0, 150.0, 45.0]])
    rel = ort_predict(bad, x) / ort_predict(DEFAULT_MODEL, x) - 1
    assert np.all((np.abs(rel) > 1e-3) & (np.abs(rel) < 1e-2)), rel
    cfg = config_copy(tmp_path, model=str(bad), **{"bus.interface": "virtual"})
    for args in (("check",), ("run", "--state-dir", str(tmp_path))):
        refused(run_cli(*args, "--config", str(cfg)), EX_CONFIG, "flipped.onnx", MISMATCH, "corrupt or was edited")
    with pytest.raises(ModelError, match=MISMATCH):
        load_model(bad)


def test_an_intact_copy_passes_check(tmp_path):
    good = tmp_path / "copy.onnx"
    shutil.copyfile(DEFAULT_MODEL, good)
    r = run_cli("check", "--config", str(config_copy(tmp_path, model=str(good))))
    assert r.returncode == 0, r.stderr


def test_every_byte_of_the_file_is_covered():
    """One bit flipped anywhere (weights, graph, opset, metadata, the digest entry itself) leaves no
    file whose recorded digest matches: a mismatch, no digest, or not a protobuf message."""
    blob = DEFAULT_MODEL.read_bytes()
    outcomes = {"mismatch": 0, "no digest": 0, "malformed": 0}
    for i in range(len(blob)):
        b = bytearray(blob)
        b[i] ^= 1 << (i % 8)
        try:
            recorded, actual = digest.recorded_and_actual(bytes(b))
        except ValueError:
            outcomes["malformed"] += 1
            continue
        assert recorded != actual, i
        outcomes["mismatch" if recorded is not None else "no digest"] += 1
    assert all(outcomes.values()), outcomes  # each way of failing was reached


def test_edited_metadata_is_refused_as_well(tmp_path):
    """The metadata the runtime relies on (envelope, oil, V_M) are covered: a wider envelope, say."""
    m = onnx.load(str(DEFAULT_MODEL))
    for p in m.metadata_props:
        if p.key == "cmcan.envelope":
            env = json.loads(p.value)
            env["dp_bar"][1] += 100.0
            p.value = json.dumps(env)
    onnx.save(m, str(tmp_path / "edited.onnx"))
    with pytest.raises(ModelError, match=f"edited.onnx: the weights and metadata {MISMATCH}"):
        load_model(tmp_path / "edited.onnx")


def _without_digest(dst):
    m = onnx.load(str(DEFAULT_MODEL))
    kept = [p for p in m.metadata_props if p.key != digest.KEY]
    del m.metadata_props[:]
    m.metadata_props.extend(kept)
    onnx.save(m, str(dst))
    return dst


def test_a_model_without_a_digest_is_refused_with_what_to_do(tmp_path):
    old = _without_digest(tmp_path / "old.onnx")
    with pytest.raises(ModelError, match=r"old.onnx: no digest of its weights .*retrain it with cmcan train"):
        load_model(old)
    # Sealing what is left gives the shipped file back: the entry is all a writer adds.
    assert digest.seal(old.read_bytes()) == DEFAULT_MODEL.read_bytes()


def test_two_digest_entries_are_refused(tmp_path):
    m = onnx.load(str(DEFAULT_MODEL))
    m.metadata_props.append(onnx.StringStringEntryProto(key=digest.KEY, value=json.dumps("0" * 64)))
    onnx.save(m, str(tmp_path / "two.onnx"))
    with pytest.raises(ModelError, match=f"two.onnx: 2 entries {digest.KEY}, expected one"):
        load_model(tmp_path / "two.onnx")


def _small_model(entries: list[tuple[str, str]], doc: str) -> onnx.ModelProto:
    g = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.DOUBLE, [None, 4])],
        [helper.make_tensor_value_info("y", TensorProto.DOUBLE, [None, 4])],
        [numpy_helper.from_array(np.arange(40, dtype=np.float64), "w")],
    )
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)], doc_string=doc)
    for k, v in entries:
        m.metadata_props.append(onnx.StringStringEntryProto(key=k, value=v))
    return m


@settings(max_examples=150, deadline=None)
@given(
    entries=st.lists(st.tuples(st.text(max_size=12), st.text(max_size=300)), max_size=6),
    stale_at=st.none() | st.integers(0, 6),
    doc=st.text(max_size=200),
)
@example(entries=[("cmcan.x", "v" * 200)], stale_at=None, doc="")  # two-byte lengths
@example(entries=[("a", "1"), ("b", "2")], stale_at=1, doc="d")  # an old digest between other entries
def test_sealing_agrees_with_the_onnx_parser(entries, stale_at, doc):
    """The hand-written walk over the protobuf records against the protobuf library (through onnx)."""
    m = _small_model(entries, doc)
    plain = m.SerializeToString()
    if stale_at is not None:  # an earlier digest entry somewhere among the others: replaced
        m.metadata_props.insert(min(stale_at, len(entries)), onnx.StringStringEntryProto(key=digest.KEY, value='"0"'))
    sealed = digest.seal(m.SerializeToString())
    parsed = onnx.load_from_string(sealed)
    assert [(p.key, p.value) for p in parsed.metadata_props] == [
        *entries,
        (digest.KEY, json.dumps(hashlib.sha256(plain).hexdigest())),
    ]
    assert parsed.graph.SerializeToString() == m.graph.SerializeToString()
    recorded, actual = digest.recorded_and_actual(sealed)
    assert recorded == actual == hashlib.sha256(plain).hexdigest()
    assert digest.seal(sealed) == sealed
    # onnx's own load and save (a tool that rewrites the file) keeps it valid
    assert digest.recorded_and_actual(parsed.SerializeToString()) == (recorded, actual)


@pytest.mark.parametrize("junk", [b"\x80", b"\x0a\x05ab", b"\x0b", b"\x00\x01"])
def test_bytes_that_are_not_protobuf_are_malformed(junk):
    with pytest.raises(digest.MalformedError):
        digest.recorded_and_actual(DEFAULT_MODEL.read_bytes() + junk)


def test_a_file_onnxruntime_takes_but_the_walk_does_not_is_refused(tmp_path):
    """A protobuf group (wire type 3, not in onnx.proto) before the model: onnxruntime skips it as
    an unknown field; the digest's walk stops, and the file is refused, not trusted undigested."""
    group = bytes([0xA3, 0x06, 0xA4, 0x06])  # field 100: start group, end group
    p = tmp_path / "group.onnx"
    p.write_bytes(group + DEFAULT_MODEL.read_bytes())
    with pytest.raises(ModelError, match=r"group\.onnx: not a well-formed model file: wire type 3 at byte 0"):
        load_model(p)
