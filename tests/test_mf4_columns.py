"""MF4 logs read in columns (:mod:`cmcan.io.mf4columns`) give exactly the frames python-can's
``MF4Reader`` gives, in its order, whatever the chunk size (several channels, CAN FD payloads beyond
8 bytes, remote and error frames in groups of their own, ties in time across groups, plain and
deflated data blocks); and a replay of an MF4 writes the same timeline, byte for byte, as the replay of the same
frames as a candump log."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("asammdf")

import can

from cmcan.can.frame import Frame, FrameColumns, to_message_kwargs
from cmcan.io import mf4support
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


@pytest.mark.parametrize("chunk", [1, 7, 256, 1 << 18])
def test_columns_are_python_cans_frames_at_any_chunk_size(mixed_mf4, chunk):
    want = _python_can(mixed_mf4)
    assert {"data", "remote", "error", "fd"} <= {
        "remote" if f.remote else "error" if f.error else "fd" if f.fd else "data" for f in want.frames()
    }  # the interesting cases are there
    assert any(len(f.data) > 8 for f in want.frames()) and len(want.channel_names) == 3
    got = FrameColumns.concat(list(column_chunks(mixed_mf4, chunk_frames=chunk)))
    _same(got, want)


@pytest.mark.parametrize("compression", [0, 2])
def test_plain_and_compressed_data_blocks_read_the_same(mixed_mf4, tmp_path, compression):
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
