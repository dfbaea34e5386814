"""MF4 logs read in columns (:mod:`cmcan.io.mf4columns`) give exactly the frames python-can's
``MF4Reader`` gives, in its order, whatever the chunk size (several channels, CAN FD payloads beyond
8 bytes, remote and error frames in groups of their own, ties in time across groups, plain and
deflated data blocks), read from the records' bytes or through ``MDF.get`` alike; and a replay of an
MF4 writes the same timeline, byte for byte, as the replay of the same frames as a candump log."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("asammdf")

import can

from cmcan.can.frame import Frame, FrameColumns, to_message_kwargs
from cmcan.io import mf4columns, mf4support
from cmcan.io.candump import iter_frames, write_candump
from cmcan.io.columns import column_chunks
from tests.conftest import run_cli
from tests.helpers import sim_frames


def _write_mf4(path, frames: list[Frame]) -> None:
    mf4support.enable()
    with can.Logger(str(path)) as w:
        for f in frames:
            w.on_message_received(can.Message(**to_message_kwargs(f)))


def _mixed(n: int, seed: int) -> list[Frame]:
    """Data frames on three channels (classic and FD, up to 64 bytes), remote and error frames, some
    at the very same time as others (ties across the writer's groups)."""
    rng = np.random.default_rng(seed)
    t = 1_700_000_000.0 + np.cumsum(rng.choice([0.0, 0.001, 0.0005], size=n))
    out = []
    for i in range(n):
        kind = rng.choice(["data", "fd", "remote", "error"], p=[0.7, 0.15, 0.1, 0.05])
        ch = str(int(rng.integers(0, 3)))
        ext = bool(rng.integers(0, 2))
        ident = int(rng.integers(0, 1 << 29 if ext else 1 << 11))
        if kind == "data":
            out.append(Frame(float(t[i]), ch, ident, ext, False, False, False, rng.bytes(int(rng.integers(0, 9)))))
        elif kind == "fd":
            size = int(rng.choice([0, 5, 8, 12, 16, 20, 24, 32, 48, 64]))
            out.append(Frame(float(t[i]), ch, ident, ext, False, False, True, rng.bytes(size)))
        elif kind == "remote":
            out.append(Frame(float(t[i]), ch, ident, ext, True, False, False, b""))
        else:
            out.append(Frame(float(t[i]), ch, 0, False, False, True, False, b""))
    return out


def _python_can(path) -> FrameColumns:
    return FrameColumns.from_frames(list(iter_frames(path)))


def _same(a: FrameColumns, b: FrameColumns) -> None:
    assert len(a) == len(b)
    assert a.frames() == b.frames()  # every field of every frame, channel names included


@pytest.fixture(scope="module")
def mixed_mf4(tmp_path_factory):
    path = tmp_path_factory.mktemp("mf4") / "mixed.mf4"
    _write_mf4(path, _mixed(3000, seed=5))
    return path


@pytest.fixture(params=["bytes", "get"])
def read_by(request, monkeypatch, mixed_mf4):
    """Each test once with the fields read from the records' bytes (every group of these files is
    plain), once through ``MDF.get`` (as for a layout that is not)."""
    if request.param == "get":
        monkeypatch.setattr(mf4columns, "layout_of", lambda *a: None)
    else:
        mdf = mf4columns.open_mdf(mixed_mf4)
        groups = mf4columns.can_groups(mdf)
        mdf.close()
        assert len(groups) >= 3 and all(g.layout is not None for g in groups)  # the bytes are read
    return request.param


@pytest.mark.parametrize("chunk", [1, 7, 256, 1 << 18])
def test_columns_are_python_cans_frames_at_any_chunk_size(mixed_mf4, chunk, read_by):
    want = _python_can(mixed_mf4)
    assert {"data", "remote", "error", "fd"} <= {
        "remote" if f.remote else "error" if f.error else "fd" if f.fd else "data" for f in want.frames()
    }  # the interesting cases are there
    assert any(len(f.data) > 8 for f in want.frames()) and len(want.channel_names) == 3
    got = FrameColumns.concat(list(column_chunks(mixed_mf4, chunk_frames=chunk)))
    _same(got, want)


@pytest.mark.parametrize("compression", [0, 2])
def test_plain_and_compressed_data_blocks_read_the_same(mixed_mf4, tmp_path, compression, read_by):
    from asammdf import MDF

    saved = tmp_path / "saved.mf4"
    with MDF(str(mixed_mf4)) as mdf:
        mdf.save(str(saved), compression=compression)  # 0: plain blocks, 2: transposed and deflated
    assert (b"##DZ" in saved.read_bytes()) == bool(compression)
    _same(FrameColumns.concat(list(column_chunks(saved, chunk_frames=500))), _python_can(mixed_mf4))


def test_the_mf4_replay_writes_the_candump_replays_timeline(tmp_path):
    _run, sim = sim_frames("single_set_leakage", duration_h=0.05)
    log = tmp_path / "run.log"
    write_candump(log, sim.timestamp_s, sim.arbitration_id, sim.dlc, sim.data)
    mf4 = tmp_path / "run.mf4"
    _write_mf4(mf4, list(iter_frames(log)))  # the same frames, as the candump log has them
    outs = {}
    for src in (log, mf4):
        out = tmp_path / f"{src.suffix[1:]}.csv"
        res = run_cli("replay", str(src), "--out", str(out), "--json")
        assert res.returncode == 0, res.stderr
        outs[src.suffix] = out.read_bytes()
    assert outs[".mf4"] == outs[".log"] and outs[".log"].count(b"\n") > 100


def test_a_layout_that_is_not_plain_is_read_through_asammdf(mixed_mf4):
    """Bit fields, conversions, big-endian or variable-length fields: the structure's record type and
    a channel's own reading may differ there, so such a group is left to ``MDF.get``."""
    from asammdf.blocks import v4_constants as v4c

    def layout_after(change) -> object:
        mdf = mf4columns.open_mdf(mixed_mf4)
        try:
            group = mdf.groups[mf4columns.can_groups(mdf)[0].index]
            by_name = {c.name: c for c in group.channels}
            change(by_name)
            return mf4columns.layout_of(mdf, group, "CAN_DataFrame")
        finally:
            mdf.close()

    plain = layout_after(lambda ch: None)
    assert plain is not None and set(plain.uints) >= {"ID", "IDE", "EDL", "BusChannel", "DataLength"}
    assert plain.payload is not None and plain.payload[1] == 64
    changes = {
        "bit field": lambda ch: setattr(ch["CAN_DataFrame.ID"], "bit_count", 29),
        "bit offset": lambda ch: setattr(ch["CAN_DataFrame.IDE"], "bit_offset", 7),
        "big-endian": lambda ch: setattr(ch["CAN_DataFrame.ID"], "data_type", v4c.DATA_TYPE_UNSIGNED_MOTOROLA),
        "conversion": lambda ch: setattr(ch["CAN_DataFrame.DataLength"], "conversion", object()),
        "variable length": lambda ch: setattr(ch["CAN_DataFrame.DataBytes"], "channel_type", v4c.CHANNEL_TYPE_VLSD),
        "beyond the record": lambda ch: setattr(ch["CAN_DataFrame.DataBytes"], "byte_offset", 10_000),
    }
    for what, change in changes.items():
        assert layout_after(change) is None, what


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.uint32, np.int64])
def test_bus_numbers_are_coded_as_numpys_unique_codes_them(dtype):
    rng = np.random.default_rng(3)
    for values in ([0], [7, 7, 7], [200, 2, 9], list(rng.integers(0, 250, 1000))):
        bus = np.asarray(values, dtype=dtype)
        numbers, code = mf4columns._codes(bus)
        want_numbers, want_code = np.unique(bus.astype(np.int64), return_inverse=True)
        assert numbers.tolist() == want_numbers.tolist()
        assert code.dtype == np.int16 and code.tolist() == want_code.tolist()


def test_the_reader_process_imports_asammdf_without_what_reading_frames_never_uses(mixed_mf4):
    """The reader process's start (``preload``) leaves canmatrix's spreadsheet formats and pandas'
    Arrow support unimported, and the file still reads (both go on without them)."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from pathlib import Path\n"
        "from cmcan.io.mf4columns import preload, UNUSED_BY_THE_READER\n"
        "from cmcan.io.columns import mf4_chunks\n"
        "preload()\n"
        "assert 'asammdf' in sys.modules and 'pandas' in sys.modules\n"
        "assert all(sys.modules.get(m) is None for m in UNUSED_BY_THE_READER), UNUSED_BY_THE_READER\n"
        f"print(sum(len(c) for c in mf4_chunks(Path({str(mixed_mf4)!r}))))\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert int(res.stdout) == len(_python_can(mixed_mf4))
