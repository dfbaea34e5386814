"""The state directory as untrusted input (issue 38, files): a crafted or damaged ``state.json`` is
kept aside as ``state.json.corrupt-N`` with a journal line naming the file, the field and what was
expected, only the damaged part starts afresh, and the monitor the daemon builds from what is left
runs; the reading is bounded (size, depth, numbers); files are written through new temporary files
that follow no link, owned by the state directory's owner when root writes them; request, node and
lock files are opened without following links or blocking."""

from __future__ import annotations

import errno
import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cmcan.errors import CmcanError, Kind
from cmcan.monitor.totals import StateError, Totals
from cmcan.service.statefile import (
    BASELINE_REQUEST_FILE,
    LOCK_FILE,
    MAX_STATE_BYTES,
    NODE_FILE,
    PARTS,
    DamagedState,
    StateLock,
    StateStore,
    done_baseline_request,
    examine,
    read_baseline_request,
    read_node_status,
    takes_reload,
    write_baseline_request,
    write_node_status,
)
from tests import statefile_support as sf
from tests.conftest import run_cli
from tests.daemon_proc import DaemonProc

SECRET = "CANARY-38-secret"


def raw(doc: dict, **literals: str) -> bytes:
    """``doc`` as JSON with ``"@name@"`` strings replaced by literal number text (what json cannot write)."""
    text = json.dumps(doc, allow_nan=True)
    for name, lit in literals.items():
        text = text.replace(f'"@{name}@"', lit)
    return text.encode()


def doc_with(edit) -> dict:
    d = sf.good_doc()
    edit(d)
    return d


def _hours_back(d: dict) -> None:
    p = d["prognosis"]["points"]
    p[5][0], p[6][0] = p[6][0], p[5][0]


# name -> (the file's bytes, the damaged part, what the message says: the field and what was expected)
CASES = {
    "an integer above 1e308": (
        raw(doc_with(lambda d: d.update(evaluated_s="@big@")), big="1" + "0" * 309),
        "totals",
        "field 'evaluated_s': 1000000000000000... (310 characters) is not a number a state file holds",
    ),
    "n above int64": (
        raw(doc_with(lambda d: d["baseline"]["n"].__setitem__(0, 2**63))),
        "baseline",
        "field 'baseline.n[0]': 9223372036854775808 is not a number",
    ),
    "100,000-deep nesting": (
        b'{"format": "cmcan-state/1", "x": ' + b"[" * 100_000 + b"]" * 100_000 + b"}",
        "file",
        "nested deeper than 64 levels",
    ),
    "70-deep nesting in the baseline's history": (
        raw(doc_with(lambda d: d["baseline"].update(history=[{"x": json.loads("[" * 70 + "]" * 70)}]))),
        "baseline",
        "nested deeper than 64 levels",
    ),
    "a prognosis leak of 1e300": (
        raw(doc_with(lambda d: d["prognosis"]["points"][3].__setitem__(1, 1e300))),
        "prognosis",
        "field 'prognosis.points[3][1]': 1e+300 is not a number",
    ),
    "a prognosis leak of 1e7 l/min": (
        raw(doc_with(lambda d: d["prognosis"]["points"][3].__setitem__(1, 1e7))),
        "prognosis",
        "field 'prognosis.points[3]': expected [hour 0..1e6, leak +-1e5 l/min",
    ),
    "a baseline one number short": (
        raw(doc_with(lambda d: d["baseline"]["sy"].pop())),
        "baseline",
        "field 'baseline.sy': expected 18 entries (one per bin of its envelope), got 17",
    ),
    "a baseline row one number short": (
        raw(doc_with(lambda d: d["baseline"]["sxx"][2].pop())),
        "baseline",
        "field 'baseline.sxx[2]': expected 9 finite numbers",
    ),
    "a prognosis hour that does not increase": (
        raw(doc_with(_hours_back)),
        "prognosis",
        "field 'prognosis.points[6]': hour 2.75 after 3.25: the hours must increase",
    ),
    "NaN in the filter": (
        raw(doc_with(lambda d: d["filter_ratios"].__setitem__(0, float("nan")))),
        "totals",
        "field 'filter_ratios[0]': NaN is not a number a state file holds",
    ),
    "1e400 as a time": (
        raw(doc_with(lambda d: d["time_in_level_s"].update(ok="@inf@")), inf="1e400"),
        "totals",
        "field 'time_in_level_s.ok': 1e400 is not a number",
    ),
    "a mandatory field missing": (
        raw(doc_with(lambda d: d.pop("warning_count"))),
        "totals",
        "field 'warning_count' missing",
    ),
    "DTC counts of the wrong type": (
        raw(doc_with(lambda d: d.update(dtc_occurrences=[1, 2]))),
        "dtc",
        "dtc_occurrences must be a mapping",
    ),
    "a learned count that is a boolean": (
        raw(doc_with(lambda d: d["baseline"].update(learned_ticks=True))),
        "baseline",
        "field 'baseline.learned_ticks': expected a count, got True",
    ),
    "bin edges that do not rise": (
        raw(doc_with(lambda d: d["baseline"]["envelope"]["edges"][1].reverse())),
        "baseline",
        "field 'baseline.envelope': expected rising bin edges",
    ),
    "another format": (
        raw(doc_with(lambda d: d.update(format="cmcan-state/9"))),
        "file",
        "not a cmcan-state/1 document",
    ),
    "not JSON": (b"{ half a docu", "file", "not a readable state file: Expecting"),
}


def files_but_lock(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name != LOCK_FILE)


@pytest.mark.parametrize("name", list(CASES))
def test_a_damaged_state_is_kept_aside_and_only_its_damaged_part_starts_afresh(tmp_path, caplog, name):
    content, part, said = CASES[name]
    cfg = sf.config_file(tmp_path)
    store = StateStore(tmp_path / "state")
    store.path.write_bytes(content)
    with pytest.raises(DamagedState) as exc:  # cmcan check --state, cmcan baseline: refused
        store.read()
    assert said in str(exc.value) and str(store.path) in str(exc.value)
    assert store.path.read_bytes() == content and files_but_lock(store.dir) == ["state.json"]

    totals = store.load()  # the daemon
    aside = store.dir / "state.json.corrupt-1"
    assert aside.read_bytes() == content
    lines = [m for m in sf.journal(caplog) if str(store.path) in m]
    assert len(lines) == 1 and said in lines[0] and f"kept as {aside}" in lines[0], sf.journal(caplog)
    good = Totals.from_dict(sf.good_doc())
    for p in PARTS:
        fresh = part in (p, "file")
        assert sf.part_of(totals, p) == sf.part_of(Totals() if fresh else good, p), p
    if part == "file":
        assert "starting with fresh totals" in lines[0] and files_but_lock(store.dir) == ["state.json.corrupt-1"]
    else:  # what was kept is on disk at once, and reads back whole
        assert f"starting afresh: {PARTS[part][1]}" in lines[0]
        assert store.read() == totals and files_but_lock(store.dir) == ["state.json", "state.json.corrupt-1"]
    mon = sf.build(cfg, totals)  # the daemon's monitor from what is left: nothing refused twice, it runs
    assert mon.baseline_note is None and mon.prognosis is not None and not mon.prognosis.note
    assert sf.still_up(mon) > 0


def test_a_damaged_clock_alone_restarts_the_clock_and_keeps_the_prognosis_history(tmp_path, caplog):
    store = StateStore(tmp_path)
    d = sf.good_doc()
    d["prognosis"]["clock"] = {"operating_s": -1.0, "last_t_s": None}
    store.path.write_bytes(raw(d))
    totals = store.load()
    assert totals.prognosis is not None and "clock" not in totals.prognosis
    assert totals.prognosis["points"] == d["prognosis"]["points"] and totals.baseline == d["baseline"]
    (line,) = sf.journal(caplog)
    assert "field 'prognosis.clock': expected {operating_s" in line and "operating clock (it goes on" in line
    (tmp_path / "cfg").mkdir()
    mon = sf.build(sf.config_file(tmp_path / "cfg"), totals)
    assert mon.prognosis is not None and not mon.prognosis.note and mon.prognosis.est.state == "imminent"


def test_a_good_state_is_read_whole(tmp_path):
    store = StateStore(tmp_path)
    store.path.write_bytes(raw(sf.good_doc()))
    assert examine(store.path.read_bytes()).damage == ()
    assert store.load() == store.read() == Totals.from_dict(sf.good_doc())
    assert files_but_lock(tmp_path) == ["state.json"]


def test_a_state_saved_before_the_orifice_sums_is_read_whole_and_its_history_goes_on(tmp_path):
    """A gateway upgraded from cmcan-prognosis/2 (the laminar sums only): its state is neither lost
    nor refused; the monitor goes on with its history and estimates as before."""
    d = sf.good_doc()
    d["prognosis"] |= {"format": "cmcan-prognosis/2", "points": [q[:5] for q in d["prognosis"]["points"]]}
    store = StateStore(tmp_path)
    store.path.write_bytes(raw(d))
    assert examine(store.path.read_bytes()).damage == ()
    totals = store.load()
    assert totals.prognosis == d["prognosis"] and files_but_lock(tmp_path) == ["state.json"]
    (tmp_path / "cfg").mkdir()
    mon = sf.build(sf.config_file(tmp_path / "cfg"), totals)
    assert mon.prognosis is not None and not mon.prognosis.note and mon.prognosis.est.state == "imminent"
    assert len(mon.prognosis.history.points) == len(d["prognosis"]["points"])


def test_the_parts_name_every_field_and_the_required_ones_are_totals_own():
    """Every field of a saved state is in one part; the warning totals' fields are the ones
    ``Totals.from_dict`` requires (the later parts may be absent: states of older versions)."""
    fields = [f for fs, _ in PARTS.values() for f in fs]
    assert sorted(fields) == sorted(k for k in Totals().to_dict() if k != "format")
    for f in fields:
        d = sf.good_doc()
        del d[f]
        required = f in PARTS["totals"][0]
        try:
            Totals.from_dict(d)
            assert not required, f
        except StateError:
            assert required, f


@pytest.mark.parametrize(
    "make",
    ["huge", "fifo", "folder", "devzero", "secret"],
)
def test_a_state_path_that_is_no_state_file_is_kept_aside_without_reading_it(tmp_path, caplog, make):
    """A file over 16 MiB, a FIFO, a folder, a link to /dev/zero or to a secret: refused by what it
    is (no hang, no endless read, nothing of the secret in the journal), the thing itself kept aside."""
    store = StateStore(tmp_path / "state")
    store.dir.mkdir()
    secret = tmp_path / "secret.json"
    secret.write_text(json.dumps({"format": SECRET}))
    if make == "huge":
        store.path.write_bytes(b" " * (MAX_STATE_BYTES + 1))
    elif make == "fifo":
        os.mkfifo(store.path)
    elif make == "folder":
        store.path.mkdir()
    else:
        store.path.symlink_to("/dev/zero" if make == "devzero" else secret)
    t0 = time.monotonic()
    with pytest.raises(DamagedState) as exc:
        store.read()
    assert time.monotonic() - t0 < 5.0
    what = {"huge": "larger than 16 MiB", "fifo": "(a FIFO)", "folder": "(a folder)"}.get(make, "(a symbolic link)")
    assert what in str(exc.value) and SECRET not in str(exc.value)
    assert store.load() == Totals()
    assert files_but_lock(store.dir) == ["state.json.corrupt-1"] and what in " ".join(sf.journal(caplog))
    assert SECRET not in caplog.text and secret.read_text() == json.dumps({"format": SECRET})


def test_an_earlier_file_kept_aside_is_never_overwritten(tmp_path):
    store = StateStore(tmp_path)
    (tmp_path / "state.json.corrupt-1").write_text("first")
    (tmp_path / "state.json.corrupt-2").symlink_to(tmp_path / "gone")  # a dangling link counts as taken
    store.path.write_text("{ second")
    assert store.load() == Totals()
    assert (tmp_path / "state.json.corrupt-1").read_text() == "first"
    assert os.readlink(tmp_path / "state.json.corrupt-2") == str(tmp_path / "gone")
    assert (tmp_path / "state.json.corrupt-3").read_text() == "{ second"


def test_a_file_that_cannot_be_kept_aside_stops_the_start_and_is_left_as_it_was(tmp_path, monkeypatch):
    store = StateStore(tmp_path)
    store.path.write_text("{ broken")

    def refuse(src, dst):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(os, "rename", refuse)
    with pytest.raises(CmcanError) as exc:
        store.load()
    assert exc.value.kind is Kind.CANT_CREATE and "cannot keep the damaged state file aside" in str(exc.value)
    assert store.path.read_text() == "{ broken"


def test_what_was_kept_stays_in_memory_when_it_cannot_be_saved_at_once(tmp_path, monkeypatch, caplog):
    import cmcan.service.statefile as statefile

    store = StateStore(tmp_path)
    store.path.write_bytes(raw(doc_with(lambda d: d["baseline"]["sy"].pop())))

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(statefile, "write_atomic", full)
    totals = store.load()
    assert totals.warning_count == sf.good_doc()["warning_count"] and totals.baseline is None
    assert any("cannot save the state kept from" in m for m in sf.journal(caplog))


# -- what the daemon, cmcan check --state and cmcan baseline status do with it ------------------------

BRIEF = [
    "an integer above 1e308",
    "n above int64",
    "100,000-deep nesting",
    "a prognosis leak of 1e300",
    "a baseline one number short",
    "a prognosis hour that does not increase",
]


@pytest.mark.parametrize("name", BRIEF)
def test_check_status_and_run_name_a_crafted_state_and_never_exit_70(tmp_path, name):
    """The review's files: ``check --state`` and ``baseline status`` exit 65 naming the field and
    change nothing; ``cmcan run`` keeps the file aside, says so, reaches READY and stops cleanly (0);
    the next start finds a sound state."""
    content, part, said = CASES[name]
    cfg = sf.config_file(tmp_path)
    state = tmp_path / "state"
    (state / "state.json").write_bytes(content)
    check = run_cli("check", "--config", str(cfg), "--state")
    assert check.returncode == 65 and said in check.stderr, check.stderr
    then = "start with fresh totals" if part == "file" else f"start afresh: {PARTS[part][1]}"
    assert f"cmcan run would keep it aside as state.json.corrupt-N and {then}" in check.stderr
    status = run_cli("baseline", "status", "--config", str(cfg))
    assert status.returncode == 65 and said in status.stderr, status.stderr
    assert files_but_lock(state) == ["state.json"] and (state / "state.json").read_bytes() == content
    for start in range(2):
        d = DaemonProc(tmp_path, cfg, name=f"d{start}")
        try:
            d.signal(15)
            assert d.wait() == 0
        finally:
            d.close()
        err = d.stderr()
        assert "Traceback" not in err and "internal error" not in err
        if start == 0:
            assert said in err and "kept as" in err and str(state / "state.json.corrupt-1") in err, err
        else:
            assert "state.json" not in err, err  # nothing damaged the second time
    assert (state / "state.json.corrupt-1").read_bytes() == content
    assert not list(state.glob("state.json.corrupt-2"))


def test_check_state_says_what_the_monitor_does_not_go_on_with(tmp_path):
    """A sound state whose baseline was learned over another envelope (the configuration changed):
    no damage, but ``check --state`` says the baseline learns afresh, as the daemon's journal does;
    and a request file the daemon will refuse."""
    cfg = sf.config_file(tmp_path)
    d = sf.good_doc()
    d["baseline"]["envelope"]["edges"][2] = [0.0, 50.0, 100.0]
    (tmp_path / "state" / "state.json").write_bytes(raw(d))
    res = run_cli("check", "--config", str(cfg), "--state", "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["state"]["notes"] == ["the configured envelope changed: learning afresh"]
    text = run_cli("check", "--config", str(cfg), "--state")
    assert "state  note: the configured envelope changed: learning afresh" in text.stdout
    os.mkfifo(tmp_path / "state" / BASELINE_REQUEST_FILE)  # a request the daemon will refuse: said, no hang
    res = run_cli("check", "--config", str(cfg), "--state", "--json", timeout=60)
    assert res.returncode == 0, res.stderr
    (_, note) = json.loads(res.stdout)["state"]["notes"]
    assert note.startswith("baseline reset not carried out: unreadable request") and "(a FIFO)" in note


# -- writing: new temporary files, no link followed, the directory's owner ----------------------------


def test_writes_follow_no_link_left_in_the_state_directory(tmp_path):
    """Links at the temporary names earlier versions used and at the files themselves: the victim
    outside is never written; the files are regular, 0640, and no temporary file is left."""
    victim = tmp_path / "victim"
    victim.write_text("untouched")
    d = tmp_path / "state"
    d.mkdir()
    for name in (".state.json.tmp", f"{BASELINE_REQUEST_FILE}.tmp", f".{NODE_FILE}.tmp", "state.json", NODE_FILE):
        (d / name).symlink_to(victim)
    StateStore(d).save(Totals(warning_count=3))
    write_baseline_request(d, "pump replaced", "2026-01-01T00:00:00Z")
    write_node_status(d, {"state": "claimed", "address": 0x80})
    assert victim.read_text() == "untouched"
    for name in ("state.json", BASELINE_REQUEST_FILE, NODE_FILE):
        st = (d / name).lstat()
        assert stat.S_ISREG(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o640, name
    assert StateStore(d).read().warning_count == 3 and read_node_status(d) == {"state": "claimed", "address": 128}
    assert sorted(p.name for p in d.iterdir() if p.name.endswith(".tmp")) == sorted(
        [".state.json.tmp", f"{BASELINE_REQUEST_FILE}.tmp", f".{NODE_FILE}.tmp"]  # the planted links, as they were
    )


@pytest.mark.skipif(os.geteuid() != 0, reason="only root gives files away")
def test_root_writes_files_the_state_directorys_owner_can_rewrite(tmp_path):
    d = tmp_path / "state"
    d.mkdir()
    os.chown(d, 4242, 4243)
    StateStore(d).save(Totals())
    StateLock(d).acquire().release()
    write_baseline_request(d, "x", "")
    for name in ("state.json", LOCK_FILE, BASELINE_REQUEST_FILE):
        st = (d / name).stat()
        assert (st.st_uid, st.st_gid) == (4242, 4243), name


def test_root_gives_new_files_to_the_directorys_owner_and_no_one_else_does(tmp_path, monkeypatch):
    """The calls made, as any user: as root, each new file to the directory's owner (a lock file that
    is there already is left as it is); as anyone else, nothing."""
    calls = []
    monkeypatch.setattr(os, "fchown", lambda fd, uid, gid: calls.append((uid, gid)))
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    StateStore(tmp_path).save(Totals())
    StateLock(tmp_path).acquire().release()
    assert calls == []
    monkeypatch.setattr(os, "geteuid", lambda: 0)
    StateStore(tmp_path).save(Totals())
    StateLock(tmp_path).acquire().release()
    (tmp_path / LOCK_FILE).unlink()
    StateLock(tmp_path).acquire().release()
    st = tmp_path.stat()
    assert calls == [(st.st_uid, st.st_gid)] * 2


# -- the request, node and lock files -----------------------------------------------------------------


def _request(d: Path, kind: str, secret: Path) -> None:
    p = d / BASELINE_REQUEST_FILE
    if kind == "fifo":
        os.mkfifo(p)
    elif kind == "devzero":
        p.symlink_to("/dev/zero")
    elif kind == "secret":
        p.symlink_to(secret)
    elif kind == "folder":
        p.mkdir()
    elif kind == "huge":
        p.write_text(json.dumps({"reason": "x" * 5000}))
    elif kind == "deep":
        p.write_text("[" * 100_000 + "]" * 100_000)
    elif kind == "list":
        p.write_text("[1, 2]")
    elif kind == "number reason":
        p.write_text('{"reason": 1e999}')
    else:
        p.write_bytes(b"\xff\xfe")


REQUESTS = ["fifo", "devzero", "secret", "folder", "huge", "deep", "list", "number reason", "not utf-8"]


@pytest.mark.parametrize("kind", REQUESTS)
def test_a_request_file_that_is_no_request_is_refused_at_once_and_removed(tmp_path, kind):
    secret = tmp_path / "secret"
    secret.write_text(json.dumps({"reason": SECRET}))
    d = tmp_path / "state"
    d.mkdir()
    _request(d, kind, secret)
    t0 = time.monotonic()
    req = read_baseline_request(d)
    assert time.monotonic() - t0 < 2.0
    assert req is not None and req["bad"] == "1" and str(d / BASELINE_REQUEST_FILE) in req["reason"]
    assert SECRET not in req["reason"]
    done_baseline_request(d)
    assert not os.path.lexists(d / BASELINE_REQUEST_FILE) and secret.exists()


def test_a_request_reason_is_one_journal_line_and_bounded(tmp_path):
    write_baseline_request(tmp_path, "pump\nreplaced\x1b[2J" + "x" * 500, "2026-01-01T00:00:00Z")
    req = read_baseline_request(tmp_path)
    assert req is not None and "bad" not in req
    assert req["reason"].startswith("pump replaced [2J") and len(req["reason"]) == 200
    assert read_baseline_request(tmp_path / "nothing") is None


@pytest.mark.parametrize("kind", ["fifo", "link"])
def test_a_lock_file_that_is_no_file_is_refused_without_hanging_or_following(tmp_path, kind):
    victim = tmp_path / "victim"
    victim.write_text("untouched")
    d = tmp_path / "state"
    d.mkdir()
    if kind == "fifo":
        os.mkfifo(d / LOCK_FILE)
    else:
        (d / LOCK_FILE).symlink_to(victim)
    with pytest.raises(CmcanError, match=LOCK_FILE):
        StateLock(d).acquire()
    assert StateLock(d).holder() is None and victim.read_text() == "untouched"


def test_a_node_file_that_is_no_file_is_none(tmp_path):
    (tmp_path / NODE_FILE).symlink_to("/dev/zero")
    assert read_node_status(tmp_path) is None
    (tmp_path / NODE_FILE).unlink()
    (tmp_path / NODE_FILE).write_text('{"address": 1e999}')
    assert read_node_status(tmp_path) is None


def test_takes_reload_reads_whether_a_process_handles_sighup():
    code = (
        "import signal, sys, time\n"
        "if sys.argv[1] == '1': signal.signal(signal.SIGHUP, lambda *a: None)\n"
        "print('ready', flush=True); time.sleep(30)\n"
    )
    for handles in (False, True):
        p = subprocess.Popen([sys.executable, "-c", code, str(int(handles))], stdout=subprocess.PIPE, text=True)
        try:
            assert p.stdout is not None and p.stdout.readline() == "ready\n"
            assert takes_reload(p.pid) is handles
        finally:
            p.kill()
            p.wait()
    assert takes_reload(p.pid) is None  # gone
