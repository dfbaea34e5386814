"""Any CAN log as chunks of columns (:class:`cmcan.frame.FrameColumns`): the columnar replay's and
training's reader."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from cmcan.frame import Frame, FrameColumns

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
    ``CHUNK_LINES`` lines, or ``chunk_bytes`` bytes when given), other formats through python-can's
    readers ``chunk_frames`` at a time. ``progress(bytes_read, frames)`` after each chunk. A log cut
    short is refused, or with ``keep_truncated`` read up to its last whole frame with the
    :class:`cmcan.io.candump.Cut` handed to ``on_cut``, as :func:`cmcan.io.candump.iter_frames` does."""
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
