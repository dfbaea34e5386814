"""The shipped default model: the paper protocol's figures, and that it rebuilds to the same model."""

import os
import subprocess
import sys
import warnings

import numpy as np
import pytest

from cmcan import config as cfgmod
from cmcan.model import load_model
from cmcan.model.evaluate import protocol
from cmcan.model.features import operating_points, series_from_columns
from cmcan.model.runtime import default_model_path
from cmcan.rebuild_default import build
from cmcan.roles import MODEL_INPUTS
from cmcan.sim import scenario as scn
from cmcan.sim.run import simulate

pytestmark = pytest.mark.slow


def points(name, **over):
    cfg = cfgmod.load()
    s = scn.load(scn.shipped(name))
    run = simulate(s.with_overrides(**over) if over else s)
    series, truth = series_from_columns(run.columns, name)
    return operating_points(series, cfg.gate_limits, 10.0, truth=truth)


@pytest.fixture(scope="module")
def report():
    model = load_model(default_model_path(), motor_disp_cc=cfgmod.load().motor_disp_cc)
    rep, _ = protocol(
        model,
        points("training_healthy"),
        1.0,
        points("two_set_validation"),
        1.0,
        {"two_set_train": points("two_set_train")},
    )
    return rep


@pytest.mark.parametrize("name", ["D_tst", "two_set_train", "D_val_healthy"])
def test_graybox_rmse_is_at_most_a_third_of_whitebox(report, name):
    f = report["sets"][name]
    print(name, f)
    assert f["points"] > 1000
    assert f["rmse_graybox"] <= f["rmse_whitebox"] / 3


@pytest.mark.parametrize("name", ["D_tst", "two_set_train", "D_val_healthy"])
def test_healthy_ratio_stays_within_one_percent(report, name):
    f = report["sets"][name]
    assert f["ratio_p1_pct"] >= 99.0 and f["ratio_p99_pct"] <= 101.0


def test_five_lpm_leakage_moves_the_ratio_by_three_halfwidths(report):
    print("shift", report["damage_shift_pct"], "halfwidths", report["damage_shift_in_halfwidths"])
    assert report["damage_shift_pct"] < 0
    assert report["damage_shift_in_halfwidths"] >= 3.0


def assert_same_model(path) -> None:
    shipped = load_model(default_model_path())
    rebuilt = load_model(path)
    assert rebuilt.meta.training["fingerprint"] == shipped.meta.training["fingerprint"]
    for k in MODEL_INPUTS:
        assert rebuilt.envelope[k] == pytest.approx(shipped.envelope[k], rel=1e-12)
    rng = np.random.default_rng(0)
    lo = np.array([shipped.envelope[k][0] for k in MODEL_INPUTS])
    hi = np.array([shipped.envelope[k][1] for k in MODEL_INPUTS])
    x = lo + rng.random((20000, 4)) * (hi - lo)
    a, _ = shipped.predict(x)
    b, _ = rebuilt.predict(x)
    # Two convex fits in float64: another BLAS kernel or thread count changes the last bits only
    # (about 1e-15 measured). 1e-6 leaves room for that and is 2e4 times finer than the 2 % margin.
    assert np.max(np.abs(a - b) / np.abs(a)) < 1e-6


def test_rebuild_matches_the_shipped_model(tmp_path):
    out = tmp_path / "rebuilt.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a fit that warns (no convergence, ill-conditioning) fails here
        build(out)
    assert_same_model(out)


def _numpy_dispatch() -> str:
    """Every SIMD target numpy dispatches to beyond its baseline on this build (disabling them all
    leaves the portable x86-64-v2 code)."""
    try:
        from numpy._core import _multiarray_umath as umath
    except ImportError:  # numpy 1.x
        from numpy.core import _multiarray_umath as umath
    return " ".join(getattr(umath, "__cpu_dispatch__", []))


# Other machines, as far as one machine can play them: OpenBLAS kernels for older CPUs, one thread,
# and numpy's SIMD dispatch limited to its baseline.
OTHER_MACHINES = {
    "haswell-1-thread": {"OPENBLAS_CORETYPE": "Haswell", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"},
    "nehalem-no-avx": {
        "OPENBLAS_CORETYPE": "Nehalem",
        "OPENBLAS_NUM_THREADS": "2",
        "NPY_DISABLE_CPU_FEATURES": _numpy_dispatch(),
    },
}

_BUILD = """
import warnings
from pathlib import Path
from cmcan.rebuild_default import build
with warnings.catch_warnings():
    warnings.simplefilter("error")
    build(Path({out!r}))
"""


@pytest.mark.parametrize("machine", list(OTHER_MACHINES))
def test_rebuild_on_other_blas_and_simd_matches_the_shipped_model(tmp_path, machine):
    out = tmp_path / f"{machine}.onnx"
    env = {**os.environ, **OTHER_MACHINES[machine]}
    r = subprocess.run(
        [sys.executable, "-c", _BUILD.format(out=str(out))], env=env, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert_same_model(out)
