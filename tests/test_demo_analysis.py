"""The demo reads the daemon's warnings off the bus as a telematics unit would: by the numbers the
DBC's signals carry, named by cmcan's vocabulary, so a DBC without value tables reads the same."""

from __future__ import annotations

import re

import cantools

from cmcan import config as cfgmod
from cmcan.demo import analyse
from cmcan.frame import Frame
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
