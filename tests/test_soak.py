"""The soak (bench/soak.py) for 15 minutes of bus time in the slow tier: the daemon's receive loop on
a full 1 Mbit/s bus (about 8 M frames, the drive's and a flood of unrelated identifiers) through an
in-memory bus, as fast as it takes them. The 24-hour run is the documented benchmark
(docs/reliability.md). Fifteen minutes are enough for its checks here: the RSS moves by some 20 kB
over them (0.08 MB per bus hour), against a limit of 1 MB per bus hour."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.conftest import ROOT

pytestmark = pytest.mark.slow


MINUTES = 15


def test_fifteen_minutes_of_a_full_bus():
    r = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "soak.py"), "--minutes", str(MINUTES), "--json"],
        capture_output=True,
        text=True,
        timeout=1800,
        cwd=ROOT,
    )
    assert r.returncode in (0, 1), r.stderr
    res = json.loads(r.stdout)
    f = res["figures"]
    print(json.dumps(f, indent=1))
    assert res["frames"] > MINUTES * 60 * 8900 and 8500 < f["bus_frames_per_s"] < 9500
    failed = [name for name, ok in res["checks"].items() if not ok]
    assert not failed, (failed, f)
    # the figures the checks stand on, said again here
    assert f["rss_slope_mb_per_bus_h"] < 1.0 and f["rss_growth_mb_per_bus_h"] < 1.0
    assert f["cpu_per_frame_last_over_first"] < 1.5
    assert 0 < f["saves"] <= f["saves_allowed"] <= MINUTES + res["transitions"] + 2  # one a minute, one a change
