"""Bus-logging MF4 (ASAM MDF 4) files straight into columns, through asammdf's array access.

python-can's ``MF4Reader`` hands over one ``Message`` at a time (about 15 us a frame). This reads the
same records in chunks of ``chunk_frames`` with ``MDF.get(..., record_offset, record_count)`` and turns
each chunk into :class:`cmcan.can.frame.FrameColumns` with array operations. It gives exactly the frames
python-can's reader gives, and in its order (a test holds the two equal):

- every channel group flagged as a bus event with a CAN source and records: ``CAN_DataFrame`` groups
  (classic and FD: ``EDL``), ``CAN_ErrorFrame`` and ``CAN_RemoteFrame`` groups;
- a frame's time is the record's time plus the file's start time; its identifier the ``ID`` masked
  to 29 bits; its payload ``DataBytes`` cut to ``DataLength``; its channel the ``BusChannel`` number
  as text (none without that channel); a remote frame carries no payload;
- the groups merged in time order, a tie in the order of the groups (python-can merges its
  per-group iterators with ``heapq.merge``, which is stable so), each group read a chunk at a time, so
  memory is bounded by a chunk per group however large the file.

Compressed data blocks are asammdf's to inflate. The file's checks are those of python-can's
readers, the same functions (:func:`cmcan.io.candump.not_frames`, applied in
:func:`cmcan.io.columns.mf4_chunks`): a time that is not finite, a payload longer than CAN FD's 64
bytes or too many channels is a :class:`cmcan.io.candump.LogError` naming the frame.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can.frame import FrameColumns

KINDS = ("CAN_DataFrame", "CAN_ErrorFrame", "CAN_RemoteFrame")
ID_MASK = 0x1FFFFFFF


@dataclass
class _Group:
    """One channel group of CAN records read a chunk at a time, and what of it is not yet merged."""

    index: int
    kind: str
    records: int
    offset: int = 0  # records read so far
    pending: FrameColumns | None = None

    @property
    def more(self) -> bool:
        return self.offset < self.records


def can_groups(mdf: Any) -> list[_Group]:
    """The channel groups python-can's reader reads: bus events from a CAN source, with records,
    holding data, error or remote frames (the first of those kinds a group holds)."""
    from asammdf.blocks.v4_constants import BUS_TYPE_CAN, FLAG_CG_BUS_EVENT, SOURCE_BUS

    out = []
    for i, group in enumerate(mdf.groups):
        cg = group.channel_group
        source = cg.acq_source
        if not cg.flags & FLAG_CG_BUS_EVENT or cg.cycles_nr == 0 or source is None:
            continue
        if not source.source_type & SOURCE_BUS or source.bus_type != BUS_TYPE_CAN:
            continue
        names = {c.name for c in group.channels}
        kind = next((k for k in KINDS if k in names), None)
        if kind is not None:
            out.append(_Group(i, kind, int(cg.cycles_nr)))
    return out


def _field(rec: Any, kind: str, name: str) -> NDArray[Any] | None:
    key = f"{kind}.{name}"
    return rec[key] if key in (rec.dtype.names or ()) else None


def _payloads(rec: Any, kind: str, n: int) -> tuple[NDArray[np.int16], NDArray[np.uint8], dict[int, bytes]]:
    """Lengths, first 8 bytes (zero padded) and whole payloads beyond 8 bytes of ``n`` records."""
    data8 = np.zeros((n, 8), dtype=np.uint8)
    length, raw = _field(rec, kind, "DataLength"), _field(rec, kind, "DataBytes")
    if kind == "CAN_RemoteFrame" or length is None or raw is None:
        return np.zeros(n, dtype=np.int16), data8, {}
    if raw.dtype == np.uint8 and raw.ndim == 2:  # fixed-width bytes: the usual layout
        dlc = np.minimum(length.astype(np.int64), raw.shape[1])
        w = min(8, raw.shape[1])
        data8[:, :w] = raw[:, :w] * (np.arange(w) < dlc[:, None])
        long = {int(i): raw[i, : dlc[i]].tobytes() for i in np.flatnonzero(dlc > 8)}
        return dlc.astype(np.int16), data8, long
    # variable-length payloads (an object array of byte strings)
    payloads = [bytes(raw[i])[: int(length[i])] for i in range(n)]
    for i, d in enumerate(payloads):
        data8[i, : min(len(d), 8)] = np.frombuffer(d[:8], dtype=np.uint8)
    return (
        np.fromiter((len(d) for d in payloads), np.int16, n),
        data8,
        {i: d for i, d in enumerate(payloads) if len(d) > 8},
    )


def chunk_of(mdf: Any, g: _Group, count: int, start_s: float) -> FrameColumns:
    """The next ``count`` records of group ``g`` as columns (channels named by their bus number)."""
    sig = mdf.get(g.kind, g.index, record_offset=g.offset, record_count=count, raw=False)
    rec = sig.samples
    n = len(rec)
    g.offset += n if n else count  # a group that yields nothing more ends
    ident = _field(rec, g.kind, "ID")
    ide, edl = _field(rec, g.kind, "IDE"), _field(rec, g.kind, "EDL")
    rtr = _field(rec, g.kind, "RTR") if g.kind == "CAN_ErrorFrame" else None
    bus = _field(rec, g.kind, "BusChannel")
    dlc, data8, long = _payloads(rec, g.kind, n)
    if bus is None:
        names: tuple[str, ...] = ("",)
        channel = np.zeros(n, dtype=np.int16)
    else:
        numbers, channel = np.unique(bus.astype(np.int64), return_inverse=True)
        names = tuple(str(int(b)) for b in numbers)
        channel = channel.astype(np.int16)
    false = np.zeros(n, dtype=bool)
    return FrameColumns(
        timestamp_s=np.asarray(sig.timestamps, dtype=np.float64) + start_s,
        channel=channel,
        channel_names=names,
        arbitration_id=(
            np.zeros(n, np.uint32) if ident is None else (ident.astype(np.int64) & ID_MASK).astype(np.uint32)
        ),
        extended=false if ide is None else ide.astype(bool),
        remote=np.full(n, g.kind == "CAN_RemoteFrame") if rtr is None else rtr.astype(bool),
        error=np.full(n, g.kind == "CAN_ErrorFrame"),
        fd=false if edl is None else edl.astype(bool),
        dlc=dlc,
        data=data8,
        long_data=long,
    )


def _merge(parts: list[FrameColumns]) -> FrameColumns:
    """Frames of the groups (in the groups' order) by time, a tie kept in that order (stable)."""
    both = FrameColumns.concat(parts)
    return both.take(np.argsort(both.timestamp_s, kind="stable"))


def iter_mf4_columns(mdf: Any, chunk_frames: int, first_frames: int | None = None) -> Iterator[FrameColumns]:
    """The CAN frames of an open MDF as chunks of columns in python-can's order (see the module);
    each group's first read ``first_frames`` long when given (a replay starts on it sooner)."""
    start_s = float(mdf.header.start_time.timestamp())
    groups = can_groups(mdf)
    while True:
        for g in groups:  # every group with more to read holds a chunk it has not merged yet
            if g.more and (g.pending is None or len(g.pending) == 0):
                first = g.offset == 0 and first_frames is not None
                g.pending = chunk_of(mdf, g, min(first_frames, chunk_frames) if first else chunk_frames, start_s)
        live = [g for g in groups if g.pending is not None and len(g.pending)]
        if not live:
            return
        if len(live) == 1 and not any(g.more for g in groups if g is not live[0]):
            g = live[0]  # one group left: its chunks as they are
            out, g.pending = g.pending, None
            assert out is not None
            yield out
            continue
        # Everything earlier than the first last-time among groups that read on is complete: a
        # record at that very time may still follow in such a group, before a later group's tie.
        ends = [float(g.pending.timestamp_s[-1]) for g in live if g.more]  # type: ignore[union-attr]
        horizon = min(ends) if ends else np.inf
        parts = []
        for g in live:
            assert g.pending is not None
            cut = len(g.pending) if horizon == np.inf else int(np.searchsorted(g.pending.timestamp_s, horizon))
            if cut:
                parts.append(g.pending.take(np.arange(cut)))
                g.pending = g.pending.take(np.arange(cut, len(g.pending)))
        if parts:
            yield _merge(parts)
            continue
        # nothing before the horizon: the groups ending at it read on (their chunk grows)
        for g in live:
            assert g.pending is not None
            if g.more and float(g.pending.timestamp_s[-1]) == horizon:
                g.pending = FrameColumns.concat([g.pending, chunk_of(mdf, g, chunk_frames, start_s)])


def preload() -> None:
    """What reading an MF4 needs, imported ahead (a reader process's start, :mod:`cmcan.io.readproc`);
    asammdf's own log of a file it cannot read kept quiet: the reader's error says it in one line."""
    logging.getLogger("asammdf").setLevel(logging.CRITICAL)
    with contextlib.suppress(ImportError):  # without it, the reading says which extra to install
        import asammdf  # noqa: F401


def open_mdf(path: Path) -> Any:
    """The file opened by asammdf (its MF4 support switched on for python-can too)."""
    from cmcan.io import mf4support

    mf4support.enable()
    from asammdf import MDF

    # asammdf decodes the bus logging into signals at open by default: not needed for raw frames
    return MDF(str(path), process_bus_logging=False)
