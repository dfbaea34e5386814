"""Benchmark: the gray-box model's single-sample inference time, its load time and its training time.

Targets on the project's machine: under 20 us per single-sample call; training on one hour of
100 Hz data under 60 s. Printed side by side with baselines run in the same process:
- inference: a do-nothing ONNX graph (Identity on the same float64 input) through the same
  onnxruntime session options and the same bound call, i.e. onnxruntime's own per-call floor;
- load (the daemon's start and SIGHUP reload): ``load_model`` with its checks against an onnxruntime
  session of the same file alone; the digest check's share (``cmcan.model.digest``) on its own;
- training: the white-box ("light gray") least-squares fit on the same steady points.

    python bench/bench_model.py [--calls 20000] [--hours 1.0] [--loads 50]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from cmcan import config as cfgmod
from cmcan.model import digest, load_model
from cmcan.model.features import operating_points, series_from_columns
from cmcan.model.physics import fit_eta_vol
from cmcan.model.runtime import default_model_path
from cmcan.sim import scenario as scn
from cmcan.sim.run import simulate


def identity_session(path: Path):
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper

    g = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])],
        "identity",
        [helper.make_tensor_value_info("x", TensorProto.DOUBLE, [None, 4])],
        [helper.make_tensor_value_info("y", TensorProto.DOUBLE, [None, 4])],
    )
    onnx.save(helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]), str(path))
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    # Bound like the model's per-tick call: preallocated input and output, run in place.
    x = np.zeros((1, 4))
    values = [ort.OrtValue.ortvalue_from_numpy(a) for a in (x, np.zeros((1, 4)))]
    binding = sess.io_binding()
    binding.bind_ortvalue_input("x", values[0])
    binding.bind_ortvalue_output("y", values[1])
    return lambda: (values, sess.run_with_iobinding(binding))


def per_call_us(fn, calls: int) -> float:
    fn()
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        best = min(best, (time.perf_counter() - t0) / calls * 1e6)
    return best


def best_ms(fn, repeats: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, (time.perf_counter() - t0) * 1e3)
    return best


def bare_session(path: Path):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=20000)
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--loads", type=int, default=50, help="model loads timed (best of)")
    args = ap.parse_args()

    model = load_model(default_model_path())
    with tempfile.TemporaryDirectory() as d:
        ident = identity_session(Path(d) / "identity.onnx")
        t_model = per_call_us(lambda: model.predict_one(2000.0, 60.0, 300.0, 50.0), args.calls)
        t_ident = per_call_us(ident, args.calls)
    print(f"inference  model predict_one     {t_model:8.2f} us/call (target < 20 us)")
    print(f"           baseline Identity     {t_ident:8.2f} us/call")
    print(f"           ratio model/baseline  {t_model / t_ident:8.2f} x")

    path = default_model_path()
    blob = path.read_bytes()
    t_load = best_ms(lambda: load_model(path), args.loads)
    t_bare = best_ms(lambda: bare_session(path), args.loads)
    t_digest = best_ms(lambda: digest.recorded_and_actual(blob), args.loads * 20)
    print(f"load       load_model (all checks)   {t_load:8.3f} ms ({len(blob)} bytes)")
    print(f"           baseline session alone    {t_bare:8.3f} ms")
    print(f"           ratio                     {t_load / t_bare:8.2f} x")
    print(f"           of which the digest       {t_digest:8.3f} ms ({t_digest / t_load * 100:.1f} % of the load)")

    cfg = cfgmod.load()
    run = simulate(scn.load(scn.shipped("training_healthy")).with_overrides(duration_h=args.hours))
    from cmcan.model.train import train_on_points

    t0 = time.perf_counter()
    series, truth = series_from_columns(run.columns)
    op = operating_points(series, cfg.gate_limits, 10.0, truth=truth)
    train_on_points(op, args.hours * 0.75, cfg.motor_disp_cc, "bench")
    t_train = time.perf_counter() - t0
    t0 = time.perf_counter()
    trn = op.steady & (op.hours < args.hours * 0.75)
    fit_eta_vol(op.x[trn], op.measured[trn] * cfg.motor_disp_cc / 1000.0)
    t_wb = time.perf_counter() - t0
    print(f"training   {args.hours:g} h of 100 Hz data ({len(run)} samples, {int(trn.sum())} steady points in D_trn)")
    print(f"           gray-box (features+fit+export) {t_train:8.2f} s (target < 60 s)")
    print(f"           baseline white-box fit          {t_wb:8.4f} s")
    print(f"           ratio                           {t_train / max(t_wb, 1e-9):8.0f} x")
    print(f"targets met: inference {'yes' if t_model < 20 else 'NO'}, training {'yes' if t_train < 60 else 'NO'}")


if __name__ == "__main__":
    main()
