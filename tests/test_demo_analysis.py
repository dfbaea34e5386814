"""The demo reads the daemon's warnings off the bus as a telematics unit would: by the numbers the
DBC's signals carry, named by cmcan's vocabulary, so a DBC without value tables reads the same."""

from __future__ import annotations

import re

import cantools

from cmcan import config as cfgmod
from cmcan.can.frame import Frame
from cmcan.demo import analyse
from cmcan.monitor.warnings import Level, Reason
from tests.conftest import ROOT


def _warning_frames(db, cfg, start: float) -> list[Frame]:
    msg = db.get_message_by_name(cfg.outputs.warning.message)
    states = [(0.5, Level.OK, Reason.NONE), (100.0, Level.LOW, Reason.RATIO_LOW), (150.0, Level.OK, Reason.NONE)]
    out = []
    for h, level, reason in states:
        values = {"warning_level": int(level), "warning_reason": int(reason), "time_below_threshold_s": 0}
        data = msg.encode({**values, "warning_count": 1})
        out.append(Frame(start + h * 3600.0, "can0", msg.frame_id, msg.is_extended_frame, False, False, False, data))
    return out


def test_warnings_read_the_same_with_and_without_value_tables(tmp_path):
    cfg = cfgmod.load(None)
    text = (ROOT / "dbc" / "cmcan.dbc").read_text()
    plain = tmp_path / "plain.dbc"
    plain.write_text("\n".join(line for line in text.splitlines() if not re.match(r"\s*VAL_ ", line)) + "\n")
    failures = [{"component": "motor", "kind": "wear", "fail_h": 120.0}]
    results = []
    for path in (ROOT / "dbc" / "cmcan.dbc", plain):
        db = cantools.database.load_file(str(path))
        assert path == plain or db.get_message_by_name(cfg.outputs.warning.message).signals
        transitions, report, checks, _, _ = analyse(_warning_frames(db, cfg, 1e9), db, cfg, 1e9, failures)
        results.append((transitions, report, checks))
    assert results[0] == results[1]
    transitions, report, _ = results[0]
    assert [(t["from"], t["to"], t["reason"]) for t in transitions] == [
        ("ok", "low", "ratio_low"),
        ("low", "ok", "none"),
    ]
    assert report[0]["level"] == "low" and abs(report[0]["lead_h"] - 20.0) < 1e-9


def test_the_demo_says_what_end_of_life_it_counts_to_and_the_default():
    from cmcan import config as cfgmod
    from cmcan.demo import demo_scenario, end_of_life, with_prognosis

    cfg = with_prognosis(cfgmod.load(), demo_scenario(5.0, 30.0))
    eol = end_of_life(cfg)
    assert eol["configured"]["kind"] == "leak_lpm" and eol["configured"]["value"] > 0
    assert "loss of function" in eol["why"] and "field does not know" in eol["why"]
    assert eol["default"] == {"kind": "ratio_pct", "value": 90.0, "high_pct": 110.0}


def test_the_default_end_of_life_is_reached_after_a_repair_not_at_it():
    import numpy as np

    from cmcan.demo import reached_after

    h = np.arange(0.0, 10.0)
    past = np.array([1, 1, 0, 0, 0, 1, 1, 0, 0, 0], dtype=bool)  # past it until a repair at 1 h, again from 5 h
    assert reached_after(h, past, 0.0, 8.0) == 5.0
    assert reached_after(h, past, 5.5, 9.0) is None  # never inside it in the window: not reached anew
    assert reached_after(h, past, 6.0, 9.0) is None  # inside it to the end
    assert reached_after(h, ~past, 1.0, 9.0) == 7.0  # past from the window's start: only after it was inside
