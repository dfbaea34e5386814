"""The compiled-DBC cache (cmcan.can.dbccache, cmcan.can.dbcmodel): a DBC read from the cache is the
DBC cantools reads, field for field and frame for frame; a damaged, hostile, outdated or foreign
entry is a miss that is rewritten; a cache that cannot be written is no error; an edited DBC is a
miss; and a replay on a warm cache does not import cantools.

Every test has its own empty cache directory (CMCAN_CACHE_DIR), as on a fresh machine."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.can import codec, dbccache
from cmcan.can.dbc import DbcError, load_dbc, message_problems
from cmcan.can.dbcmodel import BadDoc, CompiledDatabase, from_doc
from tests.conftest import ROOT

SHIPPED = [ROOT / "dbc" / "cmcan.dbc", ROOT / "dbc" / "j1939-example.dbc", ROOT / "examples" / "zema-rig" / "rig.dbc"]

# Messages in the shapes the shipped DBCs lack: multiplexed, 29-bit with a big-endian signed signal
# and a float, CAN FD with 64 bytes, a 64-bit and a 40-bit Motorola signal; and cycle times.
EXTRA_MESSAGES = """
BO_ 291 MUXED: 8 CMCAN
 SG_ mux M : 0|8@1+ (1,0) [0|255] "" CMCAN
 SG_ a m0 : 8|16@1+ (0.1,0) [0|6553.5] "bar" CMCAN
 SG_ b m1 : 8|16@1- (1,-5) [-32768|32767] "" CMCAN
 SG_ common : 24|8@1+ (1,0) [0|255] "" CMCAN

BO_ 2364540158 EXT_BE: 8 CMCAN
 SG_ be_signed : 7|12@0- (0.5,10) [-1000|1000] "degC" CMCAN
 SG_ fl : 32|32@1- (1,0) [0|0] "" CMCAN

BO_ 1024 FD64: 64 CMCAN
 SG_ wide : 0|64@1+ (1,0) [0|0] "" CMCAN
 SG_ far : 500|12@1+ (0.25,0) [0|1000] "" CMCAN
 SG_ motorola : 263|40@0- (0.001,-3) [-100|100] "m" CMCAN
"""
EXTRA_TAIL = (
    'SIG_VALTYPE_ 2364540158 fl : 1;\nVAL_ 291 mux 0 "A" 1 "B" ;\n'
    'BA_ "GenMsgCycleTime" BO_ 291 25;\nBA_ "GenMsgCycleTime" BO_ 1024 100;\n'
)
# What cantools' strict load refuses (tests/test_real_dbcs.py has their origins): overlapping
# signals in one message, a value table for a signal its message lacks.
LENIENT_MESSAGES = """
BO_ 1010 PLA_01: 8 CMCAN
 SG_ PLA_Bremsverzoegerung : 16|11@1+ (0.01,0) [0|20] "m/s2" CMCAN
 SG_ PLA_Bremsmoment : 24|13@1+ (1,0) [0|8000] "Nm" CMCAN

BO_ 568 UI_driverAssistRoadSign: 8 CMCAN
 SG_ UI_roadSign : 0|8@1+ (1,0) [0|255] "" CMCAN
"""
LENIENT_TAIL = 'VAL_ 568 UI_mapSpeedLimit 31 "SNA" 30 "UNLIMITED" 0 "UNKNOWN" ;\n'


def shipped_with(dest: Path, messages: str, tail: str) -> Path:
    text = (ROOT / "dbc" / "cmcan.dbc").read_text()
    at = text.index("\nBO_ ")
    text = text[:at] + "\n" + messages.strip("\n") + "\n" + text[at:]
    dest.write_text(text.rstrip("\n") + "\n" + tail)
    return dest


@pytest.fixture(autouse=True)
def empty_cache(tmp_path, monkeypatch):
    """Each test: its own empty cache directory, and nothing remembered from another test."""
    d = tmp_path / "cache"
    monkeypatch.setenv("CMCAN_CACHE_DIR", str(d))
    dbccache.clear_memo()
    yield d
    dbccache.clear_memo()


@pytest.fixture(scope="module")
def dbc_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("dbcs")
    return [
        *SHIPPED,
        shipped_with(d / "shapes.dbc", EXTRA_MESSAGES, EXTRA_TAIL),
        shipped_with(d / "lenient.dbc", LENIENT_MESSAGES, LENIENT_TAIL),
    ]


def entries(cache: Path) -> list[Path]:
    return sorted((cache / "dbc").glob("*.json")) if (cache / "dbc").is_dir() else []


def warm(path: Path) -> CompiledDatabase:
    """The DBC loaded twice, the second time from the cache entry the first wrote."""
    dbccache.load_compiled(path)
    dbccache.clear_memo()
    db = dbccache.load_compiled(path)
    assert isinstance(db, CompiledDatabase)
    return db


SIGNAL_FIELDS = [
    *("name", "start", "length", "byte_order", "is_signed", "is_float", "scale", "offset", "minimum", "maximum"),
    *("unit", "is_multiplexer", "multiplexer_ids", "multiplexer_signal"),
]
MESSAGE_FIELDS = ["name", "frame_id", "is_extended_frame", "is_fd", "length", "cycle_time"]


def assert_same(compiled, full) -> None:
    """Every field cmcan reads, of the same type and value, and the same codec layouts."""
    assert [m.name for m in compiled.messages] == [m.name for m in full.messages]
    assert dict(message_problems(compiled)) == dict(message_problems(full))
    for mc, mf in zip(compiled.messages, full.messages, strict=True):
        for f in MESSAGE_FIELDS:
            a, b = getattr(mc, f), getattr(mf, f)
            assert (type(a), a) == (type(b), b), (mc.name, f)
        assert mc.is_multiplexed() == mf.is_multiplexed()
        assert [s.name for s in mc.signals] == [s.name for s in mf.signals]
        for sc, sf in zip(mc.signals, mf.signals, strict=True):
            for f in SIGNAL_FIELDS:
                a, b = getattr(sc, f), getattr(sf, f)
                assert (type(a), a) == (type(b), b), (mc.name, sc.name, f)
        assert codec.message_layouts(mc) == codec.message_layouts(mf)
        assert codec.check_codable(mc) == codec.check_codable(mf)
        assert codec.covered(mc) == codec.covered(mf)
        assert compiled.get_message_by_name(mc.name) is mc


def test_a_dbc_from_the_cache_has_every_field_cantools_gives(dbc_files, empty_cache):
    for path in dbc_files:
        cold = dbccache.load_compiled(path)
        assert isinstance(cold, CompiledDatabase)
        assert_same(cold, load_dbc(path))
        assert_same(warm(path), load_dbc(path))
    assert len(entries(empty_cache)) == len(dbc_files)


def test_a_warm_cache_does_not_parse_the_dbc(dbc_files, monkeypatch):
    path = dbc_files[-2]
    dbccache.load_compiled(path)
    dbccache.clear_memo()

    def refuse(*_a, **_k):
        raise AssertionError("parsed by cantools on a warm cache")

    monkeypatch.setattr(dbccache, "load_dbc_digest", refuse)
    assert isinstance(dbccache.load_compiled(path), CompiledDatabase)


def test_a_lenient_dbc_logs_the_same_problems_cold_and_warm(tmp_path, caplog):
    path = shipped_with(tmp_path / "lenient.dbc", LENIENT_MESSAGES, LENIENT_TAIL)  # a new file: parsed here
    lines = []
    for _ in range(2):  # cold (cantools' lenient load logs), then warm (the cache's entry)
        dbccache.clear_memo()
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="cmcan.dbc"):
            db = dbccache.load_compiled(path)
        assert isinstance(db, CompiledDatabase)
        lines.append([r.getMessage() for r in caplog.records if r.levelno >= logging.INFO])
    problems = dict(message_problems(db))
    assert problems == dict(message_problems(load_dbc(path)))
    assert set(problems) == {"PLA_01", "UI_driverAssistRoadSign"}
    assert (
        lines[0]
        == lines[1]
        == [
            f"{path.resolve()}: message {k} does not pass cantools' strict check: {v}"
            for k, v in sorted(problems.items())
        ]
    )


def test_cantools_only_calls_are_cantools_own(dbc_files):
    """decode/encode with value tables, decode_message: handed to cantools' database of the file."""
    path = dbc_files[-2]
    db, full = warm(path), load_dbc(path)
    payload = bytes(range(8))
    m = db.get_message_by_name("MUXED")
    assert m.decode(payload) == full.get_message_by_name("MUXED").decode(payload)
    assert db.decode_message(291, payload) == full.decode_message(291, payload)
    values = {"mux": 0, "a": 12.3, "common": 7}
    assert m.encode(values) == full.get_message_by_name("MUXED").encode(values)
    with pytest.raises(KeyError):
        db.get_message_by_name("NO_SUCH")
    with pytest.raises(KeyError):
        m.get_signal_by_name("no_such")


# -- frames: decoded and encoded as cantools does ------------------------------------------------------


def _codable(sig) -> bool:
    return not sig.is_float and sig.multiplexer_ids is None


class Pairs(list):
    def __repr__(self) -> str:  # hypothesis prints its arguments: not every message of five DBCs
        return f"<{len(self)} DBCs>"


@pytest.fixture(scope="module")
def pairs(dbc_files, tmp_path_factory):
    """Each DBC from a warm cache of its own, and as cantools reads it."""
    mp = pytest.MonkeyPatch()
    mp.setenv("CMCAN_CACHE_DIR", str(tmp_path_factory.mktemp("cache")))
    try:
        return Pairs((warm(p), load_dbc(p)) for p in dbc_files)
    finally:
        mp.undo()
        dbccache.clear_memo()


@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_random_payloads_decode_as_cantools_decodes_them(pairs, data):
    for db, full in pairs:
        for mc in db.messages:
            mf = full.get_message_by_name(mc.name)
            payload = data.draw(st.binary(min_size=mc.length, max_size=mc.length))
            arr = np.frombuffer(payload, dtype=np.uint8).reshape(1, mc.length)
            ours = codec.decode(mc, arr)
            theirs = codec.decode(mf, arr)
            assert ours.keys() == theirs.keys()
            for k in ours:  # the compiled layouts give the very bits the cantools-built ones give
                assert np.array_equal(ours[k], theirs[k]), (mc.name, k)
            try:
                ref = mf.decode(payload, decode_choices=False, scaling=False)
            except Exception:  # cantools decodes nothing: a multiplexer value the DBC does not list, or
                assert mc.is_multiplexed() or mc.name in db.problems  # overlapping signals (a lenient load)
                continue
            raw = codec.decode_raw(mc, arr, [s.name for s in mc.signals if _codable(s)])
            for k, v in raw.items():
                assert int(v[0]) == ref[k], (mc.name, k)


@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_random_values_encode_as_cantools_encodes_them(pairs, data):
    for db, full in pairs:
        for mc in db.messages:
            mf = full.get_message_by_name(mc.name)
            if mc.is_multiplexed() or any(s.is_float for s in mc.signals):
                continue
            raws, phys = {}, {}
            for lay in codec.message_layouts(mc):
                lo, hi = codec.raw_bounds(lay)
                if lo > hi or lay.length > 48:  # beyond 48 bits physical floats no longer hold every raw
                    continue
                raws[lay.name] = data.draw(st.integers(lo, hi))
                phys[lay.name] = raws[lay.name] * lay.scale + lay.offset
            ours = codec.frame_encoder(codec.message_layouts(mc), codec.frame_bytes(mc), mc.length)(phys)
            built = codec.frame_encoder(codec.message_layouts(mf), codec.frame_bytes(mf), mf.length)(phys)
            assert ours == built
            if len(raws) == len(mc.signals) and mc.name not in db.problems:  # overlapping signals: not cmcan's
                assert ours == mf.encode(raws, scaling=False, strict=False, padding=False), mc.name
            cols = {k: np.array([v]) for k, v in phys.items()}
            assert np.array_equal(codec.encode(mc, cols, fill_unused=True), codec.encode(mf, cols, fill_unused=True))


# -- damaged, hostile and foreign entries --------------------------------------------------------------


def _entry(cache: Path) -> Path:
    (e,) = entries(cache)
    return e


def _rewrite_body(e: Path, edit) -> None:
    """The entry with its body edited and its digest recomputed: well-formed but for the edit."""
    doc = json.loads(e.read_text())
    edit(doc["body"])
    body = json.dumps(doc["body"], separators=(",", ":"))
    e.write_text(dbccache.envelope(body, doc["key"]["dbc_sha256"], doc["key"]["cantools"]))


def _set(path: list, value):
    def edit(body):
        node = body
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value

    return edit


DAMAGE = {
    "empty": lambda e: e.write_bytes(b""),
    "truncated": lambda e: e.write_bytes(e.read_bytes()[: len(e.read_bytes()) // 2]),
    "garbage": lambda e: e.write_bytes(os.urandom(4096)),
    "not utf-8": lambda e: e.write_bytes(b'{"key": "\xff\xfe"}'),
    "a list": lambda e: e.write_text("[1, 2, 3]"),
    "deeply nested": lambda e: e.write_text("[" * 100_000 + "]" * 100_000),
    "another format": lambda e: e.write_text(e.read_text().replace('"format": 1', '"format": 999')),
    "another cantools": lambda e: e.write_text(e.read_text().replace('"cantools": "', '"cantools": "0.0.0-')),
    "another dbc": lambda e: e.write_text(e.read_text().replace('"dbc_sha256": "', '"dbc_sha256": "00')),
    "a bit flipped in the body": lambda e: e.write_text(e.read_text().replace('"length":8', '"length":9', 1)),
    "a signal of 10**9 bits": lambda e: _rewrite_body(e, _set(["messages", 0, "signals", 0, "length"], 10**9)),
    "a signal beyond its frame": lambda e: _rewrite_body(e, _set(["messages", 0, "signals", 0, "start"], 4000)),
    "a frame of 10**6 bytes": lambda e: _rewrite_body(e, _set(["messages", 0, "length"], 10**6)),
    "a string scale": lambda e: _rewrite_body(e, _set(["messages", 0, "signals", 0, "scale"], "0.25")),
    "a NaN offset": lambda e: _rewrite_body(e, _set(["messages", 0, "signals", 0, "offset"], float("nan"))),
    "a boolean length": lambda e: _rewrite_body(e, _set(["messages", 0, "signals", 0, "length"], True)),
    "a float start": lambda e: _rewrite_body(e, _set(["messages", 0, "signals", 0, "start"], 0.0)),
    "an unknown byte order": lambda e: _rewrite_body(e, _set(["messages", 0, "signals", 0, "byte_order"], "pdp")),
    "an extra field": lambda e: _rewrite_body(e, _set(["messages", 0, "evil"], 1)),
    "messages not a list": lambda e: _rewrite_body(e, _set(["messages"], {"a": 1})),
    "a signal that is a number": lambda e: _rewrite_body(e, _set(["messages", 0, "signals", 0], 7)),
    "an empty name": lambda e: _rewrite_body(e, _set(["messages", 0, "name"], "")),
    "a negative frame id": lambda e: _rewrite_body(e, _set(["messages", 0, "frame_id"], -1)),
    "problems not texts": lambda e: _rewrite_body(e, _set(["problems"], {"X": ["list"]})),
    "a directory": lambda e: (e.unlink(), e.mkdir()),
    "a symbolic link": lambda e: (e.rename(e.with_suffix(".real")), e.symlink_to(e.with_suffix(".real"))),
}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_a_damaged_or_foreign_entry_is_ignored_and_rebuilt(damage, empty_cache, caplog):
    path = SHIPPED[0]
    dbccache.load_compiled(path)
    e = _entry(empty_cache)
    good = e.read_bytes()
    DAMAGE[damage](e)
    assert e.is_dir() or e.is_symlink() or e.read_bytes() != good  # damaged indeed
    dbccache.clear_memo()
    with caplog.at_level(logging.WARNING):
        db = dbccache.load_compiled(path)
    assert not caplog.records  # a miss is not worth a warning
    assert isinstance(db, CompiledDatabase)
    assert_same(db, load_dbc(path))
    if damage != "a directory":  # a directory in its place cannot be renamed over: the entry stays away
        assert e.read_bytes() == good and not e.is_symlink()  # rewritten, whole
        dbccache.clear_memo()
        assert isinstance(dbccache.read_entry(e, str(path), db.sha256, dbccache.cantools_version()), CompiledDatabase)


def test_from_doc_refuses_what_is_not_a_document():
    for doc in (None, [], {"messages": [], "problems": {}, "x": 1}, {"messages": [1], "problems": {}}):
        with pytest.raises(BadDoc):
            from_doc(doc, "x.dbc", "0")
    assert from_doc({"messages": [], "problems": {}}, "x.dbc", "0").messages == []


# -- where the cache cannot be written, and a DBC edited -----------------------------------------------


@pytest.mark.parametrize("where", ["below a file", "a file"])
def test_a_cache_that_cannot_be_written_falls_back_to_cantools_silently(where, tmp_path, monkeypatch, caplog):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("x")
    monkeypatch.setenv("CMCAN_CACHE_DIR", str(blocker / "cache" if where == "below a file" else blocker))
    for _ in range(2):
        dbccache.clear_memo()
        with caplog.at_level(logging.WARNING):
            db = dbccache.load_compiled(SHIPPED[0])
        assert not caplog.records
        assert_same(db, load_dbc(SHIPPED[0]))
    assert blocker.read_text() == "x"


def test_a_read_only_cache_directory_is_read_and_never_written(tmp_path, monkeypatch, empty_cache):
    dbccache.load_compiled(SHIPPED[0])
    e = _entry(empty_cache)
    before = e.stat().st_mtime_ns
    os.chmod(e.parent, 0o500)
    try:
        dbccache.clear_memo()
        assert isinstance(dbccache.load_compiled(SHIPPED[0]), CompiledDatabase)
        dbccache.clear_memo()
        assert isinstance(dbccache.load_compiled(SHIPPED[1]), CompiledDatabase)  # a miss, not written (unless root)
    finally:
        os.chmod(e.parent, 0o700)
    assert e.stat().st_mtime_ns == before


def test_an_edited_dbc_misses_the_cache(tmp_path, empty_cache):
    path = tmp_path / "m.dbc"
    text = (ROOT / "dbc" / "cmcan.dbc").read_text()
    path.write_text(text)
    first = dbccache.load_compiled(path)
    sig = first.get_message_by_name("PUMP_STATUS").get_signal_by_name("pump_speed_rpm")
    assert sig.scale == 0.25
    path.write_text(text.replace("pump_speed_rpm : 0|16@1+ (0.25,0)", "pump_speed_rpm : 0|16@1+ (0.5,0)"))
    second = dbccache.load_compiled(path)  # the same process: the bytes, not the name, are the key
    assert second.get_message_by_name("PUMP_STATUS").get_signal_by_name("pump_speed_rpm").scale == 0.5
    assert len(entries(empty_cache)) == 2
    assert_same(second, load_dbc(path))
    dbccache.clear_memo()
    path.write_text(text)  # back to the first bytes: the first entry again
    assert (
        dbccache.load_compiled(path).get_message_by_name("PUMP_STATUS").get_signal_by_name("pump_speed_rpm").scale
        == 0.25
    )


def test_a_missing_or_unparsable_dbc_is_the_same_error_as_without_a_cache(tmp_path, empty_cache):
    with pytest.raises(DbcError, match="not found"):
        dbccache.load_compiled(tmp_path / "none.dbc")
    bad = tmp_path / "bad.dbc"
    bad.write_text("this is no DBC")
    with pytest.raises(DbcError) as cached:
        dbccache.load_compiled(bad)
    with pytest.raises(DbcError) as plain:
        load_dbc(bad)
    assert str(cached.value) == str(plain.value)
    assert entries(empty_cache) == []


def test_writers_racing_for_one_entry_leave_it_whole(empty_cache):
    """xdist workers and several services starting at once write the same entry: readers see the old
    file or a new one, whole, never a part."""
    db = dbccache.load_compiled(SHIPPED[0])
    e = _entry(empty_cache)
    body = json.loads(e.read_text())["body"]
    text = json.dumps(body, separators=(",", ":"))
    version = dbccache.cantools_version()
    stop = threading.Event()
    bad = []

    def write():
        while not stop.is_set():
            dbccache.write_entry(e, text, db.sha256, version)

    def read():
        while not stop.is_set():
            if dbccache.read_entry(e, str(SHIPPED[0]), db.sha256, version) is None:
                bad.append(1)

    threads = [threading.Thread(target=write) for _ in range(3)] + [threading.Thread(target=read) for _ in range(2)]
    for t in threads:
        t.start()
    threading.Event().wait(1.0)
    stop.set()
    for t in threads:
        t.join()
    assert bad == []
    assert [p.name for p in e.parent.iterdir()] == [e.name]  # no temporary file left behind


# -- a whole command on a warm cache -------------------------------------------------------------------


def _modules_after(args: list[str], cache: Path, tmp_path: Path) -> set[str]:
    script = (
        "import contextlib, io, json, sys\n"
        "import cmcan.cli\n"
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):\n"
        "    try:\n"
        f"        cmcan.cli.main({args!r})\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print(json.dumps(sorted(k for k, v in sys.modules.items() if v is not None)))\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT), "CMCAN_CACHE_DIR": str(cache)},
        check=True,
    )
    return set(json.loads(r.stdout.splitlines()[-1]))


def test_a_replay_and_a_check_on_a_warm_cache_do_not_import_cantools(tmp_path, empty_cache):
    log = tmp_path / "x.log"
    log.write_text("".join(f"({1 + i / 100:.6f}) can0 100#0102030405060708\n" for i in range(20)))
    replay = ["replay", str(log), "--out", str(tmp_path / "x.csv"), "--force"]
    cold = _modules_after(replay, empty_cache, tmp_path)
    assert "cantools" in cold and "cmcan.replay" in cold  # an empty cache: parsed by cantools, then written
    assert len(entries(empty_cache)) == 1
    warm_mods = _modules_after(replay, empty_cache, tmp_path)
    assert "cmcan.replay" in warm_mods
    assert not {m for m in warm_mods if m in ("cantools", "can") or m.startswith(("cantools.", "can."))}
    check = _modules_after(["check"], empty_cache, tmp_path)
    assert "cmcan.assemble" in check and "cantools" not in check


def test_where_the_cache_lives(monkeypatch, tmp_path):
    monkeypatch.setenv("CMCAN_CACHE_DIR", str(tmp_path / "own"))
    monkeypatch.setenv("CACHE_DIRECTORY", str(tmp_path / "service"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert dbccache.cache_dir() == tmp_path / "own"
    monkeypatch.delenv("CMCAN_CACHE_DIR")
    assert dbccache.cache_dir() == tmp_path / "service"  # systemd's CacheDirectory=
    monkeypatch.delenv("CACHE_DIRECTORY")
    assert dbccache.cache_dir() == tmp_path / "xdg" / "cmcan"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative")  # ignored, as the XDG spec says
    assert dbccache.cache_dir() == tmp_path / "home" / ".cache" / "cmcan"


def test_cantools_only_calls_parse_the_file_once_and_refuse_a_file_changed_since(tmp_path, monkeypatch):
    """A compiled database hands value-table decoding to cantools' database of the same bytes, kept
    once parsed: a decode per frame reads no file. A file rewritten after it was compiled is named."""
    import shutil

    from cmcan.can import dbc as dbc_mod

    path = tmp_path / "m.dbc"
    shutil.copy(SHIPPED[0], path)
    db = warm(path)
    m = db.messages[0]
    reads = []
    real = dbc_mod.file_sha256
    monkeypatch.setattr(dbc_mod, "file_sha256", lambda name: reads.append(name) or real(name))
    for _ in range(50):
        db.decode_message(m.frame_id, bytes(m.length))
        m.decode(bytes(m.length))
    assert 0 < len(reads) <= 2  # the bytes hashed before and after the one parse, not per call

    other = warm(path)
    path.write_bytes(path.read_bytes() + b"\n")
    with pytest.raises(DbcError, match="changed since it was read"):
        other.decode_message(m.frame_id, bytes(m.length))
