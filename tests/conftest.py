from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]


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
    from cmcan.dbc import load_dbc

    return load_dbc()
