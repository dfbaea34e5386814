"""The benchmarks are run by hand, not by CI: this keeps them from rotting when the code they call
changes (an import of a removed module, a name that moved). Each is imported as a module, which runs
its imports and definitions but not its ``main``; ``--help`` is run as a process."""

from __future__ import annotations

import importlib.util
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
