"""candump logs read in large chunks straight into arrays (the columnar replay's reader).

A chunk of the file is one numpy byte buffer; its lines are grouped by length and, within a length,
by the positions of ``)``, the second space and ``#``: every line of such a group has its fields in
the same columns, so timestamps, identifiers and payloads are parsed for the whole group at once
with array arithmetic. A line that does not fit the common shape (a timestamp in exponent notation,
trailing tokens, odd hex) goes through the line-by-line reader of :mod:`cmcan.io.candump`, which
defines the semantics; tests check both give the same frames.

Timestamps: ``(SSSSSSSSSS.ffffff)`` is read as the exact integer N = SSSSSSSSSSffffff and divided
by 10^6 in floating point, which is the correctly rounded value of the decimal, exactly what
Python's ``float()`` of the same text gives.
"""

from __future__ import annotations

import gzip
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from cmcan.can.frame import FrameColumns
from cmcan.io import native
from cmcan.io.candump import (
    CAN_ERR_FLAG,
    CUT_LINE,
    MAX_CHANNELS,
    MAX_DATA_BYTES,
    MAX_LINE_BYTES,
    Cut,
    CutHandler,
    LogError,
    lines_before_failure,
    parse_candump_line,
    report_cut,
    too_many_channels,
    truncated_error,
)

CHUNK_BYTES = 4 << 20
# the columnar replay's chunk: about 4 MiB of lines with 11-bit identifiers (the engine's cost per
# chunk is spread over more frames; its memory grows with the chunk: the 4 M-frame target)
CHUNK_LINES = 90_000
SUB_BYTES = 1 << 20  # the numpy reader parses a chunk in pieces of this size
_NIBBLE = np.full(256, 255, dtype=np.uint8)
for _i, _c in enumerate(b"0123456789ABCDEF"):
    _NIBBLE[_c] = _i
for _i, _c in enumerate(b"abcdef"):
    _NIBBLE[_c] = 10 + _i
_DIGIT = np.full(256, 255, dtype=np.uint8)
for _i, _c in enumerate(b"0123456789"):
    _DIGIT[_c] = _i


def iter_candump_columns(
    path: str | Path,
    chunk_bytes: int = CHUNK_BYTES,
    progress: Callable[[int], None] | None = None,
    chunk_lines: int | None = None,
    keep_truncated: bool = False,
    on_cut: CutHandler | None = None,
) -> Iterator[FrameColumns]:
    """The frames of a candump log (``.log`` or ``.log.gz``) in chunks of about ``chunk_bytes``, or
    with ``chunk_lines``, of about that many lines (read as that many lines' worth of bytes at the
    first chunk's mean line length, within a quarter and twice ``chunk_bytes``): the replay's
    work goes by frames, so a log of longer lines (29-bit identifiers) comes in as many chunks.
    ``progress`` is told the bytes of the file read so far. A log cut short is refused or, with
    ``keep_truncated``, read up to its last whole frame, as :func:`cmcan.io.candump.iter_candump` does."""
    p = Path(path)
    opener = gzip.open if p.suffix == ".gz" else open
    channels: dict[bytes, int] = {}
    line0 = 1
    frames = 0
    with opener(p, "rb") as f:  # type: ignore[operator]
        raw = getattr(f, "fileobj", None) or f  # for .gz: the compressed file, as its size on disk counts
        rest = b""
        size, resized = chunk_bytes, False
        while True:
            try:
                block = _read(f, size, p, line0, keep_truncated)
            except _Failed as failed:  # a compressed log that ends early: its whole lines, then the cut
                text = _whole_lines_after(p, line0 - 1)
                if text:
                    cols, n_lines = _parse(text, p, line0, channels)
                    line0 += n_lines
                    frames += len(cols)
                    if len(cols):
                        yield cols
                report_cut(Cut(str(p), line0, frames, failed.reason), on_cut)
                return
            if progress is not None:
                progress(raw.tell())
            if not block:
                break
            data = rest + block
            cut = data.rfind(b"\n") + 1
            if cut:
                cols, n_lines = _parse(data, p, line0, channels, cut)
                line0 += n_lines
                frames += len(cols)
                if len(cols):
                    yield cols
            rest = data[cut:]
            if chunk_lines and not resized and line0 > 1:  # after the first chunk: by lines
                resized = True
                per_line = cut / max(line0 - 1, 1)
                size = int(min(2 * size, max(size // 4, chunk_lines * per_line)))
            if len(rest) > MAX_LINE_BYTES:  # no newline in sight: not a text log (and memory stays bounded)
                raise LogError(f"{p}: line {line0}: longer than {MAX_LINE_BYTES} bytes: not a candump log")
        if rest.strip():  # the last line, without its line end: cut mid-line
            if len(rest) > MAX_LINE_BYTES:
                raise LogError(f"{p}: line {line0}: longer than {MAX_LINE_BYTES} bytes: not a candump log")
            if not keep_truncated:
                raise truncated_error(p, line0, CUT_LINE)
            report_cut(Cut(str(p), line0, frames, CUT_LINE), on_cut)


class _Failed(Exception):
    def __init__(self, reason: str) -> None:
        self.reason = reason


def _read(f: BinaryIO, n: int, path: Path, line: int, keep_truncated: bool = False) -> bytes:
    try:
        return f.read(n)
    except (EOFError, OSError, zlib.error) as exc:  # a truncated or corrupt .gz (BadGzipFile is an OSError)
        # the chunk failed somewhere after ``line``: the line as the line reader names it
        line = lines_before_failure(path)
        reason = f"cannot read past line {line}: {exc} (truncated or corrupt compressed log)"
        if keep_truncated:
            raise _Failed(reason) from None
        raise LogError(f"{path}: {reason}; pass --keep-truncated to read it up to its last whole frame") from None


def _whole_lines_after(path: Path, skip: int) -> bytes:
    """The whole lines of a compressed log that ends early, after its first ``skip`` lines (as the
    line reader reads them: up to the failure)."""
    out: list[bytes] = []
    n = 0
    try:
        with gzip.open(path, "rb") as f:
            while line := f.readline(MAX_LINE_BYTES + 1):
                n += 1
                if not line.endswith(b"\n"):
                    break
                if n > skip:
                    out.append(line)
    except (EOFError, OSError, zlib.error):
        pass
    return b"".join(out)


def _parse(
    text: bytes, path: Path, line0: int, channels: dict[bytes, int], length: int | None = None
) -> tuple[FrameColumns, int]:
    """:func:`parse_chunk`, a log with too many channel names refused at the line the line reader names."""
    before = set(channels)
    try:
        return parse_chunk(text, path, line0, channels, length)
    except TooManyChannels:
        seen = {k.decode("ascii", errors="replace") for k in before}
        for i, line in enumerate(text[: length or len(text)].decode("ascii", errors="replace").splitlines(), line0):
            f = parse_candump_line(line, path, i)
            if f is not None and f.channel not in seen:
                seen.add(f.channel)
                if len(seen) > MAX_CHANNELS:
                    raise too_many_channels(path, i) from None
        raise too_many_channels(path, line0) from None


def parse_chunk(
    text: bytes, path: Path, line0: int, channels: dict[bytes, int], length: int | None = None
) -> tuple[FrameColumns, int]:
    """Frames of the complete lines in ``text[:length]`` (which ends with a newline). ``channels`` maps
    channel names to codes across chunks; ``line0`` is the number of the chunk's first line.
    By the C parser when it was built, else with numpy in pieces of at most ``SUB_BYTES`` (its
    temporaries, several times the text, stay small while the engine gets large chunks)."""
    size = len(text) if length is None else length
    if native.LIB is not None:
        return _parse_native(text, size, path, line0, channels)
    if size <= SUB_BYTES:
        return _parse_numpy(text[:size] if size < len(text) else text, path, line0, channels)
    parts: list[FrameColumns] = []
    n_lines = start = 0
    while start < size:
        cut = text.rfind(b"\n", start, min(size, start + SUB_BYTES)) + 1
        if cut <= start:  # a line longer than a piece (the slow path will say what is wrong with it)
            cut = text.find(b"\n", start) + 1
        cols, n = _parse_numpy(text[start:cut], path, line0 + n_lines, channels)
        n_lines += n
        start = cut
        if len(cols):
            parts.append(cols)
    if not parts:
        return _Out(0).columns(channels), n_lines
    return (parts[0] if len(parts) == 1 else FrameColumns.concat(parts)), n_lines


def _parse_native(
    text: bytes, size: int, path: Path, line0: int, channels: dict[bytes, int]
) -> tuple[FrameColumns, int]:
    got = native.parse(text, size)
    n = got.n_lines
    out = _Out(n)
    codes = np.array([_code(channels, name) for name in got.names], dtype=np.int16)
    out.present = got.fast
    out.t, out.cid, out.ext, out.dlc, out.data = got.timestamp_s, got.arbitration_id, got.extended, got.dlc, got.data
    if len(codes):
        out.ch = codes[np.maximum(got.chan, 0)]
    if not got.fast.all():
        _slow_lines(
            text,
            np.flatnonzero(np.frombuffer(text, dtype=np.uint8, count=size) == 10),
            np.flatnonzero(~got.fast),
            out,
            path,
            line0,
            channels,
        )
    return out.columns(channels), n


def _slow_lines(
    text: bytes,
    ends: NDArray[np.int64],
    slow: Iterable[int],
    out: _Out,
    path: Path,
    line0: int,
    channels: dict[bytes, int],
) -> None:
    """Lines not of the common shape, by the line reader (which defines what a line means)."""
    for i in sorted(slow):
        start = int(ends[i - 1]) + 1 if i else 0
        line = text[start : int(ends[i])].decode("ascii", errors="replace")
        f = parse_candump_line(line, path, line0 + i)
        if f is None:
            continue
        out.set_one(i, f, channels)


def _parse_numpy(text: bytes, path: Path, line0: int, channels: dict[bytes, int]) -> tuple[FrameColumns, int]:
    buf = np.frombuffer(text, dtype=np.uint8)
    width = text.find(b"\n") + 1
    n_lines = len(buf) // width
    slow: list[int] = []
    if len(buf) == width * n_lines and (buf[width - 1 :: width] == 10).all() and np.count_nonzero(buf == 10) == n_lines:
        # every line equally long (the usual candump log): the chunk is a matrix as it is
        ends = np.arange(width - 1, len(buf), width)
        out = _Out(n_lines)
        slow += _parse_group(buf.reshape(n_lines, width)[:, :-1], np.arange(n_lines), out, channels)
    else:
        ends = np.flatnonzero(buf == 10)
        n_lines = len(ends)
        out = _Out(n_lines)
        starts = np.empty_like(ends)
        starts[0] = 0
        starts[1:] = ends[:-1] + 1
        lengths = ends - starts
        for length in np.unique(lengths):
            idx = np.flatnonzero(lengths == length)
            if length < 8:
                slow += idx.tolist()
                continue
            for k in range(0, len(idx), _BATCH):  # gather a bounded number of lines at a time
                sub = idx[k : k + _BATCH]
                rows = buf[starts[sub, None] + np.arange(length, dtype=np.int64)]
                slow += _parse_group(rows, sub, out, channels)
    _slow_lines(text, ends, slow, out, path, line0, channels)
    return out.columns(channels), n_lines


_BATCH = 1 << 16


class _Out:
    """Per-line result arrays (in line order); lines without a frame stay marked absent."""

    def __init__(self, n: int) -> None:
        self.present = np.zeros(n, dtype=bool)
        self.t = np.zeros(n)
        self.ch = np.zeros(n, dtype=np.int16)
        self.cid = np.zeros(n, dtype=np.uint32)
        self.ext = np.zeros(n, dtype=bool)
        self.rtr = np.zeros(n, dtype=bool)
        self.err = np.zeros(n, dtype=bool)
        self.fd = np.zeros(n, dtype=bool)
        self.dlc = np.zeros(n, dtype=np.int16)
        self.data = np.zeros((n, 8), dtype=np.uint8)
        self.long: dict[int, bytes] = {}  # CAN FD payloads beyond 8 bytes, by line

    def set_one(self, i: int, f: object, channels: dict[bytes, int]) -> None:
        from cmcan.can.frame import Frame

        assert isinstance(f, Frame)
        self.present[i] = True
        self.t[i] = f.timestamp_s
        # the name as bytes that decode back to it (``columns``): a character the line reader
        # replaced (U+FFFD, from a byte that is not ASCII) stands for one such byte
        name = bytes(ord(ch) if ord(ch) < 128 else 0xFF for ch in f.channel)
        self.ch[i] = _code(channels, name)
        self.cid[i] = f.arbitration_id
        self.ext[i], self.rtr[i], self.err[i], self.fd[i] = f.extended, f.remote, f.error, f.fd
        self.dlc[i] = len(f.data)
        if len(f.data) > 8:
            self.long[i] = f.data
        if f.data:  # the first 8 bytes of any payload (FrameColumns.data)
            self.data[i, : min(len(f.data), 8)] = np.frombuffer(f.data[:8], dtype=np.uint8)

    def columns(self, channels: dict[bytes, int]) -> FrameColumns:
        keep = slice(None) if self.present.all() else self.present
        names = tuple(k.decode("ascii", errors="replace") for k in sorted(channels, key=channels.__getitem__))
        long = {}
        if self.long:
            pos = np.cumsum(self.present) - 1
            long = {int(pos[i]): v for i, v in self.long.items()}
        return FrameColumns(
            timestamp_s=self.t[keep],
            channel=self.ch[keep],
            channel_names=names,
            arbitration_id=self.cid[keep],
            extended=self.ext[keep],
            remote=self.rtr[keep],
            error=self.err[keep],
            fd=self.fd[keep],
            dlc=self.dlc[keep],
            data=self.data[keep],
            long_data=long,
        )


class TooManyChannels(ValueError):
    """More distinct channel names than a CAN log has (``MAX_CHANNELS``): the codes are int16."""


def _code(channels: dict[bytes, int], name: bytes) -> int:
    if name not in channels:
        if len(channels) >= MAX_CHANNELS:
            raise TooManyChannels(name)
        channels[name] = len(channels)
    return channels[name]


def _unique(keys: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """np.unique(return_inverse=True) with a shortcut for the usual case of one value."""
    if len(keys) and (keys == keys[0]).all():
        return keys[:1], np.zeros(len(keys), dtype=np.int64)
    u, inv = np.unique(keys, return_inverse=True)
    return u, inv.ravel()


def _shape_of(row: bytes) -> tuple[int, int, int, int] | None:
    """Columns of ')', the two spaces and '#' in one line, or None when it is not of the common form."""
    c = row.find(b")")
    a = row.find(b" ")
    b = row.find(b" ", a + 1)
    h = row.find(b"#")
    if row[:1] == b"(" and c > 0 and c + 1 == a and a + 1 < b < h and h - b - 1 in (3, 8):
        return c, a, b, h
    return None


def _parse_group(rows: NDArray[np.uint8], idx: NDArray[np.int64], out: _Out, channels: dict[bytes, int]) -> list[int]:
    """Parse lines of one length, shape by shape: the first unparsed line's field columns are
    checked on all the others (four columns and two runs, not whole lines); lines of that shape are
    parsed together, the rest tried with the next shape. Returns the lines left to the slow path."""
    slow: list[int] = []
    todo = np.arange(len(rows))
    for _ in range(8):  # a handful of shapes per length at most; beyond, the slow path
        if not len(todo):
            break
        shape = _shape_of(rows[todo[0]].tobytes())
        if shape is None:
            slow.append(int(idx[todo[0]]))
            todo = todo[1:]
            continue
        c, a, b, h = shape
        r = rows if len(todo) == len(rows) else rows[todo]  # (no copy on the first, usual, pass)
        match = (r[:, c] == ord(")")) & (r[:, a] == ord(" ")) & (r[:, b] == ord(" ")) & (r[:, h] == ord("#"))
        sel = todo if match.all() else todo[match]
        slow += _parse_shape(rows[sel], idx[sel], shape, out, channels)
        todo = todo[~match]
    slow += idx[todo].tolist()
    return slow


# -- eight characters at a time (SWAR: one uint64 per row holds eight ASCII characters) ---------------

_U = np.uint64


def _u64(block: NDArray[np.uint8]) -> NDArray[np.uint64]:
    """Rows of eight bytes as one little-endian uint64 each (first character in the lowest byte)."""
    if block.strides[1] == 1:  # a (possibly unaligned) view of each row's eight bytes, then one copy
        return block.view("<u8")[:, 0].copy()
    return np.ascontiguousarray(block).view("<u8").ravel()


def _digits8(x: NDArray[np.uint64]) -> tuple[NDArray[np.uint64], NDArray[np.bool_]]:
    """Eight ASCII decimal digits -> their value; and whether all eight were digits."""
    ok = ((x + _U(0x4646464646464646)) | (x - _U(0x3030303030303030))) & _U(0x8080808080808080) == 0
    v = x - _U(0x3030303030303030)
    v = ((v * _U(10)) + (v >> _U(8))) & _U(0x00FF00FF00FF00FF)
    v = ((v * _U(100)) + (v >> _U(16))) & _U(0x0000FFFF0000FFFF)
    v = ((v * _U(10000)) + (v >> _U(32))) & _U(0xFFFFFFFF)
    return v, ok


def _hex8(x: NDArray[np.uint64]) -> tuple[NDArray[np.uint64], NDArray[np.bool_]]:
    """Eight ASCII hex digits (upper case, as candump writes them) -> four bytes (first pair in the
    lowest byte); and whether they were exactly that (anything else takes the slow path)."""
    n = (x & _U(0x0F0F0F0F0F0F0F0F)) + _U(9) * ((x >> _U(6)) & _U(0x0101010101010101))
    # written back as upper-case hex, they must be the characters we read
    back = n + _U(0x3030303030303030) + _U(7) * (((n + _U(0x0606060606060606)) >> _U(4)) & _U(0x0101010101010101))
    ok = (back == x) & ((n & _U(0xF0F0F0F0F0F0F0F0)) == 0)
    v = ((n << _U(4)) | (n >> _U(8))) & _U(0x00FF00FF00FF00FF)
    v = (v | (v >> _U(8))) & _U(0x0000FFFF0000FFFF)
    v = (v | (v >> _U(16))) & _U(0xFFFFFFFF)
    return v, ok


def _parse_shape(
    rows: NDArray[np.uint8],
    idx: NDArray[np.int64],
    pos: tuple[int, int, int, int],
    out: _Out,
    channels: dict[bytes, int],
) -> list[int]:
    c, a, b, h = pos
    width = rows.shape[1]
    n = len(rows)
    good = rows[:, 0] == ord("(")
    # timestamp: digits, the decimal point where the first line has it, digits
    first_row = rows[0, 1:c].tobytes()
    d = first_row.find(b".")
    n_frac = c - 2 - d if d >= 0 else 0
    t = np.zeros(n)
    if d < 1 or n_frac < 1 or c - 2 > 19:  # no digits on a side of the point, or more than uint64 holds:
        # the slow path decides
        good[:] = False
    elif d == 10 and n_frac == 6:  # candump's own (SSSSSSSSSS.ffffff): two groups of eight digits
        hi, ok_hi = _digits8(_u64(rows[:, 1:9]))
        # the last two second digits and the six fraction digits: "S.ffffff" read as one word, the
        # point checked, then replaced by the digit before it (the word shifted up one byte)
        w = _u64(rows[:, 10:18])
        good &= (w >> _U(8)) & _U(0xFF) == _U(ord("."))
        lo, ok_lo = _digits8((w & _U(0xFFFFFFFFFFFF0000)) | ((w & _U(0xFF)) << _U(8)) | rows[:, 9].astype(_U))
        num = hi * _U(100_000_000) + lo
        good &= ok_hi & ok_lo & (num < _U(1 << 53))
        t = num.astype(np.float64) / 1e6
    else:
        good &= rows[:, 1 + d] == ord(".")
        # digit columns, transposed to contiguous rows: a column of a row-major block is slow to walk
        dig = _DIGIT[np.ascontiguousarray(np.concatenate([rows[:, 1 : 1 + d], rows[:, 2 + d : c]], axis=1).T)]
        good &= dig.max(axis=0) != 255
        num = np.zeros(n, dtype=np.uint64)
        ten = np.uint64(10)
        for col in dig:
            num *= ten
            num += col
        good &= num < np.uint64(1 << 53)  # below 2^53 the integer is exact as a float
        t = num.astype(np.float64) / float(10**n_frac)
    # identifier: 3 or 8 hex digits
    id_len = h - b - 1
    if h >= 8:
        # the eight characters before '#' as one word, those left of the identifier made '0'
        x = _u64(rows[:, h - 8 : h])
        keep = _U((1 << 64) - (1 << (8 * (8 - id_len))))
        hexw, ok_id = _hex8((x & keep) | (_U(0x3030303030303030) & ~keep))
        good &= ok_id
        cid = hexw.astype("<u4").byteswap().astype(np.uint64)  # first pair in the highest byte
    else:
        nib = _NIBBLE[np.ascontiguousarray(rows[:, b + 1 : h].T)]
        good &= nib.max(axis=0) != 255
        cid = np.zeros(n, dtype=np.uint64)
        four = np.uint64(4)
        for col in nib:
            cid <<= four
            cid |= col
    extended = id_len > 3
    # payload: after '#', hex pairs to the end of the line; '##f' is CAN FD, 'R' remote
    tail = rows[:, h + 1 :]
    n_tail = width - h - 1
    first = tail[:, 0] if n_tail else np.zeros(len(rows), dtype=np.uint8)
    fd = first == ord("#")
    remote = (first == ord("R")) | (first == ord("r"))
    good &= ~fd | (n_tail >= 2)
    classic = ~fd & ~remote
    data = np.zeros((len(rows), 8), dtype=np.uint8)
    dlc = np.zeros(len(rows), dtype=np.int16)
    long_rows: dict[int, bytes] = {}
    if n_tail == 16 and classic.all():  # eight data bytes on every line: two groups of eight hex digits
        lo, ok_lo = _hex8(_u64(tail[:, :8]))
        hi, ok_hi = _hex8(_u64(tail[:, 8:]))
        good &= ok_lo & ok_hi
        data = (lo | (hi << _U(32))).astype("<u8").view(np.uint8).reshape(n, 8)
        dlc[:] = 8
        classic = np.zeros(n, dtype=bool)  # done
    for kind_mask, skip in ((classic, 0), (fd, 2)):
        if not kind_mask.any():
            continue
        hexpart = tail[kind_mask, skip:]
        nib = _NIBBLE[hexpart]
        ok = ((nib != 255).all(axis=1)) & (hexpart.shape[1] % 2 == 0) & (hexpart.shape[1] <= 2 * MAX_DATA_BYTES)
        nbytes = hexpart.shape[1] // 2
        sel = np.flatnonzero(kind_mask)
        good[sel[~ok]] = False
        if hexpart.shape[1] % 2 or hexpart.shape[1] > 2 * MAX_DATA_BYTES:
            continue
        vals = (nib[:, 0::2].astype(np.uint8) << 4) | nib[:, 1::2]
        dlc[sel] = nbytes
        data[sel, : min(nbytes, 8)] = vals[:, :8]  # a longer (CAN FD) payload: its first 8 bytes too
        if nbytes > 8:
            for j, r in zip(sel.tolist(), vals, strict=True):
                long_rows[j] = bytes(r)
    # CAN FD flags digit must be hex, remote frames carry nothing
    if fd.any():
        good[fd] &= _NIBBLE[tail[fd, 1]] != 255
    err = (cid & np.uint64(CAN_ERR_FLAG)) != 0  # an error frame of any class (parse_candump_line)
    # the channel name
    ch_bytes = rows[:, a + 1 : b]
    if ch_bytes.shape[1] <= 8:  # a name of up to 8 characters is one integer
        packed = np.zeros((len(rows), 8), dtype=np.uint8)
        packed[:, : ch_bytes.shape[1]] = ch_bytes
        uniq, ch_inv = _unique(packed.view("<u8").ravel())
        names = [
            uniq_row.tobytes()[: ch_bytes.shape[1]] for uniq_row in uniq.astype("<u8").view(np.uint8).reshape(-1, 8)
        ]
    else:
        uniq_rows, ch_inv = np.unique(ch_bytes, axis=0, return_inverse=True)
        ch_inv = ch_inv.ravel()
        names = [bytes(r) for r in uniq_rows]
    codes = np.array([_code(channels, nm) for nm in names], dtype=np.int16)[ch_inv]
    # a name with white space in it is not one field: such lines are for the reader of record
    spaced = np.array([any(ch in nm for ch in (b" ", b"\t", b"\r")) for nm in names])
    if spaced.any():
        good &= ~spaced[ch_inv]

    if good.all() and not (err.any() or remote.any() or fd.any() or long_rows):
        # the usual chunk: every line a classic data frame
        cid32 = (cid & np.uint64(0x1FFFFFFF)).astype(np.uint32)
        if len(idx) == len(out.present):  # the whole chunk (the lines in order): the arrays as they are
            out.present[:] = True
            out.t, out.ch, out.cid, out.dlc, out.data = t, codes, cid32, dlc, data
            out.ext[:] = extended
            return []
        lines = idx
        out.present[lines] = True
        out.t[lines] = t
        out.ch[lines] = codes
        out.cid[lines] = cid32
        out.ext[lines] = extended
        out.dlc[lines] = dlc
        out.data[lines] = data
        return []
    g = np.flatnonzero(good)
    lines = idx[g]
    out.present[lines] = True
    out.t[lines] = t[g]
    out.ch[lines] = codes[g]
    e = err[g]
    out.err[lines] = e
    out.cid[lines] = np.where(e, 0, cid[g] & np.uint64(0x1FFFFFFF)).astype(np.uint32)
    out.ext[lines] = np.where(e, True, extended)
    out.rtr[lines] = remote[g] & ~e
    out.fd[lines] = fd[g] & ~e
    out.dlc[lines] = np.where(e | remote[g], 0, dlc[g])
    out.data[lines] = np.where((e | remote[g])[:, None], 0, data[g])
    for j, payload in long_rows.items():
        if good[j] and not err[j]:
            out.long[int(idx[j])] = payload
    return idx[~good].tolist()
