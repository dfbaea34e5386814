"""The soak (bench/soak.py) for 30 minutes of bus time in the slow tier: the daemon's receive loop on
a full 1 Mbit/s bus (about 16 M frames, the drive's and a flood of unrelated identifiers) through an
in-memory bus, as fast as it takes them. The 24-hour run is the documented benchmark
(docs/reliability.md)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.conftest import ROOT

pytestmark = pytest.mark.slow


def test_thirty_minutes_of_a_full_bus():
    r = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "soak.py"), "--minutes", "30", "--json"],
        capture_output=True,
        text=True,
        timeout=1800,
        cwd=ROOT,
    )
    assert r.returncode in (0, 1), r.stderr
    res = json.loads(r.stdout)
    f = res["figures"]
    print(json.dumps(f, indent=1))
    assert res["frames"] > 16_000_000 and 8500 < f["bus_frames_per_s"] < 9500
    failed = [name for name, ok in res["checks"].items() if not ok]
    assert not failed, (failed, f)
    # the figures the checks stand on, said again here
    assert f["rss_slope_mb_per_bus_h"] < 1.0 and f["rss_growth_mb_per_bus_h"] < 1.0
    assert f["cpu_per_frame_last_over_first"] < 1.5
    assert 0 < f["saves"] <= f["saves_allowed"] <= 30 + res["transitions"] + 2  # one a minute, one a change
