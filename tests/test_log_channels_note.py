"""A log of several buses read by a machine of one bus: training, scoring and gap diagnosis say so,
as replay does (a foreign bus's frames with a mapped identifier would be read as inputs)."""

from __future__ import annotations

from tests.conftest import run_cli


def test_score_of_a_log_of_two_buses_notes_they_were_read_as_one(tmp_path):
    one = tmp_path / "a.log"
    res = run_cli("simulate", "single_set_healthy", "--duration-h", "0.02", "--out", str(tmp_path / "r.csv"),
                  "--candump", str(one))  # fmt: skip
    assert res.returncode == 0, res.stderr
    lines = one.read_text().splitlines()
    two = tmp_path / "two.log"
    two.write_text("".join(f"{ln}\n{ln.replace(' can0 ', ' can1 ')}\n" for ln in lines))
    merged = run_cli("score", str(two), "--out", str(tmp_path / "s.csv"))
    assert merged.returncode == 0, merged.stderr
    assert "the log's channels can0, can1 were all read as can0" in merged.stderr
    assert "channels.from_log" in merged.stderr
    single = run_cli("score", str(one), "--out", str(tmp_path / "s1.csv"))
    assert single.returncode == 0 and "were all read as" not in single.stderr, single.stderr
