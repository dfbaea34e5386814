"""Bus-logging MF4 (ASAM MDF 4) files straight into columns, through asammdf's array access.

python-can's ``MF4Reader`` hands over one ``Message`` at a time (about 15 us a frame). This reads the
same records in chunks of ``chunk_frames`` and turns each chunk into
:class:`cmcan.can.frame.FrameColumns` with array operations. It gives exactly the frames python-can's
reader gives, and in its order (a test holds the two equal):

- every channel group flagged as a bus event with a CAN source and records: ``CAN_DataFrame`` groups
  (classic and FD: ``EDL``), ``CAN_ErrorFrame`` and ``CAN_RemoteFrame`` groups;
- a frame's time is the record's time plus the file's start time; its identifier the ``ID`` masked
  to 29 bits; its payload ``DataBytes`` cut to ``DataLength``; its channel the ``BusChannel`` number
  as text (none without that channel); a remote frame carries no payload;
- the groups merged in time order, a tie in the order of the groups (python-can merges its
  per-group iterators with ``heapq.merge``, which is stable so), each group read a chunk at a time, so
  memory is bounded by a chunk per group however large the file.

A chunk's records are asammdf's to find and inflate (``_load_data``: the group's record bytes from
``record_offset``, in one fragment or a few). Where every field the frames need is plain (an unsigned
Intel integer of 1, 2 or 4 whole bytes, a fixed byte array, no conversion: python-can's writer's layout
and the common one), each is read straight from those bytes at the channel's byte offset, which is
what the structure's record type holds for it: only the fields used, and of the payload its first 8
bytes and the longer payloads (the structure ``MDF.get`` copies whole was a third of the reading).
Any other layout (bit fields, a variable-length payload, a conversion, big-endian fields) and an
asammdf without that access read the chunk with ``MDF.get(..., record_offset, record_count)``, as
python-can does. Both paths make the columns with one function (:func:`_columns`); a test holds
them equal.

The file's checks are those of python-can's
readers, the same functions (:func:`cmcan.io.candump.not_frames`, applied in
:func:`cmcan.io.columns.mf4_chunks`): a time that is not finite, a payload longer than CAN FD's 64
bytes or too many channels is a :class:`cmcan.io.candump.LogError` naming the frame.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can.frame import FrameColumns

KINDS = ("CAN_DataFrame", "CAN_ErrorFrame", "CAN_RemoteFrame")
ID_MASK = 0x1FFFFFFF


@dataclass(frozen=True)
class _Layout:
    """Where a group's fields lie in its records, for the fields read straight from the bytes:
    ``uints`` maps a field's name to its (byte offset, size in bytes); ``payload`` is the byte
    array's (byte offset, width) or None."""

    record_size: int
    uints: dict[str, tuple[int, int]]
    payload: tuple[int, int] | None


@dataclass
class _Group:
    """One channel group of CAN records read a chunk at a time, and what of it is not yet merged."""

    index: int
    kind: str
    records: int
    layout: _Layout | None = None  # None: read through ``MDF.get``
    offset: int = 0  # records read so far
    pending: FrameColumns | None = None

    @property
    def more(self) -> bool:
        return self.offset < self.records


UINT_FIELDS = ("ID", "IDE", "EDL", "RTR", "BusChannel", "DataLength")


def layout_of(mdf: Any, group: Any, kind: str) -> _Layout | None:
    """The group's fields as plain bytes of its records, or None where any is not plain (see the
    module) or asammdf cannot hand over a chunk's record bytes."""
    from asammdf.blocks import v4_constants as v4c

    inner = getattr(mdf, "_mdf", None)
    if not hasattr(inner, "_load_data") or getattr(group, "uses_ld", False):
        return None
    cg = group.channel_group
    samples = int(cg.samples_byte_nr)
    by_name: dict[str, Any] = {}
    for ch in group.channels:
        if ch.name in by_name:
            return None  # a name twice: which one get() takes is asammdf's to say
        by_name[ch.name] = ch
    uints: dict[str, tuple[int, int]] = {}
    payload = None
    for name in (*UINT_FIELDS, "DataBytes"):
        ch = by_name.get(f"{kind}.{name}")
        if ch is None:
            continue
        if ch.channel_type != v4c.CHANNEL_TYPE_VALUE or ch.conversion is not None:
            return None
        byte, bit, bits = int(ch.byte_offset), int(ch.bit_offset), int(ch.bit_count)
        if bit or bits % 8 or byte + bits // 8 > samples:
            return None  # a bit field: the structure's view and the channel's reading differ
        if name == "DataBytes":
            if ch.data_type != v4c.DATA_TYPE_BYTEARRAY or not bits:
                return None
            payload = (byte, bits // 8)
        elif ch.data_type != v4c.DATA_TYPE_UNSIGNED_INTEL or bits not in (8, 16, 32):
            return None
        else:
            uints[name] = (byte, bits // 8)
    return _Layout(samples + int(cg.invalidation_bytes_nr), uints, payload)


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
            out.append(_Group(i, kind, int(cg.cycles_nr), layout_of(mdf, group, kind)))
    return out


def _uint(rec: NDArray[np.uint8], byte: int, size: int) -> NDArray[Any]:
    """A little-endian unsigned field of ``size`` bytes of every record: what the structure's own
    record type (asammdf's and python-can's reading) holds for it."""
    if size == 1:
        return rec[:, byte]
    return np.ascontiguousarray(rec[:, byte : byte + size]).view(f"<u{size}")[:, 0]


def _payloads(
    kind: str, n: int, length: NDArray[Any] | None, raw: Any
) -> tuple[NDArray[np.int16], NDArray[np.uint8], dict[int, bytes]]:
    """Lengths, first 8 bytes (zero padded) and whole payloads beyond 8 bytes of ``n`` records."""
    data8 = np.zeros((n, 8), dtype=np.uint8)
    if kind == "CAN_RemoteFrame" or length is None or raw is None:
        return np.zeros(n, dtype=np.int16), data8, {}
    if raw.dtype == np.uint8 and raw.ndim == 2:  # fixed-width bytes: the usual layout
        dlc = np.minimum(length.astype(np.int64), raw.shape[1])
        w = min(8, raw.shape[1])
        data8[:, :w] = raw[:, :w]
        short = np.flatnonzero(dlc < w)  # bytes beyond the length are not the frame's
        if short.size:
            data8[short] *= np.arange(8) < dlc[short, None]
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


def _codes(bus: NDArray[Any]) -> tuple[NDArray[Any], NDArray[np.int16]]:
    """The distinct bus numbers in order and each record's index among them (``np.unique`` with
    ``return_inverse``; counted rather than sorted where the numbers are small unsigned integers)."""
    if bus.dtype.kind == "u" and bus.itemsize <= 2 and len(bus):
        numbers = np.flatnonzero(np.bincount(bus))
        code = np.zeros(int(numbers[-1]) + 1, dtype=np.int16)
        code[numbers] = np.arange(len(numbers), dtype=np.int16)
        return numbers, code[bus]
    numbers, inverse = np.unique(bus.astype(np.int64), return_inverse=True)
    return numbers, inverse.astype(np.int16)


def _columns(kind: str, time_s: NDArray[Any], fields: dict[str, Any], raw: Any, start_s: float) -> FrameColumns:
    """The frames of ``len(time_s)`` records from their fields (``fields``: the integer fields by
    name, those the group has; ``raw``: the payload bytes), however they were read; a frame's time is
    its record's plus the file's start."""
    n = len(time_s)
    ident, ide, edl, bus = (fields.get(k) for k in ("ID", "IDE", "EDL", "BusChannel"))
    rtr = fields.get("RTR") if kind == "CAN_ErrorFrame" else None
    dlc, data8, long = _payloads(kind, n, fields.get("DataLength"), raw)
    if bus is None:
        names: tuple[str, ...] = ("",)
        channel = np.zeros(n, dtype=np.int16)
    else:
        numbers, channel = _codes(bus)
        names = tuple(str(int(b)) for b in numbers)
    false = np.zeros(n, dtype=bool)
    return FrameColumns(
        timestamp_s=np.asarray(time_s, dtype=np.float64) + start_s,
        channel=channel,
        channel_names=names,
        arbitration_id=(np.zeros(n, np.uint32) if ident is None else ident.astype(np.uint32) & np.uint32(ID_MASK)),
        extended=false if ide is None else ide.astype(bool),
        remote=np.full(n, kind == "CAN_RemoteFrame") if rtr is None else rtr.astype(bool),
        error=np.full(n, kind == "CAN_ErrorFrame"),
        fd=false if edl is None else edl.astype(bool),
        dlc=dlc,
        data=data8,
        long_data=long,
    )


def _chunk_by_get(mdf: Any, g: _Group, count: int, start_s: float) -> tuple[int, list[FrameColumns]]:
    sig = mdf.get(g.kind, g.index, record_offset=g.offset, record_count=count, raw=False)
    rec = sig.samples
    names = rec.dtype.names or ()
    fields = {k: rec[f"{g.kind}.{k}"] for k in UINT_FIELDS if f"{g.kind}.{k}" in names}
    raw = rec[f"{g.kind}.DataBytes"] if f"{g.kind}.DataBytes" in names else None
    return len(rec), [_columns(g.kind, sig.timestamps, fields, raw, start_s)]


def _records(mdf: Any, group: Any, offset: int, count: int) -> Iterator[Any]:
    """The group's record bytes from record ``offset`` on, ``count`` of them, as asammdf's fragments
    (inflated, transposed back). asammdf's private ``MDF4._load_data``, which its own ``get`` reads
    through: it has no public way to a chunk's records without copying each channel out of them
    (:func:`layout_of` checks it is there; the tests read every file through it and through
    ``MDF.get`` alike, so a change of its meaning fails them)."""
    return mdf._mdf._load_data(group, record_offset=offset, record_count=count)


def _chunk_by_bytes(mdf: Any, g: _Group, count: int, layout: _Layout, start_s: float) -> tuple[int, list[FrameColumns]]:
    group = mdf.groups[g.index]
    n_all, parts = 0, []
    for fragment in _records(mdf, group, g.offset, count):
        n = len(fragment.data) // layout.record_size
        if not n:
            continue
        rec = np.frombuffer(fragment.data, dtype=np.uint8, count=n * layout.record_size).reshape(n, -1)
        time_s = mdf.get_master(g.index, data=fragment, one_piece=True)
        fields = {k: _uint(rec, *spec) for k, spec in layout.uints.items()}
        raw = None if layout.payload is None else rec[:, layout.payload[0] : sum(layout.payload)]
        parts.append(_columns(g.kind, time_s, fields, raw, start_s))
        n_all += n
    return n_all, parts


def chunk_of(mdf: Any, g: _Group, count: int, start_s: float) -> FrameColumns:
    """The next ``count`` records of group ``g`` as columns (channels named by their bus number)."""
    if g.layout is not None:
        n, parts = _chunk_by_bytes(mdf, g, count, g.layout, start_s)
    else:
        n, parts = _chunk_by_get(mdf, g, count, start_s)
    g.offset += n if n else count  # a group that yields nothing more ends
    if len(parts) == 1:
        return parts[0]
    return FrameColumns.concat(parts) if parts else _columns(g.kind, np.zeros(0), {}, None, start_s)


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


# Optional modules asammdf's import pulls in that reading raw frames never uses: canmatrix's
# spreadsheet formats (openpyxl, xlrd: 0.17 s) and pandas' Arrow support (pyarrow: 0.06 s). Both
# import them inside ``try ... except ImportError`` and go on without them.
UNUSED_BY_THE_READER = ("openpyxl", "xlrd", "pyarrow")


def preload() -> None:
    """What reading an MF4 needs, imported ahead in a reader process of its own (its start,
    :mod:`cmcan.io.readproc`), and nothing it does not: the modules of :data:`UNUSED_BY_THE_READER`
    are marked absent there first (that process only reads frames; a process that already holds one
    keeps it). asammdf's own log of a file it cannot read kept quiet: the reader's error says it in
    one line."""
    logging.getLogger("asammdf").setLevel(logging.CRITICAL)
    for name in UNUSED_BY_THE_READER:
        sys.modules.setdefault(name, None)  # type: ignore[arg-type]  # "import name" raises ImportError
    with contextlib.suppress(ImportError):  # without it, the reading says which extra to install
        import asammdf  # noqa: F401


def open_mdf(path: Path) -> Any:
    """The file opened by asammdf (its MF4 support switched on for python-can too)."""
    from cmcan.io import mf4support

    mf4support.enable()
    from asammdf import MDF

    # asammdf decodes the bus logging into signals at open by default: not needed for raw frames
    return MDF(str(path), process_bus_logging=False)
