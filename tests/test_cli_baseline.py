"""``cmcan baseline``: status and show read the state, reset writes it with no daemon and goes through
the running daemon otherwise (one writer), bad use named with its exit code."""

from __future__ import annotations

import json
import signal

from tests.conftest import run_cli
from tests.daemon_proc import DaemonProc, virtual_config

BASELINE = {"enabled": True, "coverage_pct": 20, "min_points": 40, "min_hours": 0.02}


def _history(tmp_path):
    return json.loads((tmp_path / "state" / "state.json").read_text())["baseline"]["history"]


def test_status_reset_and_show_without_a_daemon(tmp_path):
    cfg = virtual_config(tmp_path, baseline=BASELINE)
    r = run_cli("baseline", "status", "--config", str(cfg))
    assert r.returncode == 0, r.stderr
    assert "learning" in r.stdout
    r = run_cli("baseline", "reset", "--config", str(cfg), "--reason", "pump replaced")
    assert r.returncode == 0, r.stderr
    (old,) = _history(tmp_path)
    assert old["reset_reason"] == "pump replaced" and old["reset_at"].endswith("Z")
    r = run_cli("baseline", "status", "--config", str(cfg), "--json")
    st = json.loads(r.stdout)
    assert st["state"] == "learning" and st["earlier_baselines"] == 1 and st["bins"] == 18
    r = run_cli("baseline", "show", "--config", str(cfg))
    assert json.loads(r.stdout)["history"][0]["reset_reason"] == "pump replaced"


def test_reset_goes_through_the_running_daemon(tmp_path):
    cfg = virtual_config(tmp_path, baseline=BASELINE)
    d = DaemonProc(tmp_path, cfg)
    try:
        r = run_cli("baseline", "reset", "--config", str(cfg), "--reason", "motor replaced")
        assert r.returncode == 0, r.stderr
        assert "running daemon" in r.stdout
        assert [h["reset_reason"] for h in _history(tmp_path)] == ["motor replaced"]
        assert not (tmp_path / "state" / "baseline-reset.json").exists()
        assert d.wait_for(lambda: "baseline reset (motor replaced)" in d.stderr())
        d.signal(signal.SIGTERM)
        assert d.wait() == 0
    finally:
        d.close()
    assert [h["reset_reason"] for h in _history(tmp_path)] == ["motor replaced"]  # the daemon's save kept it


def test_bad_use_is_named(tmp_path):
    cfg = virtual_config(tmp_path)  # no baseline section
    r = run_cli("baseline", "status", "--config", str(cfg))
    assert r.returncode == 78 and "baseline.enabled is false" in r.stderr
    cfg = virtual_config(tmp_path, name="b.yaml", baseline=BASELINE)
    r = run_cli("baseline", "reset", "--config", str(cfg), "--reason", "  ")
    assert r.returncode == 64 and "--reason" in r.stderr
    r = run_cli("baseline", "reset", "--config", str(cfg))
    assert r.returncode == 64
    (tmp_path / "state" / "state.json").write_text("{not json")
    r = run_cli("baseline", "status", "--config", str(cfg))
    assert r.returncode == 65 and "state.json" in r.stderr
    r = run_cli("baseline", "reset", "--config", str(cfg), "--reason", "x")
    assert r.returncode == 65 and (tmp_path / "state" / "state.json").read_text() == "{not json"
    bad = virtual_config(tmp_path, name="c.yaml", baseline={**BASELINE, "learning_low_pct": 101})
    r = run_cli("baseline", "status", "--config", str(bad))
    assert r.returncode == 78 and "learning_low_pct" in r.stderr
