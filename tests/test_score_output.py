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
        return d, list(csv.DictReader(f))


def test_epoch_times_keep_their_fraction_and_hours_are_fixed_decimals(scored):
    _, scored = scored
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


def test_score_refuses_a_log_cut_mid_line_and_reads_it_with_keep_truncated(scored):
    d, rows = scored
    text = (d / "run.log").read_text()
    cut = d / "cut.log"
    cut.write_text(text[: len(text) - 9])  # the last line cut in its data
    n_lines = text.count("\n")
    r = run_cli("score", str(cut), "--out", str(d / "cut.csv"))
    assert r.returncode == 65 and f"cut.log: line {n_lines}" in r.stderr and "--keep-truncated" in r.stderr
    assert not (d / "cut.csv").exists()
    r = run_cli("score", str(cut), "--out", str(d / "cut.csv"), "--keep-truncated")
    assert r.returncode == 0, r.stderr
    assert f"cut.log: line {n_lines}" in r.stderr  # the warning names the cut
    with open(d / "cut.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == len(rows)  # one frame less: the same points
