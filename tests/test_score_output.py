"""``cmcan score``'s table keeps the log's time resolution: epoch seconds to the microsecond (they
were written with 10 significant digits, whole seconds) and operating hours in fixed decimals."""

from __future__ import annotations

import csv
import itertools

import pytest

from tests.conftest import run_cli


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    d = tmp_path_factory.mktemp("score")
    r = run_cli(
        "simulate", "single_set_healthy", "--duration-h", "0.01", "--out", str(d / "run.csv"),
        "--candump", str(d / "run.log"),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = run_cli("score", str(d / "run.log"), "--out", str(d / "scores.csv"))
    assert r.returncode == 0, r.stderr
    with open(d / "scores.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_epoch_times_keep_their_fraction_and_hours_are_fixed_decimals(scored):
    times = [row["time_s"] for row in scored]
    assert float(times[0]) > 1e9  # epoch-stamped (the simulator's logs are)
    assert all(len(t.split(".")[1]) == 6 for t in times)
    # 10 points a second: every point its own time, 0.1 s apart
    values = [float(t) for t in times]
    assert len(set(values)) == len(values)
    assert max(abs(b - a - 0.1) for a, b in itertools.pairwise(values)) < 1e-6
    hours = [row["operating_h"] for row in scored]
    assert not any("e" in h.lower() for h in hours)
    assert all(len(h.split(".")[1]) == 9 for h in hours)
    assert float(hours[1]) - float(hours[0]) == pytest.approx(0.1 / 3600, abs=1e-9)
