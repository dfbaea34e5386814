"""Public material cmcan did not write: every log of python-can's ``test/data`` through both replay
engines, and every DBC of cantools' ``tests/files/dbc`` through ``cmcan check``'s DBC path and the
bit extractor.

The files are not in this repository: they come from the projects' own source distributions
(python-can: LGPL-3.0, cantools: MIT), which ``python -m tests.third_party`` fetches from the package
index into ``tests/third_party`` (CI does so before the suite), and are looked for there (or in
``$CMCAN_THIRD_PARTY``) as ``python-can/test/data`` and ``cantools/tests/files/dbc``; the tests skip,
saying so, where they are absent. The generated tests
of ``test_log_formats.py``, ``test_real_dbcs.py`` and ``test_codec_widths.py`` cover the same
shapes everywhere."""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import can
import numpy as np
import pytest
import yaml

from cmcan.can import codec
from cmcan.can.dbc import DbcError, load_dbc
from cmcan.cli.errors import EX_SOFTWARE
from tests.conftest import ROOT

THIRD_PARTY = Path(os.environ.get("CMCAN_THIRD_PARTY", ROOT / "tests" / "third_party"))
PYTHON_CAN_DATA = THIRD_PARTY / "python-can" / "test" / "data"
CANTOOLS_DBC = THIRD_PARTY / "cantools" / "tests" / "files" / "dbc"
LOG_SUFFIXES = (".asc", ".blf", ".trc", ".csv", ".log", ".gz", ".mf4", ".db")


def _files(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in suffixes)


def _absent(folder: Path, what: str):
    return pytest.mark.skipif(
        not folder.is_dir(), reason=f"{what} not found at {folder} (python -m tests.third_party fetches it)"
    )


# -- python-can's test logs -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def shipped_parts():
    from cmcan import config as cfgmod
    from cmcan.assemble import assemble

    cfg = cfgmod.load()
    return cfg, assemble


@_absent(PYTHON_CAN_DATA, "python-can's test/data")
@pytest.mark.parametrize("log", _files(PYTHON_CAN_DATA, LOG_SUFFIXES), ids=lambda p: p.name)
def test_python_cans_test_logs_replay_the_same_in_both_engines(log, shipped_parts):
    from cmcan.io.candump import LogError, iter_frames
    from cmcan.replay import replay_file

    cfg, assemble = shipped_parts
    try:
        want = sum(1 for _ in can.LogReader(str(log)))
    except Exception as exc:  # a file python-can itself cannot read: cmcan must refuse it cleanly
        with pytest.raises(LogError):
            list(iter_frames(log))
        pytest.skip(f"python-can cannot read it either ({type(exc).__name__})")
    frames = list(iter_frames(log))
    assert len(frames) == want
    results = []
    for engine in ("columnar", "streaming"):
        mon = assemble(cfg).monitor
        res = replay_file(log, mon, engine=engine)
        results.append((res.counters, res.warnings, res.totals, res.first_t, res.duration_h))
        assert res.counters["frames_total"] == want
    assert results[0] == results[1]


@_absent(PYTHON_CAN_DATA, "python-can's test/data")
def test_every_log_of_python_cans_test_data_is_tried():
    names = {p.name for p in _files(PYTHON_CAN_DATA, LOG_SUFFIXES)}
    assert {"logfile.asc", "test_CanFdMessage64.blf", "test_CanMessage.asc.gz", "test_CanMessage_V2_1.trc"} <= names


# -- cantools' test DBCs ----------------------------------------------------------------------------------


def _check(cfg_path: Path) -> tuple[int, str]:
    """``cmcan check --config`` in this process: its exit code and what it printed on stderr."""
    from cmcan.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(["check", "--config", str(cfg_path)])
    return rc, err.getvalue()


@_absent(CANTOOLS_DBC, "cantools' tests/files/dbc")
@pytest.mark.parametrize("dbc", _files(CANTOOLS_DBC, (".dbc",)), ids=lambda p: p.name)
def test_cantools_test_dbcs_through_check_and_the_bit_extractor(dbc, tmp_path):
    """Each DBC loads (or is refused as a DBC, naming the file), and ``cmcan check`` with one of its
    integer signals mapped to a role exits with a sysexits code and one line, never 70; every signal
    cmcan can read decodes as cantools decodes it, per frame and in arrays."""
    try:
        db = load_dbc(dbc)
    except DbcError as exc:
        assert str(dbc) in str(exc) and "not a valid DBC" in str(exc)
        return
    readable = []
    rng = np.random.default_rng(0)
    for msg in db.messages:
        names = [s.name for s in msg.signals if codec.check_codable(msg, [s.name]) is None]
        if not names or msg.length == 0:
            continue
        readable.append((msg, names[0]))
        frames = rng.integers(0, 256, size=(8, msg.length), dtype=np.uint8)
        per_frame = codec.raw_decoder(codec.message_layouts(msg, names), codec.frame_bytes(msg))
        arr = codec.decode_raw(msg, frames, names)
        for i, row in enumerate(frames):
            data = bytes(row)
            try:
                ref = msg.decode(data, decode_choices=False, scaling=False, allow_truncated=True)
            except Exception:  # cantools cannot decode this frame (its multiplexer value unknown, say)
                continue
            got = per_frame(data)
            for k, n in enumerate(names):
                if n in ref:
                    assert got[k] == ref[n] and int(arr[n][i]) == ref[n], (msg.name, n)
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(dbc)
    if readable:
        msg, sig = readable[0]
        raw["signals"]["temp_c"] = {"message": msg.name, "signal": sig}
    cfg = tmp_path / "m.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    rc, err = _check(cfg)
    assert rc != EX_SOFTWARE, err
    assert rc == 0 or len([x for x in err.splitlines() if x.startswith("cmcan check:")]) == 1, err
