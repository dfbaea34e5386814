from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _fresh_native_helpers() -> None:
    """The checkout's C helpers rebuilt when their sources changed after the install built them, so
    the tests exercise the sources as they are (nothing where there is no compiler)."""
    sys.path.insert(0, str(ROOT))
    import hatch_build

    lib, sources = ROOT / hatch_build.LIBRARY, [ROOT / s for s in hatch_build.SOURCES]
    if not all(s.is_file() for s in sources):
        return
    if not lib.is_file() or lib.stat().st_mtime < max(s.stat().st_mtime for s in sources):
        hatch_build.build_native(ROOT)


_fresh_native_helpers()

# The compiled-DBC cache (cmcan.can.dbccache) of this test session: empty at its start, as on a fresh
# CI machine, shared by the xdist workers (they inherit it and race to write its entries), and never
# the user's own. Set by the first process to import this file; CMCAN_CACHE_DIR given outside wins.
if not os.environ.get("CMCAN_CACHE_DIR"):
    os.environ["CMCAN_CACHE_DIR"] = _session_cache = tempfile.mkdtemp(prefix="cmcan-test-cache-")
    atexit.register(shutil.rmtree, _session_cache, True)


def small_scenario(**over: Any) -> dict[str, Any]:
    """A short healthy scenario as a dict, for tests that build their own variants."""
    base: dict[str, Any] = {
        "name": "small",
        "seed": 3,
        "duration_h": 0.02,
        "oil": {"model": "prescribed", "temp_c": 50.0},
        "duty": {"kind": "constant", "pump_speed_rpm": 2000, "pump_disp_pct": 80, "dp_bar": 300},
    }
    base.update(over)
    return base


def run_cli(
    *args: str, cwd: Path | None = None, timeout: float = 600, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """Run the real ``cmcan`` command line in a subprocess."""
    full_env = {**os.environ, **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", "cmcan", *args],
        capture_output=True,
        text=True,
        cwd=cwd or ROOT,
        timeout=timeout,
        env=full_env,
    )


@pytest.fixture(scope="session")
def db():
    from cmcan.can.dbc import load_dbc

    return load_dbc()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    """Under xdist, a vcan test (setup, where the VM runs them all, call and teardown) has the
    machine to itself; see ``tests/machine_share.py``."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        yield
        return
    from tests.machine_share import machine_share

    with machine_share(exclusive=item.get_closest_marker("vcan") is not None):
        yield


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The longest files first: the vcan tier's (the VM, which then has the machine while the other
    workers have only started), then files with a slow test, then the rest, each file's tests in
    their own order. xdist's loadfile distribution hands files to the workers in this order, and a
    long file taken last leaves the other workers idle while it runs (the soak's 3 min at the end
    of a CI run)."""
    rank: dict[str, int] = {}
    for item in items:
        r = 0 if item.get_closest_marker("vcan") else 1 if item.get_closest_marker("slow") else 2
        rank[item.nodeid.split("::")[0]] = min(r, rank.get(item.nodeid.split("::")[0], 2))
    items.sort(key=lambda item: rank[item.nodeid.split("::")[0]])
