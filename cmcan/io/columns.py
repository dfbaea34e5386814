"""Any CAN log as chunks of columns (:class:`cmcan.can.frame.FrameColumns`): the columnar replay's and
training's reader."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cmcan.can.frame import Frame, FrameColumns

if TYPE_CHECKING:
    from cmcan.io.candump import Cut

CHUNK_FRAMES = 1 << 18


def column_chunks(
    path: str | Path,
    chunk_frames: int = CHUNK_FRAMES,
    chunk_bytes: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    keep_truncated: bool = False,
    on_cut: Callable[[Cut], None] | None = None,
) -> Iterator[FrameColumns]:
    """A log as chunks of columns: candump logs by the array reader (chunks of about
    ``CHUNK_LINES`` lines, or ``chunk_bytes`` bytes when given), MF4 files by asammdf's array access
    (:mod:`cmcan.io.mf4columns`), other formats through python-can's readers ``chunk_frames`` at a
    time. ``progress(bytes_read, frames)`` after each chunk. A log cut short is refused, or with
    ``keep_truncated`` read up to its last whole frame with the :class:`cmcan.io.candump.Cut` handed
    to ``on_cut``, as :func:`cmcan.io.candump.iter_frames` does."""
    from cmcan.io.candump import iter_frames
    from cmcan.io.candump_columns import CHUNK_BYTES, CHUNK_LINES, iter_candump_columns
    from cmcan.io.readahead import read_ahead

    p = Path(path)
    frames = 0
    if p.name.endswith((".log", ".log.gz")):
        done = [0]
        # the next chunk is parsed in a thread while this one is replayed
        chunks = iter_candump_columns(
            p,
            chunk_bytes or CHUNK_BYTES,
            lambda b: done.__setitem__(0, b),
            None if chunk_bytes else CHUNK_LINES,
            keep_truncated,
            on_cut,
        )
        for cols in read_ahead(chunks):
            frames += len(cols)
            yield cols
            if progress is not None:
                progress(done[0], frames)
        return
    if p.suffix.lower() == ".mf4":
        from cmcan.io.readproc import read_in_process

        # read in a process of its own: asammdf holds the GIL (a thread would only take turns)
        for cols in read_in_process(mf4_chunks, p, chunk_frames):
            frames += len(cols)
            yield cols
            if progress is not None:
                progress(-1, frames)
        return
    batch: list[Frame] = []
    for f in iter_frames(p, keep_truncated, on_cut):
        batch.append(f)
        if len(batch) >= chunk_frames:
            frames += len(batch)
            yield FrameColumns.from_frames(batch)
            batch = []
            if progress is not None:
                progress(-1, frames)  # python-can's readers do not say how far into the file they are
    if batch:
        frames += len(batch)
        yield FrameColumns.from_frames(batch)


def mf4_chunks(p: Path, chunk_frames: int = CHUNK_FRAMES) -> Iterator[FrameColumns]:
    """An MF4 log as chunks of columns, checked as every reader's frames are (a time that is not
    finite, a payload beyond 64 bytes, too many channels: :class:`cmcan.io.candump.LogError` naming
    the frame; asammdf missing: the extra to install; a file asammdf cannot read: said in one line)."""
    from cmcan.errors import CmcanError, Kind
    from cmcan.io.candump import MAX_CHANNELS, LogError, more_channels, not_a_frame, not_frames
    from cmcan.io.mf4columns import iter_mf4_columns, open_mdf

    try:
        mdf = open_mdf(p)
    except ImportError as exc:
        raise CmcanError(f"{p}: reading .mf4 logs needs the 'mf4' extra: pip install 'cmcan[mf4]' ({exc})",
                         Kind.UNAVAILABLE) from None  # fmt: skip
    except Exception as exc:  # asammdf's own exceptions for a file that is not an MDF
        raise LogError(f"{p}: cannot read as a .mf4 log: {type(exc).__name__}: {exc}") from None
    n, names = 0, set()
    try:
        chunks = iter_mf4_columns(mdf, chunk_frames, max(1, chunk_frames // 8))  # the replay starts sooner
        while True:
            try:
                cols = next(chunks)
            except StopIteration:
                break
            except Exception as exc:  # a damaged block, a record asammdf cannot convert
                raise LogError(f"{p}: cannot read as a .mf4 log after frame {n}: {type(exc).__name__}: {exc}") from None
            bad = np.flatnonzero(not_frames(cols.timestamp_s, cols.arbitration_id, cols.dlc))
            if len(bad):
                i = int(bad[0])
                t, ident, nb = float(cols.timestamp_s[i]), int(cols.arbitration_id[i]), int(cols.dlc[i])
                raise not_a_frame(p, f"frame {n + i + 1}", t, ident, nb)
            if more_channels(names, cols.channel_names):
                raise LogError(f"{p}: after frame {n}: more than {MAX_CHANNELS} channel names: not a CAN log")
            n += len(cols)
            yield cols
    finally:
        mdf.close()
