"""`cmcan replay LOG [LOG ...]`: a machine's logs replayed as its life, the monitor's state carried from
each log to the next as the daemon carries it across a restart, or handed in and out as a state file;
in-process (main) except where the process is the point."""

from __future__ import annotations

import json

import pytest

from cmcan.cli import main
from tests.conftest import run_cli
from tests.helpers import sim_frames, write_log

LEAK = {"type": "leakage", "component": "loop", "start_h": 0.2, "extra_lpm": 5.0, "ref_dp_bar": 300}
SPLIT_H = 0.3  # after the leak's low warning (the leak from 0.2 h) and before the log's end (0.4 h)


@pytest.fixture(scope="module")
def life(tmp_path_factory):
    """A 0.4 h log with a leak from 0.2 h, whole, and cut at SPLIT_H into two logs a and b."""
    d = tmp_path_factory.mktemp("life")
    _run, frames = sim_frames("two_set_validation", duration_h=0.4, events=[LEAK])
    whole = write_log(d / "whole.log", frames)
    lines = whole.read_text().splitlines(keepends=True)
    t0 = float(lines[0][1:].split(")")[0])
    cut = next(i for i, ln in enumerate(lines) if float(ln[1:].split(")")[0]) >= t0 + SPLIT_H * 3600.0)
    (d / "a.log").write_text("".join(lines[:cut]))
    (d / "b.log").write_text("".join(lines[cut:]))
    return d


def replay_json(capsys, *args: str) -> dict:
    assert main(["replay", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def levels(warnings):
    return [(w["from"], w["to"]) for w in warnings]


def test_two_logs_are_one_life_whatever_order_they_are_given_in(life, capsys, tmp_path):
    d = life
    whole = replay_json(capsys, str(d / "whole.log"))
    assert ("ok", "low") in levels(whole["warnings"])
    for order, tl in ((("a.log", "b.log"), "ab.csv"), (("b.log", "a.log"), "ba.csv")):
        got = replay_json(capsys, *(str(d / n) for n in order), "--out", str(tmp_path / tl))
        assert [p["log"] for p in got["logs"]] == [str(d / "a.log"), str(d / "b.log")]
        # the warning raised in a goes on through b: not raised again at b's start
        assert levels(got["warnings"]) == levels(whole["warnings"]), got["warnings"]
        assert got["logs"][1]["warnings"] == []
        assert got["totals"]["warning_count"] == whole["totals"]["warning_count"] == 1
    assert (tmp_path / "ab.csv").read_bytes() == (tmp_path / "ba.csv").read_bytes()
    rows = (tmp_path / "ab.csv").read_text().splitlines()
    assert len(rows) > 0.38 * 3600 * 10  # one timeline over both logs (ticks at 10 Hz)


def test_b_alone_starts_afresh_and_raises_the_warning_again(life, capsys):
    alone = replay_json(capsys, str(life / "b.log"))
    assert ("ok", "low") in levels(alone["warnings"])


def test_a_state_file_hands_the_life_on_like_one_run(life, capsys, tmp_path):
    d = life
    state = tmp_path / "state.json"
    replay_json(capsys, str(d / "a.log"), "--state-out", str(state))
    doc = json.loads(state.read_text())
    assert doc["format"] == "cmcan-state/1" and doc["warning_count"] == 1 and doc["condition"] == "low"
    b = replay_json(capsys, str(d / "b.log"), "--state-in", str(state))
    both = replay_json(capsys, str(d / "a.log"), str(d / "b.log"))
    assert b["warnings"] == both["logs"][1]["warnings"] == []
    assert b["totals"] == both["totals"]
    # an existing state file is not overwritten without --force
    assert main(["replay", str(d / "a.log"), "--state-out", str(state)]) == 73
    assert "already exists" in capsys.readouterr().err


def test_bad_lives_are_named(life, capsys, tmp_path):
    d = life
    assert main(["replay", str(d / "a.log"), str(d / "a.log")]) == 64
    assert "given twice" in capsys.readouterr().err
    assert main(["replay", str(d / "whole.log"), str(d / "b.log")]) == 65
    err = capsys.readouterr().err
    assert "overlapping logs" in err and "b.log" in err
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "nonsense"}))
    assert main(["replay", str(d / "b.log"), "--state-in", str(bad)]) == 65
    assert "--state-in" in capsys.readouterr().err
    assert main(["replay", str(d / "b.log"), "--state-in", str(tmp_path / "none.json")]) == 66
    assert main(["replay", str(d / "b.log"), str(tmp_path / "gone.log")]) == 66
    assert "gone.log: log file not found" in capsys.readouterr().err


def test_a_week_between_two_logs_starts_the_second_afresh(life, capsys, tmp_path):
    d = life
    late = tmp_path / "late.log"
    shift = 200 * 3600.0
    out = []
    for ln in (d / "b.log").read_text().splitlines(keepends=True):
        t, rest = ln[1:].split(")", 1)
        out.append(f"({float(t) + shift:.6f}){rest}")
    late.write_text("".join(out))
    assert main(["replay", str(d / "a.log"), str(late), "--json"]) == 0
    out = capsys.readouterr()
    got = json.loads(out.out)
    assert "late.log: the state starts afresh: 200.0 h after" in out.err
    assert ("ok", "low") in levels(got["logs"][1]["warnings"])


def test_the_command_line_takes_several_logs(life):
    r = run_cli("replay", str(life / "a.log"), str(life / "b.log"))
    assert r.returncode == 0, r.stderr
    assert r.stdout.count("frames (") == 2 and "a.log" in r.stdout and "b.log" in r.stdout
