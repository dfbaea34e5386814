"""A machine's logs as one life: the fleet carries the monitor's state from each log to the next in
time order, on Dask, and the result is what the daemon says across restarts on the same logs (its
saved totals read back and handed to the next monitor). Where the state is not carried (a long gap,
overlapping logs, other inputs) the log starts fresh and says why."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest

from cmcan.fleet.chain import MAX_CARRY_GAP_H, Carry, LogEnd, next_carry

STATE = {"format": "cmcan-state/1", "warning_count": 1, "condition": "low"}
END = LogEnd("ab" * 32, "a.log", 1000.0, STATE, ("c", "d", "m"))


def test_the_first_log_starts_fresh_the_next_carries_the_state_of_the_one_before():
    first = next_carry(None, 0.0)
    assert not first.carried and first.state_hash == "" and "first log" in first.note
    c = next_carry(END, 1000.0 + 1200.0)
    assert c.carried and c.state == STATE and c.from_log_hash == END.log_hash and c.inputs == END.inputs
    assert c.note == "carried from a.log (0.33 h between them)"
    assert len(c.state_hash) == 16 and c.state_hash != Carry({**STATE, "warning_count": 2}).state_hash


@pytest.mark.parametrize(
    ("first_t", "why"),
    [
        (1000.0 + MAX_CARRY_GAP_H * 3600.0 + 1.0, "more than 168 h: not carried"),
        (990.0, "overlapping logs"),
        (None, "first frame is unknown"),
    ],
)
def test_where_the_state_is_not_carried(first_t, why):
    c = next_carry(END, first_t)
    assert not c.carried and c.note.startswith("fresh: ") and why in c.note
    assert next_carry(END, 1000.0 + MAX_CARRY_GAP_H * 3600.0).carried  # the limit itself still carries
    assert next_carry(END, 999.5).carried  # a frame's worth of overlap is no overlap


# -- against the daemon, through the command line on Dask -----------------------------------------------

pytest.importorskip("distributed")
pytest.importorskip("duckdb")

from cmcan import config as cfgmod  # noqa: E402
from cmcan.assemble import assemble  # noqa: E402
from cmcan.fleet.query import run_sql  # noqa: E402
from cmcan.monitor.totals import Totals  # noqa: E402
from cmcan.replay import replay_file  # noqa: E402
from tests.conftest import run_cli  # noqa: E402

SHIFT_S = (MAX_CARRY_GAP_H + 32.0) * 3600.0


def shifted(src: Path, dst: Path, by_s: float) -> Path:
    """A copy of a candump log with every timestamp moved by ``by_s`` (another log of another day)."""
    out = []
    for line in src.read_text().splitlines(keepends=True):
        m = re.match(r"\((\d+\.\d+)\)", line)
        out.append(f"({float(m.group(1)) + by_s:.6f}){line[m.end() :]}" if m else line)
    dst.write_text("".join(out))
    return dst


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """One wearing machine, 48 h in six 8 h logs (a warning raised in the fifth is still active at the
    end of the sixth), replayed on Dask with 2 workers; a second machine whose second log starts more
    than a week after its first ends."""
    d = tmp_path_factory.mktemp("chain")
    sim = d / "sim"
    r = run_cli(
        *("simulate", "fleet", "--machines", "1", "--hours", "48", "--log-hours", "8"),
        *("--degrading-share", "1", "--seed", "5", "--out", str(sim), "--json"),
    )
    assert r.returncode == 0, r.stderr
    with open(sim / "manifest.csv", newline="") as f:
        rows = list(csv.reader(f))[1:]
    logs = [sim / row[1] for row in rows]
    late = shifted(logs[1], sim / "logs" / "m001" / "late.log", SHIFT_S)
    with open(sim / "chains.csv", "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(("machine", "log", "config", "model"))
        for row in rows:
            w.writerow(row)
        w.writerow(("m002", rows[0][1], rows[0][2], rows[0][3]))
        w.writerow(("m002", late.relative_to(sim).as_posix(), rows[0][2], rows[0][3]))
    # m002's first log is m001's first: one content, one machine; so m002 gets a copy of it
    copy = sim / "logs" / "m001" / "copy.log"
    copy.write_bytes(logs[0].read_bytes() + b"\n")
    text = (sim / "chains.csv").read_text().replace(f"m002,{rows[0][1]},", f"m002,{copy.relative_to(sim)},")
    (sim / "chains.csv").write_text(text)
    ds = d / "ds"
    r = run_cli("fleet", "replay", str(sim / "chains.csv"), "--out", str(ds), "--workers", "2", "--json")
    assert r.returncode == 0, r.stderr
    return {"sim": sim, "logs": logs, "ds": ds, "cfg": sim / rows[0][2], "model": sim / rows[0][3]}


def daemon_across_restarts(cfg_path: Path, model: Path, logs: list[Path]) -> list[dict]:
    """What the daemon keeps and says on these logs, one after another, stopped and started between
    them: its totals saved to JSON (as the state file holds them), read back, and handed to the next
    monitor; the streaming engine feeds frame by frame as the daemon's receive loop does."""
    cfg = cfgmod.load(cfg_path)
    saved = None
    out = []
    for log in logs:
        totals = Totals.from_dict(json.loads(saved)) if saved else None
        mon = assemble(cfg, model, totals).monitor
        n_before = len(mon.totals.history) if totals else 0
        res = replay_file(log, mon, engine="streaming")
        state = mon.save_totals().to_dict()
        saved = json.dumps(state)
        out.append({"state": {**state, "history": []}, "events": res.warnings[n_before:], "summary": res})
    return out


@pytest.mark.slow
def test_the_carried_state_is_the_daemons_across_restarts(chain):
    daemon = daemon_across_restarts(chain["cfg"], chain["model"], chain["logs"])
    _, rows = run_sql(
        chain["ds"],
        "SELECT log_name, state_in, state_out, log_hash, warnings_low, final_level, time_low_h FROM logs "
        "WHERE machine = 'm001' ORDER BY first_time_s",
    )
    assert [r[0] for r in rows] == [p.name for p in chain["logs"]]
    assert [r[1] for r in rows] == ["fresh"] + ["carried"] * 5
    for (name, _state_in, state_out, log_hash, n_low, final, _low_h), want in zip(rows, daemon, strict=True):
        got = json.loads(state_out)
        exact = {k: v for k, v in got.items() if k not in ("time_in_level_s", "evaluated_s")}
        assert exact == {k: v for k, v in want["state"].items() if k not in ("time_in_level_s", "evaluated_s")}, name
        for k, v in want["state"]["time_in_level_s"].items():
            assert got["time_in_level_s"][k] == pytest.approx(v, abs=1e-6), (name, k)
        assert got["evaluated_s"] == pytest.approx(want["state"]["evaluated_s"], abs=1e-6)
        _, ev = run_sql(
            chain["ds"],
            f"SELECT time_s, from_level, to_level, reason FROM events WHERE log_hash = '{log_hash}' ORDER BY time_s",
        )
        assert ev == [(e["t_s"], e["from"], e["to"], e["reason"]) for e in want["events"]], name
        assert final == want["summary"].snapshot["level"]
        assert n_low == sum(e["to"] == "low" for e in want["events"])
    # the episode: raised once in the fifth log, still active through the sixth (a fresh start there
    # would have cleared it and raised it again)
    assert [r[4] for r in rows] == [0, 0, 0, 0, 1, 0] and rows[-1][5] == "low" and rows[-1][6] > 0
    fresh = daemon_across_restarts(chain["cfg"], chain["model"], chain["logs"][-1:])[0]
    assert fresh["summary"].snapshot["level"] != "low" or fresh["events"] != []


@pytest.mark.slow
def test_a_long_gap_starts_the_next_log_fresh_and_says_why(chain):
    _, rows = run_sql(
        chain["ds"],
        "SELECT log_name, state_in, state_note, carried_from FROM logs WHERE machine = 'm002' ORDER BY first_time_s",
    )
    assert [(r[0], r[1]) for r in rows] == [("copy.log", "fresh"), ("late.log", "fresh")]
    assert "more than 168 h: not carried" in rows[1][2] and rows[1][3] is None
