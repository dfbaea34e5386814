"""The benchmarks are run by hand, not by CI: this keeps them from rotting when the code they call
changes (an import of a removed module, a name that moved). Each is imported as a module, which runs
its imports and definitions but not its ``main``; ``--help`` is run as a process."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import pytest

from tests.conftest import ROOT

BENCHES = sorted((ROOT / "bench").glob("*.py"))


def test_there_are_benchmarks():
    assert {p.name for p in BENCHES} >= {"bench_model.py", "bench_replay.py", "bench_uplink.py", "soak.py"}


@pytest.mark.parametrize("path", BENCHES, ids=lambda p: p.name)
def test_a_benchmark_imports_and_says_how_to_run_it(path):
    spec = importlib.util.spec_from_file_location(f"bench_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    try:
        spec.loader.exec_module(module)  # its imports resolve against the code as it is now
    finally:
        del sys.modules[spec.name]
    r = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0 and "usage" in r.stdout.lower(), r.stderr


def test_the_baseline_benchmark_runs_in_its_quick_mode(tmp_path):
    """bench_baseline.py end to end on a tiny fleet (4 machines x 20 h): the fleet written to its cache,
    every arm the monitor has replayed, the table and the fit's cost printed."""
    path = ROOT / "bench" / "bench_baseline.py"
    r = subprocess.run(
        [sys.executable, str(path), "--quick", "--cache", str(tmp_path), "--json", str(tmp_path / "b.json")],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    for line in ("false low warnings /100 h, healthy", "arriving leaks flagged", "on-board fit cost", "Baseline.learn"):
        assert line in r.stdout, r.stdout
    doc = json.loads((tmp_path / "b.json").read_text())
    assert doc["spec"]["machines"] == 4 and {"type", "engineer"} <= set(doc["arms"])
    assert len(doc["machines"]) == 4 and doc["learning_cost"]["ticks"] > 0
