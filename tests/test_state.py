"""The state directory (issue 17, items 5 to 7): every field of a state file checked, ``cmcan check
--state`` reads and changes nothing, one daemon per directory (a lock; the second exits 75)."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.cli.errors import EX_DATAERR, EX_IOERR, EX_TEMPFAIL
from cmcan.errors import CmcanError, Kind
from cmcan.monitor.totals import StateError, Totals
from cmcan.service.statefile import LOCK_FILE, StateAccessError, StateLock, StateStore
from tests.conftest import ROOT, run_cli
from tests.daemon_proc import DaemonProc, virtual_config

EX_NOPERM = 77  # sysexits(3)


def good() -> dict:
    t = Totals(warning_count=2, fault_count=1, evaluated_s=3600.5)
    t.time_in_level_s = {"ok": 3000.0, "low": 500.0, "high": 0.0, "fault": 100.5}
    t.history = [{"t_s": 1767225600.0, "from": "ok", "to": "low", "reason": "ratio_low", "ratio_filt_pct": 97.8}]
    t.condition, t.filter_ratios, t.filter_leaks = "low", [97.8, 97.9], [1.0, 1.1]
    return t.to_dict()


def edit(path: str, value):
    def apply(d: dict) -> dict:
        node = d
        keys = path.split(".")
        for k in keys[:-1]:
            node = node[int(k)] if isinstance(node, list) else node[k]
        last = keys[-1]
        if value is KeyError:
            del node[last]
        else:
            node[int(last) if isinstance(node, list) else last] = value
        return d

    return apply


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (edit("warning_count", float("nan")), "warning_count"),
        (edit("warning_count", -1), "warning_count"),
        (edit("warning_count", 1.5), "warning_count"),
        (edit("warning_count", "3"), "warning_count"),
        (edit("fault_count", True), "fault_count"),
        (edit("evaluated_s", -5.0), "evaluated_s"),
        (edit("evaluated_s", float("inf")), "evaluated_s"),
        (edit("time_in_level_s.low", float("nan")), "time_in_level_s.low"),
        (edit("time_in_level_s.low", KeyError), "time_in_level_s"),
        (edit("time_in_level_s.warm", 1.0), "time_in_level_s"),
        (edit("history", {"t_s": 1}), "history"),
        (edit("history.0.t_s", float("nan")), "history[0].t_s"),
        (edit("history.0.to", "panic"), "history[0].to"),
        (edit("history.0.reason", 4), "history[0].reason"),
        (edit("history.0.ratio_filt_pct", float("-inf")), "history[0].ratio_filt_pct"),
        (edit("condition", "fault"), "condition"),
        (edit("filter_ratios.1", float("nan")), "filter_ratios[1]"),
        (edit("filter_leaks", [1.0]), "differ in length"),
        (edit("filter_leaks", KeyError), "filter_leaks"),
    ],
)
def test_a_state_document_with_a_bad_field_is_refused_naming_it(change, field):
    with pytest.raises(StateError, match=field.replace("[", r"\[").replace("]", r"\]")):
        Totals.from_dict(change(good()))


@settings(max_examples=100, deadline=None)
@given(
    counts=st.tuples(st.integers(0, 10**9), st.integers(0, 10**9)),
    times=st.lists(st.floats(0, 1e9), min_size=5, max_size=5),
    ratios=st.lists(st.tuples(st.floats(0, 200), st.floats(-50, 50)), max_size=50),
    condition=st.sampled_from(["ok", "low", "high"]),
)
def test_what_is_saved_reads_back_the_same(counts, times, ratios, condition):
    t = Totals(warning_count=counts[0], fault_count=counts[1], evaluated_s=times[0])
    t.time_in_level_s = dict(zip(("ok", "low", "high", "fault"), times[1:], strict=True))
    t.condition = condition
    t.filter_ratios = [r for r, _ in ratios]
    t.filter_leaks = [x for _, x in ratios]
    assert Totals.from_dict(json.loads(json.dumps(t.to_dict()))) == t


def test_nan_in_the_file_is_refused_by_the_reader_and_kept_aside_by_the_daemon(tmp_path, caplog):
    store = StateStore(tmp_path)
    store.path.write_text(json.dumps(good()).replace('"warning_count": 2', '"warning_count": NaN'))
    before = store.path.read_bytes()
    with pytest.raises(StateError, match=r"state.json: .*NaN"):
        store.read()
    assert store.path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]
    assert store.load() == Totals()  # the daemon: a fresh start, the file kept aside, not lost
    assert (tmp_path / "state.json.corrupt-1").read_bytes() == before and not store.path.exists()
    assert "kept as" in caplog.text


# -- cmcan check --state: read only ------------------------------------------------------------------


@pytest.mark.parametrize("content", [b"{ half a docu", json.dumps({**good(), "fault_count": -3}).encode()])
def test_check_state_names_a_corrupt_file_and_changes_nothing(tmp_path, content):
    cfg = virtual_config(tmp_path)
    state = tmp_path / "state"
    (state / "state.json").write_bytes(content)
    res = run_cli("check", "--config", str(cfg), "--state")
    assert res.returncode == EX_DATAERR, res.stderr
    assert "state.json" in res.stderr and "cmcan run would keep it aside" in res.stderr
    assert sorted(p.name for p in state.iterdir()) == ["state.json"]
    assert (state / "state.json").read_bytes() == content


def test_check_state_reports_a_good_file(tmp_path):
    cfg = virtual_config(tmp_path)
    (tmp_path / "state" / "state.json").write_text(json.dumps(good()))
    res = run_cli("check", "--config", str(cfg), "--state", "--json")
    assert res.returncode == 0, res.stderr
    st_ = json.loads(res.stdout)["state"]
    assert st_["warning_count"] == 2 and st_["condition"] == "low" and st_["locked_by_pid"] is None
    assert sorted(p.name for p in (tmp_path / "state").iterdir()) == ["state.json"]


# -- a state file that is there but cannot be read: no corruption, the start stops -------------------

# The operating system refusing the state file as a non-root user meets it (root reads any file whatever
# its mode, and an EIO needs a failing disk): EACCES/EPERM where the kernel reports them, at the open;
# EIO at the read; through os.open/os.read and open() alike. Only for that file; every other call goes
# to the real functions.
_REFUSING = """
import builtins, errno, io, os, sys


class _FailingFile(io.RawIOBase):
    def __init__(self, code):
        self.code = code

    def readable(self):
        return True

    def readinto(self, b):
        raise OSError(self.code, os.strerror(self.code))


def fakes(target, name):
    # replacements for os.open, os.read and open (builtins and io) that refuse target
    target, code = os.path.realpath(target), getattr(errno, name)
    real_open, real_read, real_io_open, fds = os.open, os.read, io.open, set()

    def is_target(path):
        return isinstance(path, (str, os.PathLike)) and os.path.realpath(path) == target

    def refusing_open(path, flags, *args, **kwargs):
        if is_target(path):
            if code != errno.EIO:
                raise PermissionError(code, os.strerror(code), os.fspath(path))
            fd = real_open(path, flags, *args, **kwargs)
            fds.add(fd)
            return fd
        return real_open(path, flags, *args, **kwargs)

    def refusing_read(fd, n):
        if fd in fds:
            raise OSError(code, os.strerror(code))
        return real_read(fd, n)

    def refusing_io_open(file, mode="r", *args, **kwargs):
        if is_target(file) and "r" in mode:
            if code != errno.EIO:
                raise PermissionError(code, os.strerror(code), os.fspath(file))
            return io.BufferedReader(_FailingFile(code))
        return real_io_open(file, mode, *args, **kwargs)

    return {(os, "open"): refusing_open, (os, "read"): refusing_read, (io, "open"): refusing_io_open,
            (builtins, "open"): refusing_io_open}


if __name__ == "__main__":
    for (module, attr), fake in fakes(sys.argv[1], sys.argv[2]).items():
        setattr(module, attr, fake)
    from cmcan.cli import main

    sys.exit(main(sys.argv[3:]))
"""
_FAKES: dict = {}
exec(_REFUSING, _FAKES)

REFUSALS = [("EACCES", EX_NOPERM, Kind.NO_PERMISSION), ("EPERM", EX_NOPERM, Kind.NO_PERMISSION)]
REFUSALS.append(("EIO", EX_IOERR, Kind.IO_ERROR))


def run_refused(tmp_path, target, name: str, *args: str):
    """The real command line in a subprocess whose os.open/os.read refuse ``target`` with ``name``."""
    script = tmp_path / "refusing.py"
    script.write_text(_REFUSING)
    return subprocess.run(
        [sys.executable, str(script), str(target), name, *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,  # it stops at once; a daemon that started anyway runs until this
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )


def listing(d) -> dict[str, bytes]:
    """What the folder holds (the daemon's lock file aside: taking the lock is no change)."""
    return {p.name: p.read_bytes() if p.is_file() else b"" for p in sorted(d.iterdir()) if p.name != LOCK_FILE}


@pytest.mark.parametrize(("name", "code", "kind"), REFUSALS)
def test_a_state_file_that_cannot_be_read_is_no_corruption_and_nothing_changes(tmp_path, monkeypatch, name, code, kind):
    store = StateStore(tmp_path)
    store.path.write_text(json.dumps(good()))
    before = listing(tmp_path)
    for (module, attr), fake in _FAKES["fakes"](store.path, name).items():
        monkeypatch.setattr(module, attr, fake)
    for how in (store.read, store.load):  # cmcan check and the daemon alike
        with pytest.raises(StateAccessError) as exc:
            how()
        assert exc.value.kind is kind and not isinstance(exc.value, StateError)
        assert str(store.path) in str(exc.value) and os.strerror(getattr(errno, name)) in str(exc.value)
    monkeypatch.undo()
    assert listing(tmp_path) == before  # not kept aside, not overwritten
    assert store.load() == Totals.from_dict(good())  # readable again: the history is all there


@pytest.mark.parametrize(("name", "code", "kind"), REFUSALS)
def test_the_daemon_stops_on_a_state_file_it_cannot_read_with_a_sysexits_code(tmp_path, name, code, kind):
    """The review's case (a backup restored as root the service user cannot read; a disk error): one
    line naming the file and the OS error, 77 or 74, the file as it was, no ``state.json.corrupt-N``."""
    cfg = virtual_config(tmp_path)
    state = tmp_path / "state"
    (state / "state.json").write_text(json.dumps(good()))
    before = listing(state)
    res = run_refused(tmp_path, state / "state.json", name, "run", "--config", str(cfg))
    assert res.returncode == code, res.stderr
    err = [line for line in res.stderr.splitlines() if "state.json" in line]
    assert len(err) == 1 and os.strerror(getattr(errno, name)) in err[0], res.stderr
    assert "Traceback" not in res.stderr and "kept as" not in res.stderr and "fresh totals" not in res.stderr
    assert listing(state) == before and not list(state.glob("state.json.corrupt-*"))

    check = run_refused(tmp_path, state / "state.json", name, "check", "--config", str(cfg), "--state", "--json")
    doc = json.loads(check.stdout)
    assert check.returncode == code and doc["exit_code"] == code, check.stderr
    assert str(state / "state.json") in doc["error"] and "keep it aside" not in doc["error"]
    assert listing(state) == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads a file whatever its mode")
def test_a_state_file_without_read_permission_exits_77(tmp_path):
    cfg = virtual_config(tmp_path)
    path = tmp_path / "state" / "state.json"
    path.write_text(json.dumps(good()))
    path.chmod(0)
    try:
        res = run_cli("check", "--config", str(cfg), "--state")
        assert res.returncode == EX_NOPERM and f"{path}: cannot read the state file" in res.stderr, res.stderr
    finally:
        path.chmod(0o640)
    assert sorted(p.name for p in path.parent.iterdir()) == ["state.json"]


@pytest.mark.parametrize(
    "content", [b"\xff\xfe not utf-8", b"{ half a docu", b"[1, 2]", json.dumps({**good(), "fault_count": -3}).encode()]
)
def test_a_state_file_with_bad_content_is_still_kept_aside(tmp_path, content):
    store = StateStore(tmp_path)
    store.path.write_bytes(content)
    with pytest.raises(StateError):
        store.read()
    assert store.load() == Totals()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json.corrupt-1"]
    assert (tmp_path / "state.json.corrupt-1").read_bytes() == content


@pytest.mark.parametrize("make", [os.mkfifo, os.mkdir], ids=["fifo", "folder"])
def test_a_state_path_that_is_no_regular_file_is_kept_aside_without_hanging(tmp_path, make):
    store = StateStore(tmp_path)
    make(store.path)
    with pytest.raises(StateError, match=r"state\.json: not a regular file"):
        store.read()
    assert store.load() == Totals()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json.corrupt-1"]


# -- the lock ----------------------------------------------------------------------------------------


def test_the_lock_is_exclusive_names_its_holder_and_goes_with_it(tmp_path):
    a = StateLock(tmp_path).acquire()
    with pytest.raises(CmcanError, match=rf"{LOCK_FILE}: the state directory is in use .*pid \d+") as exc:
        StateLock(tmp_path).acquire()
    assert exc.value.kind == Kind.TEMPFAIL
    assert StateLock(tmp_path).holder() is not None
    a.release()
    assert StateLock(tmp_path).holder() is None
    StateLock(tmp_path).acquire().release()  # the file left behind blocks nobody


def test_a_second_daemon_on_the_same_state_directory_exits_75_naming_the_lock(tmp_path):
    cfg = virtual_config(tmp_path)
    first = DaemonProc(tmp_path, cfg, "first")
    try:
        res = run_cli("run", "--config", str(cfg), timeout=120)
        assert res.returncode == EX_TEMPFAIL, res.stderr
        assert f"{tmp_path / 'state' / LOCK_FILE}" in res.stderr and f"pid {first.proc.pid}" in res.stderr
        check = run_cli("check", "--config", str(cfg), "--state", "--json")
        assert json.loads(check.stdout)["state"]["locked_by_pid"] == first.proc.pid
        assert first.proc.poll() is None
    finally:
        first.signal(signal.SIGKILL)  # no clean stop: the kernel still drops the lock
        first.wait()
    again = DaemonProc(tmp_path, cfg, "again")
    again.signal(signal.SIGTERM)
    assert again.wait() == 0, again.stderr()


def test_a_level_changes_run_time_is_checked_and_may_be_absent():
    entry = {"t_s": 10.0, "from": "ok", "to": "low", "reason": "ratio_low", "ratio_filt_pct": 97.0}
    base = Totals().to_dict()
    assert Totals.from_dict({**base, "history": [entry]}).history == [entry]  # a state of an older version
    assert Totals.from_dict({**base, "history": [{**entry, "t_run_s": 12.0}]}).history[0]["t_run_s"] == 12.0
    with pytest.raises(StateError, match=r"history\[0\].t_run_s': expected a finite time"):
        Totals.from_dict({**base, "history": [{**entry, "t_run_s": "garbage"}]})
