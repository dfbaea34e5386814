"""The inputs of a bad week (issue 17, items 3 to 5): each refused with a sysexits code and one line
naming the file, never exit 70 "internal error", never a traceback, never a silent partial result."""

from __future__ import annotations

import gzip
import json
import math

import can
import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from cmcan.can.frame import to_message_kwargs
from cmcan.cli.errors import EX_CANTCREAT, EX_CONFIG, EX_DATAERR, EX_UNAVAILABLE
from cmcan.model import digest
from tests.conftest import ROOT, run_cli
from tests.helpers import as_frames, sim_frames, write_log
from tests.test_cli_run import config_copy

DEFAULT_MODEL = ROOT / "cmcan" / "model" / "default.onnx"


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """The same 40 s of frames as candump, BLF, SQLite and MF4 logs."""
    d = tmp_path_factory.mktemp("logs")
    _run, frames = sim_frames("single_set_healthy", duration_h=40 / 3600)
    out = {"log": write_log(d / "run.log", frames)}
    for fmt in ("blf", "db", "mf4"):
        out[fmt] = d / f"run.{fmt}"
        with can.Logger(str(out[fmt])) as w:
            for f in as_frames(frames):
                w.on_message_received(can.Message(**to_message_kwargs(f)))
    out["n"] = len(frames.timestamp_s)
    return out


def refused(res, code: int, *names: str) -> None:
    """Exit ``code``, one line on stderr naming each of ``names``, no traceback."""
    assert res.returncode == code, (res.returncode, res.stderr)
    assert "Traceback" not in res.stderr and "internal error" not in res.stderr, res.stderr
    lines = [x for x in res.stderr.splitlines() if x.strip()]
    assert len(lines) == 1, res.stderr
    for n in names:
        assert n in lines[0], (n, lines[0])


# -- configuration and model ------------------------------------------------------------------------


def test_a_configuration_that_is_not_utf8(tmp_path):
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes(("# Maschine f\xfcr den Bagger\n" + config_copy(tmp_path).read_text()).encode("latin-1"))
    for args in (("check",), ("run", "--state-dir", str(tmp_path))):
        refused(run_cli(*args, "--config", str(bad)), EX_CONFIG, "latin1.yaml", "UTF-8")


def test_an_unknown_role_under_max_signal_age_is_refused(tmp_path):
    cfg = config_copy(tmp_path, **{"max_signal_age_s.tmp_c": 2.0})
    refused(run_cli("check", "--config", str(cfg)), EX_CONFIG, "max_signal_age_s.tmp_c", "did you mean 'temp_c'")


def with_metadata(dst, change):
    m = onnx.load(str(DEFAULT_MODEL))
    props = {p.key.removeprefix("cmcan."): json.loads(p.value) for p in m.metadata_props}
    change(props)
    del m.metadata_props[:]
    for k, v in props.items():
        e = m.metadata_props.add()
        e.key, e.value = f"cmcan.{k}", json.dumps(v)
    dst.write_bytes(digest.seal(m.SerializeToString()))  # sealed again: a writer's wrong types, not corruption
    return dst


@pytest.mark.parametrize(
    ("name", "change", "field"),
    [
        ("no_unit", lambda p: p["inputs"][0].pop("unit"), "cmcan.inputs[0]"),
        ("unit_number", lambda p: p["inputs"][2].update(unit=5), "cmcan.inputs[2]"),
        ("version_number", lambda p: p.update(model_version=3), "cmcan.model_version"),
        ("outputs_text", lambda p: p.update(outputs="predicted"), "cmcan.outputs"),
        ("physics_list", lambda p: p.update(physics=[1, 2]), "cmcan.physics"),
        ("envelope_foreign_input", lambda p: p["envelope"].update(foo=[0, 1]), "cmcan.envelope"),
        ("envelope_missing_input", lambda p: p["envelope"].pop("temp_c"), "cmcan.envelope"),
        ("oil_text", lambda p: p["oil"].update(nu40_cst="46"), "cmcan.oil"),
    ],
)
def test_model_metadata_of_the_wrong_type_is_named_in_check_run_and_replay(tmp_path, logs, name, change, field):
    model = with_metadata(tmp_path / f"{name}.onnx", change)
    cfg = config_copy(tmp_path, model=str(model), **{"bus.interface": "virtual"})
    for args in (("check",), ("run", "--state-dir", str(tmp_path))):
        refused(run_cli(*args, "--config", str(cfg)), EX_CONFIG, f"{name}.onnx", field)
    refused(run_cli("replay", str(logs["log"]), "--model", str(model)), EX_CONFIG, f"{name}.onnx", field)


def spoiled_model(dst, factor: float):
    """The default model with its physics coefficients multiplied by ``factor`` (NaN, -1, 1e30) and
    sealed again: a graph that loads and runs, and predicts nonsense (a bad fit, not a bad copy)."""
    m = onnx.load(str(DEFAULT_MODEL))
    for init in m.graph.initializer:
        if init.name == "physics_coef":
            init.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(init) * factor, init.name))
    dst.write_bytes(digest.seal(m.SerializeToString()))
    return dst


@pytest.mark.parametrize("factor", [math.nan, -1.0, 1e30])
def test_check_and_run_refuse_a_model_that_returns_nonsense(tmp_path, factor):
    model = spoiled_model(tmp_path / "spoiled.onnx", factor)
    cfg = config_copy(tmp_path, model=str(model), **{"bus.interface": "virtual"})
    for args in (("check",), ("run", "--state-dir", str(tmp_path))):
        refused(run_cli(*args, "--config", str(cfg)), EX_CONFIG, "spoiled.onnx", "inside its training envelope")


# -- CAN logs -------------------------------------------------------------------------------------------


ENGINES = ("columnar", "streaming")


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("keep", [0.45, 0.9])
def test_a_truncated_blf_is_refused_not_replayed_in_part(tmp_path, logs, engine, keep):
    """python-can's BLFReader stops quietly where the data end: a cut copy replayed part of the log
    with exit 0. The file's own framing (header size, object sizes) shows the cut."""
    data = logs["blf"].read_bytes()
    cut = tmp_path / "cut.blf"
    cut.write_bytes(data[: int(len(data) * keep)])
    refused(run_cli("replay", str(cut), "--engine", engine), EX_DATAERR, "cut.blf", "truncated")


def test_a_blf_whose_writer_died_is_read_to_its_last_whole_object(tmp_path, logs):
    """A logger that lost power never wrote the file's size into the header: the objects that are
    whole are read (with a warning), one cut in half is refused."""
    import struct

    data = bytearray(logs["blf"].read_bytes())
    struct.pack_into("<Q", data, 4 * 1 + 4 + 8, 144)  # the header's file size as the writer first wrote it
    died = tmp_path / "died.blf"
    died.write_bytes(bytes(data))
    res = run_cli("replay", str(died), "--json")
    assert res.returncode == 0, res.stderr
    assert "never completed" in res.stderr and json.loads(res.stdout)["final"]["counters"]["frames_total"] == logs["n"]
    (tmp_path / "died_cut.blf").write_bytes(bytes(data[: len(data) - 100]))
    refused(run_cli("replay", str(tmp_path / "died_cut.blf")), EX_DATAERR, "died_cut.blf", "truncated")


def read_both(path):
    """The frames of ``path`` by both readers (the streaming engine's and the columnar one's)."""
    from cmcan.io.candump import iter_frames
    from cmcan.io.columns import column_chunks

    return len(list(iter_frames(path))), sum(len(c) for c in column_chunks(path))


NOT_LOGS = [
    ("garbage.blf", bytes(range(256)) * 8),
    ("text.db", b"(1767225600.000000) can0 100#00\n" * 50),
    ("garbage.mf4", b"\x81\xe8l\xc8" * 300),
    ("garbage.asc", bytes(range(128, 256)) * 8),
    ("empty.blf", b""),
    ("x.txt", b"(1767225600.000000) can0 100#00\n"),
]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # asammdf's destructor
@pytest.mark.parametrize(("name", "content"), NOT_LOGS)
def test_logs_that_are_not_of_their_format(tmp_path, name, content):
    from cmcan.io.candump import LogError

    p = tmp_path / name
    p.write_bytes(content)
    with pytest.raises(LogError, match=name):
        read_both(p)


def test_a_log_that_is_not_of_its_format_through_the_cli(tmp_path):
    for name, content in NOT_LOGS[:3]:
        (tmp_path / name).write_bytes(content)
        refused(run_cli("replay", str(tmp_path / name)), EX_DATAERR, name)


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # asammdf's destructor
@pytest.mark.parametrize("fmt", ["db", "mf4"])
@pytest.mark.parametrize("keep", [0.3, 0.5, 0.8])
def test_truncated_sqlite_and_mf4_logs(tmp_path, logs, fmt, keep):
    from cmcan.io.candump import LogError

    data = logs[fmt].read_bytes()
    cut = tmp_path / f"cut.{fmt}"
    cut.write_bytes(data[: int(len(data) * keep)])
    try:
        n = read_both(cut)
    except LogError as exc:
        assert f"cut.{fmt}" in str(exc)
    else:  # a reader that read it whole after all: then it must be the whole log
        assert n == (logs["n"], logs["n"])


@pytest.mark.parametrize("engine", ENGINES)
def test_a_truncated_gzipped_candump_log(tmp_path, logs, engine):
    gz = gzip.compress(logs["log"].read_bytes())
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(gz[: len(gz) // 2])
    refused(run_cli("replay", str(cut), "--engine", engine), EX_DATAERR, "cut.log.gz", "truncated or corrupt")


def test_both_engines_name_the_same_line_of_a_truncated_gzipped_log(tmp_path, logs):
    """The columnar reader fails a whole chunk at a time: it names the line the line reader stops at,
    not the chunk's first line."""
    gz = gzip.compress(logs["log"].read_bytes() * 40)  # a log of several chunks
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(gz[: len(gz) * 2 // 3])
    said = {e: run_cli("replay", str(cut), "--engine", e).stderr for e in ENGINES}
    assert said["columnar"] == said["streaming"] and "cannot read past line" in said["columnar"]


def test_mf4_replays_with_its_extra_and_names_the_extra_without_it(tmp_path, logs):
    res = run_cli("replay", str(logs["mf4"]), "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["final"]["counters"]["frames_total"] == logs["n"]
    # without asammdf (a gateway's install): exit 69 naming the extra, not an internal error
    block = tmp_path / "block"
    block.mkdir()
    (block / "asammdf.py").write_text("raise ImportError('asammdf is not installed here')\n")
    res = run_cli("replay", str(logs["mf4"]), env={"PYTHONPATH": str(block)})
    refused(res, EX_UNAVAILABLE, "run.mf4", "pip install 'cmcan[mf4]'")


@pytest.mark.parametrize(
    "line",
    [
        "can0 100#0011223344556677",  # no timestamp at all: python-can's reader makes one up
        "1767225600.000000 can0 100#0011223344556677",  # no parentheses: read as 767225600.00000
        "(1767225600.000000 can0 100#0011223344556677",
        "(.) can0 100#0011223344556677",
        "(nan) can0 100#0011223344556677",
        "(inf) can0 100#0011223344556677",
        "(-5.000000) can0 100#0011223344556677",
        "(1_767_225_600.0) can0 100#0011223344556677",
    ],
)
def test_candump_lines_without_a_real_timestamp_are_refused(tmp_path, logs, line):
    from cmcan.io.candump import iter_frames
    from cmcan.io.columns import column_chunks

    lines = logs["log"].read_text().splitlines(keepends=True)
    bad = tmp_path / "bad.log"
    bad.write_text("".join(lines[:100]) + line + "\n" + "".join(lines[100:200]))
    for read in (lambda: list(iter_frames(bad)), lambda: list(column_chunks(bad))):
        with pytest.raises(ValueError, match=r"bad.log: line 101: not a candump -l line"):
            read()


@pytest.mark.parametrize("engine", ENGINES)
def test_a_candump_line_without_a_timestamp_through_the_cli(tmp_path, logs, engine):
    lines = logs["log"].read_text().splitlines(keepends=True)
    bad = tmp_path / "bad.log"
    bad.write_text("".join(lines[:100]) + "can0 100#0011223344556677\n" + "".join(lines[100:200]))
    refused(run_cli("replay", str(bad), "--engine", engine), EX_DATAERR, "bad.log", "line 101")


def test_a_log_without_line_ends_is_refused_with_bounded_memory(tmp_path):
    big = tmp_path / "one_line.log"
    with open(big, "wb") as f:
        for _ in range(64):
            f.write(b"(1767225600.000000) can0 100#00 " * 4096)
    for engine in ENGINES:
        refused(run_cli("replay", str(big), "--engine", engine), EX_DATAERR, "one_line.log", "longer than")


def test_an_output_in_a_missing_folder_is_refused_before_the_replay(tmp_path, logs):
    res = run_cli(
        "replay", str(logs["log"]), "--out", str(tmp_path / "nope" / "t.csv"), "--emit", str(tmp_path / "e.log")
    )
    refused(res, EX_CANTCREAT, "nope", "does not exist")
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written, not even the other output


def test_timestamps_of_other_formats_must_be_times(tmp_path):
    from cmcan.io.candump import LogError, iter_frames

    p = tmp_path / "nan.csv"
    p.write_text("timestamp,arbitration_id,extended,remote,error,dlc,data\nnan,0x100,0,0,0,1,AA==\n")
    with pytest.raises(LogError, match=r"nan.csv: line 2: timestamp nan is not a time"):
        list(iter_frames(p))
    assert np.isnan(next(iter(can.LogReader(str(p)))).timestamp)  # python-can takes it as it is
