"""``cmcan baseline``: status and show read the state, reset writes it with no daemon and goes through
the running daemon otherwise (one writer), bad use named with its exit code."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

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


# -- the request file and the daemon's start (issue 38) -------------------------------------------------


@pytest.mark.parametrize("kind", ["fifo", "devzero"])
def test_a_request_that_is_no_file_neither_hangs_nor_stops_the_daemon(tmp_path, kind):
    """A FIFO (a blocking open would hang the loop: SIGTERM ignored, the next start stuck before
    READY) or a link to /dev/zero (an endless read) at baseline-reset.json: refused at the reload and
    at a start, said in the journal, removed; the daemon runs on and stops cleanly."""
    cfg = virtual_config(tmp_path, baseline=BASELINE)
    request = tmp_path / "state" / "baseline-reset.json"

    def plant():
        os.mkfifo(request) if kind == "fifo" else request.symlink_to("/dev/zero")

    said = f"baseline reset not carried out: unreadable request {request} (not a regular file"
    d = DaemonProc(tmp_path, cfg)
    try:
        plant()
        d.signal(signal.SIGHUP)
        assert d.wait_for(lambda: said in d.stderr() and not os.path.lexists(request)), d.stderr()
        t0 = time.monotonic()
        d.signal(signal.SIGTERM)
        assert d.wait() == 0 and time.monotonic() - t0 < 10
    finally:
        d.close()
    plant()
    d = DaemonProc(tmp_path, cfg, name="again")  # READY, not stuck on the request
    try:
        assert said in d.stderr() and not os.path.lexists(request)
        d.signal(signal.SIGTERM)
        assert d.wait() == 0
    finally:
        d.close()


# A stand-in for a daemon between its lock and its signal handlers: it takes the state lock, runs with
# SIGHUP's default action (the end of the process) for a while, then handles SIGHUP and, as the daemon
# does, carries out the request and removes it.
HOLDER = """
import os, signal, sys, time
from cmcan.service.statefile import BASELINE_REQUEST_FILE, StateLock

d, bare_s = sys.argv[1], float(sys.argv[2])
lock = StateLock(d).acquire()
print("locked", flush=True)
time.sleep(bare_s)
got = []
signal.signal(signal.SIGHUP, lambda *a: got.append(1))
print("handlers", flush=True)
deadline = time.monotonic() + 30
while not got and time.monotonic() < deadline:
    time.sleep(0.05)
print("request", open(os.path.join(d, BASELINE_REQUEST_FILE)).read().strip(), flush=True)
os.unlink(os.path.join(d, BASELINE_REQUEST_FILE))
"""


def start_holder(tmp_path, bare_s: float) -> subprocess.Popen:
    p = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(tmp_path / "state"), str(bare_s)], stdout=subprocess.PIPE, text=True
    )
    assert p.stdout is not None and p.stdout.readline() == "locked\n"
    return p


def test_a_reset_waits_for_the_daemons_signal_handlers(tmp_path):
    """A reset that lands between the daemon's lock and its signal handlers: no SIGHUP until the
    daemon handles it (the default action would end it, and systemd takes that for a clean stop)."""
    cfg = virtual_config(tmp_path, baseline=BASELINE)
    holder = start_holder(tmp_path, bare_s=8.0)  # longer than the command takes to start (~3 s)
    try:
        r = run_cli("baseline", "reset", "--config", str(cfg), "--reason", "pump replaced", "--wait", "30")
        out, _ = holder.communicate(timeout=30)
    finally:
        holder.kill()
    assert r.returncode == 0 and f"running daemon (pid {holder.pid})" in r.stdout, r.stderr
    assert holder.returncode == 0, holder.returncode  # not -1: not killed by SIGHUP
    assert out.splitlines()[0] == "handlers" and '"reason": "pump replaced"' in out


def test_a_reset_gives_up_on_a_holder_that_takes_no_reload_and_changes_nothing(tmp_path):
    cfg = virtual_config(tmp_path, baseline=BASELINE)
    holder = start_holder(tmp_path, bare_s=60.0)
    try:
        r = run_cli("baseline", "reset", "--config", str(cfg), "--reason", "x", "--wait", "1")
        assert r.returncode == 75 and "takes no reload request yet" in r.stderr and "cmcan.lock" in r.stderr
        assert holder.poll() is None and not (tmp_path / "state" / "baseline-reset.json").exists()
    finally:
        holder.kill()
        holder.wait()


def test_a_reset_writes_through_no_link_left_in_the_state_directory(tmp_path):
    cfg = virtual_config(tmp_path, baseline=BASELINE)
    victim = tmp_path / "victim"
    victim.write_text("untouched")
    for name in (".state.json.tmp", "baseline-reset.json.tmp"):  # the temporary names of earlier versions
        (tmp_path / "state" / name).symlink_to(victim)
    r = run_cli("baseline", "reset", "--config", str(cfg), "--reason", "pump replaced")
    assert r.returncode == 0, r.stderr
    assert victim.read_text() == "untouched" and [h["reset_reason"] for h in _history(tmp_path)] == ["pump replaced"]


@pytest.mark.skipif(os.geteuid() != 0 or not shutil.which("setpriv"), reason="needs root and setpriv")
def test_a_reset_by_root_with_the_daemon_stopped_leaves_the_daemon_able_to_start(tmp_path):
    """``cmcan baseline reset`` as root, no daemon running: state.json and the lock it made belong to
    the state directory's owner, and the daemon started as that user comes up (it exited 77 before)."""
    uid, gid = 4242, 4243
    top = Path(tempfile.mkdtemp(prefix="cmcan-root-reset-"))  # a folder the daemon's user can reach
    try:
        top.chmod(0o755)
        cfg = virtual_config(top, baseline=BASELINE)
        os.chown(top / "state", uid, gid)
        r = run_cli("baseline", "reset", "--config", str(cfg), "--reason", "pump replaced")
        assert r.returncode == 0, r.stderr
        for name in ("state.json", "cmcan.lock"):
            st = (top / "state" / name).stat()
            assert (st.st_uid, st.st_gid) == (uid, gid), name
        launcher = ["setpriv", f"--reuid={uid}", f"--regid={gid}", "--clear-groups", sys.executable, "-m", "cmcan"]
        if subprocess.run([*launcher[:-2], "-c", "import cmcan"], capture_output=True).returncode != 0:
            pytest.skip("the daemon's user cannot reach this Python and its cmcan (a private folder above it)")
        old = os.umask(0)  # the notify socket: the daemon's user sends READY to it
        try:
            d = DaemonProc(top, cfg, launcher=launcher)
        finally:
            os.umask(old)
        try:
            d.signal(signal.SIGTERM)
            assert d.wait() == 0, d.stderr()
        finally:
            d.close()
        assert [h["reset_reason"] for h in _history(top)] == ["pump replaced"]
    finally:
        shutil.rmtree(top, ignore_errors=True)
