"""What an operator's gateway sees of the command line: log priorities in the journal, no onnxruntime
usage records, and an extra that is missing named before a long run, not after it."""

from __future__ import annotations

import logging
import os
import subprocess
import sys

from cmcan.cli.errors import EX_CONFIG, EX_UNAVAILABLE
from cmcan.cli.journal import stderr_handler, syslog_priority
from tests.conftest import ROOT, run_cli


def _with_journal_stream(tmp_path, *args: str) -> tuple[int, str]:
    """Run cmcan with stderr on a file that JOURNAL_STREAM names, as systemd sets it up."""
    err = tmp_path / "stderr.txt"
    with open(err, "w") as f:
        st = os.fstat(f.fileno())
        env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        res = subprocess.run(
            [sys.executable, "-m", "cmcan", *args], stdout=subprocess.DEVNULL, stderr=f, env=env, cwd=ROOT, timeout=120
        )
    return res.returncode, err.read_text()


def test_log_lines_carry_their_syslog_priority_where_stderr_is_the_journal(tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("bus: {bitrate: fast}\n")
    code, err = _with_journal_stream(tmp_path, "check", "--config", str(cfg))
    assert code == EX_CONFIG
    assert err.startswith("<3>cmcan check: ") and "bitrate" in err, err
    # the same command on a plain stderr (a terminal, a file): no prefix
    res = run_cli("check", "--config", str(cfg), env={"JOURNAL_STREAM": "1:2"})
    assert res.returncode == EX_CONFIG and res.stderr.startswith("cmcan check: "), res.stderr


def test_each_log_line_carries_its_level_as_a_priority_in_the_journal(tmp_path, monkeypatch):
    path = tmp_path / "journal"
    with open(path, "w") as stream:
        st = os.fstat(stream.fileno())
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
        log = logging.getLogger("cmcan.test.journal")
        log.propagate = False
        log.addHandler(stderr_handler("%(levelname)s %(name)s: %(message)s", stream))
        try:
            log.warning("the receive buffer is %d bytes", 212992)
            log.error("no state")
            log.critical("gone")
        finally:
            log.handlers.clear()
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino + 1}")  # another stream: no prefix
        log.addHandler(stderr_handler("%(levelname)s %(name)s: %(message)s", stream))
        try:
            log.warning("plain")
        finally:
            log.handlers.clear()
    assert path.read_text().splitlines() == [
        "<4>WARNING cmcan.test.journal: the receive buffer is 212992 bytes",
        "<3>ERROR cmcan.test.journal: no state",
        "<2>CRITICAL cmcan.test.journal: gone",
        "WARNING cmcan.test.journal: plain",
    ]


def test_syslog_priorities_of_the_levels():
    assert [syslog_priority(lv) for lv in (logging.CRITICAL, logging.ERROR, logging.WARNING, logging.INFO)] == [
        2,
        3,
        4,
        6,
    ]
    assert syslog_priority(logging.DEBUG) == 7 and syslog_priority(logging.WARNING + 5) == 4


def test_loading_a_model_leaves_no_onnxruntime_usage_records(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    env = {"HOME": str(home), "XDG_CACHE_HOME": ""}
    env = {k: v for k, v in {**os.environ, **env}.items() if k != "ORT_DISABLE_TELEMETRY"}
    res = subprocess.run(
        [sys.executable, "-m", "cmcan", "check"], capture_output=True, text=True, env=env, cwd=ROOT, timeout=120
    )
    assert res.returncode == 0, res.stderr
    assert "telemetry" not in res.stderr.lower()
    assert not [p for p in home.rglob("*") if p.is_file()], list(home.rglob("*"))


def test_demo_without_the_plot_extra_says_so_before_running(tmp_path):
    block = tmp_path / "block"
    block.mkdir()
    (block / "matplotlib.py").write_text("raise ImportError('matplotlib is not on a gateway')\n")
    out = tmp_path / "demo"
    res = run_cli("demo", "--out-dir", str(out), env={"PYTHONPATH": str(block)}, timeout=60)
    assert res.returncode == EX_UNAVAILABLE, res.stderr
    assert "pip install 'cmcan[plot]'" in res.stderr and "--no-plot" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not out.exists()  # nothing made before the refusal


def test_a_command_runs_openblas_on_one_thread_unless_the_caller_chose(monkeypatch):
    from cmcan.cli import one_blas_thread

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    one_blas_thread()
    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "3")
    one_blas_thread()
    assert os.environ["OPENBLAS_NUM_THREADS"] == "3"
