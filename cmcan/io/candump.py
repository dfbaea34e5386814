"""CAN logs: writing the ``candump -l`` format fast, reading any format python-can's LogReader reads.

Whatever the format, a log that cannot be read whole is an error naming the file
(:class:`LogError`): a truncated or corrupt file never replays its readable part as if it were all.
"""

from __future__ import annotations

import gzip
import math
import re
import zlib
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cmcan.errors import CmcanError, Kind
from cmcan.frame import Frame, FrameColumns, from_message
from cmcan.io import native
from cmcan.io import textcols as tc

# The formats python-can reads (by suffix, also gzipped text formats); .log is candump -l.
LOG_FORMATS = (".log", ".asc", ".blf", ".trc", ".csv", ".db", ".mf4")


class LogError(CmcanError, ValueError):
    """A CAN log cannot be read (truncated, corrupt, not of its format); ``str()`` names the file."""

    kind = Kind.DATA


def write_candump(
    path: str | Path,
    timestamp_s: NDArray[np.float64],
    arbitration_id: NDArray[np.int64],
    dlc: NDArray[np.int64],
    data: NDArray[np.uint8],
    channel: str | Sequence[str] = "can0",
    extended: NDArray[np.bool_] | None = None,
) -> int:
    """Write frames as ``candump -l`` does: ``(1436509052.249713) can0 100#0011223344556677``, a 29-bit
    identifier with 8 hex digits (``18FEF100#...``). ``channel`` is one name or one per frame;
    ``extended`` says which identifiers are 29-bit (None: those above 0x7FF).

    Written to a temporary file then renamed, so an existing log is never left half-written.
    """
    p = Path(path)
    hexdata = _hex_rows(data, dlc)
    ext = (np.asarray(arbitration_id) > 0x7FF) if extended is None else np.asarray(extended, dtype=bool)
    per_frame = not isinstance(channel, str)
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "w", encoding="ascii", newline="\n") as f:
        chunk = 200_000
        for a in range(0, len(timestamp_s), chunk):
            b = min(a + chunk, len(timestamp_s))
            chans = list(channel[a:b]) if per_frame else [channel] * (b - a)  # type: ignore[index]
            lines = [
                f"({ts:017.6f}) {ch} {cid:08X}#{hx}\n" if e else f"({ts:017.6f}) {ch} {cid:03X}#{hx}\n"
                for ts, ch, cid, e, hx in zip(
                    timestamp_s[a:b].tolist(),
                    chans,
                    arbitration_id[a:b].tolist(),
                    ext[a:b].tolist(),
                    hexdata[a:b],
                    strict=True,
                )
            ]
            f.writelines(lines)
    tmp.replace(p)
    return len(timestamp_s)


def candump_line(f: Frame, channel: str | None = None, default_channel: str = "can0") -> str:
    """One frame as ``candump -l`` writes it: on ``channel`` if given, else on its own (frames with no
    channel on ``default_channel``); CAN FD as ``##`` with its flags digit, remote as ``R``, an error
    frame with the error flag in its identifier."""
    ch = channel or f.channel or default_channel
    cid = f"{f.arbitration_id:08X}" if f.extended else f"{f.arbitration_id:03X}"
    if f.error:
        cid = f"{CAN_ERR_FLAG | CAN_ERR_BUSERROR:08X}"
    if f.remote:
        return f"({f.timestamp_s:017.6f}) {ch} {cid}#R\n"
    if f.fd:
        return f"({f.timestamp_s:017.6f}) {ch} {cid}##0{f.data.hex().upper()}\n"
    return f"({f.timestamp_s:017.6f}) {ch} {cid}#{f.data.hex().upper()}\n"


def write_frames(path: str | Path, frames: Iterable[Frame], default_channel: str = "can0") -> int:
    """Write :class:`Frame` objects as a ``candump -l`` log, each on its own channel (frames with no
    channel on ``default_channel``); a temporary file renamed into place."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    n = 0
    with open(tmp, "w", encoding="ascii", newline="\n") as out:
        for f in frames:
            out.write(candump_line(f, None, default_channel))
            n += 1
    tmp.replace(p)
    return n


_HEX = np.frombuffer(b"0123456789ABCDEF", dtype=np.uint8)


def candump_lines(cols: FrameColumns, channel: str | None = None) -> str:
    """``candump_line`` of every frame, with arrays: classic data frames stamped in [1e9, 1e10) s
    (every frame cmcan emits); anything else goes through ``candump_line``."""
    n = len(cols)
    if n == 0:
        return ""
    t = cols.timestamp_s
    with np.errstate(invalid="ignore"):
        slow = cols.remote | cols.fd | cols.error | (cols.dlc > 8) | ~((t >= 1e9) & (t < 1e10))
    fast = np.flatnonzero(~slow)
    text = ""
    if len(fast):
        one = cols.channel_names[0] if len(cols.channel_names) == 1 else ""
        ch = (channel or one or "can0").encode("ascii")
        if not channel and len(cols.channel_names) != 1:  # frames of several buses: per frame
            slow[:] = True
            fast = fast[:0]
        elif (
            native.LIB is not None
            and (
                got := native.format_rows(
                    len(fast),
                    [
                        native.TextColumn(native.FIXED, t[fast], b"(", 6),
                        native.TextColumn(
                            native.HEX_ID, cols.arbitration_id[fast], b") " + ch + b" ", widths=cols.extended[fast]
                        ),
                        native.TextColumn(native.HEX_DATA, cols.data[fast], b"#", widths=cols.dlc[fast]),
                    ],
                    b"\n",
                )
            )
            is not None
        ):  # the same lines by the C formatter, which holds no GIL
            text = got.decode("ascii")
        else:
            ts = tc.fixed(t[fast], 6)
            cid = cols.arbitration_id[fast].astype(np.int64)
            ids = np.empty((len(fast), 8), dtype=np.uint8)
            for k in range(8):
                ids[:, 7 - k] = _HEX[(cid >> (4 * k)) & 0xF]
            id_col = tc.Column(ids, np.where(cols.extended[fast], 8, 3).astype(np.int64))
            data = cols.data[fast]
            nib = np.empty((len(fast), 16), dtype=np.uint8)
            nib[:, 0::2] = _HEX[data >> 4]
            nib[:, 1::2] = _HEX[data & 0xF]
            width = 2 * cols.dlc[fast].astype(np.int64)
            right = np.full((len(fast), 16), 0x20, dtype=np.uint8)
            col = np.arange(16)[None, :]
            src = col - (16 - width)[:, None]
            take = src >= 0
            right[take] = nib[np.nonzero(take)[0], src[take]]
            data_col = tc.Column(right, width)
            text = tc.rows([b"(", ts, b") " + ch + b" ", id_col, b"#", data_col], end=b"\n").decode("ascii")
    if not slow.any():
        return text
    lines = text.splitlines(keepends=True)
    out: list[str] = []
    it = iter(lines)
    for i in range(n):
        out.append(candump_line(cols.frame(i), channel) if slow[i] else next(it))
    return "".join(out)


def _hex_rows(data: NDArray[np.uint8], dlc: NDArray[np.int64]) -> list[str]:
    full = [bytes(r).hex().upper() for r in data]
    if np.all(dlc == data.shape[1]):
        return full
    return [h[: 2 * int(n)] for h, n in zip(full, dlc.tolist(), strict=True)]


CAN_ERR_FLAG = 0x20000000
CAN_ERR_BUSERROR = 0x00000080
# A candump timestamp: seconds in parentheses, a plain decimal (an exponent is tolerated); python-can
# takes whatever sits between the first and last character, which turns a line without one into an
# invented time.
# No candump line comes near this (CAN FD's 64 bytes are 128 hex digits): a longer one is not a log.
MAX_LINE_BYTES = 4096
_STAMP = re.compile(r"\(([0-9]+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)?)\)")


def parse_candump_line(line: str, path: Path | str, n: int) -> Frame | None:
    """One ``candump -l`` line as python-can's ``CanutilsLogReader`` reads it (None for a blank
    line), except that the timestamp must be one and that every error frame is one (see below);
    ValueError names the file and line."""
    parts = line.split()
    if not parts:
        return None
    try:
        stamp, channel, frame = parts[0], parts[1], parts[2]
        m = _STAMP.fullmatch(stamp)
        if m is None:
            raise ValueError(stamp)
        t = float(m.group(1))
        if not math.isfinite(t):
            raise ValueError(stamp)
        cid_s, data = frame.split("#", 1)
        cid = int(cid_s, 16)
    except (IndexError, ValueError):
        raise ValueError(f"{path}: line {n}: not a candump -l line: {line.strip()[:80]!r}") from None
    fd = data[:1] == "#"
    if fd:  # CAN FD: '##' and one flags digit
        data = data[2:]
    remote = data[:1] in ("R", "r")
    if remote:
        payload = b""
    else:
        try:
            payload = bytes.fromhex(data)
        except ValueError:
            raise ValueError(f"{path}: line {n}: bad data {data[:40]!r}") from None
    if cid & CAN_ERR_FLAG:
        # SocketCAN marks an error frame by CAN_ERR_FLAG in its identifier, whatever its class (bus
        # error, controller problem, bus-off...), as the daemon receives it; python-can's reader takes
        # only bus errors for one and reads the others as frames of identifier 0x4, 0x40...
        return Frame(t, channel, 0, True, False, True, False, b"")
    return Frame(t, channel, cid & 0x1FFFFFFF, len(cid_s) > 3, remote, False, fd, payload)


def _open_text(p: Path):  # type: ignore[no-untyped-def]
    opener = gzip.open if p.suffix == ".gz" else open
    return opener(p, "rt", encoding="ascii", errors="replace")  # type: ignore[operator]


def lines_before_failure(path: str | Path) -> int:
    """How many lines of a log that cannot be read to its end (a truncated .gz) are read before it
    fails, read as :func:`iter_candump` reads them: both readers name the same line."""
    n = 0
    try:
        with _open_text(Path(path)) as f:
            while f.readline(MAX_LINE_BYTES + 1):
                n += 1
    except (EOFError, OSError, zlib.error):
        pass
    return n


def iter_candump(path: str | Path) -> Iterator[Frame]:
    """Frames of a ``candump -l`` log, with the semantics of python-can's ``CanutilsLogReader``
    (tests check both agree) but about three times faster: it builds no ``can.Message``."""
    p = Path(path)
    n = 0
    try:
        with _open_text(p) as f:
            while line := f.readline(MAX_LINE_BYTES + 1):
                n += 1
                if len(line) > MAX_LINE_BYTES:
                    raise LogError(f"{p}: line {n}: longer than {MAX_LINE_BYTES} bytes: not a candump -l log")
                frame = parse_candump_line(line, p, n)
                if frame is not None:
                    yield frame
    except (EOFError, gzip.BadGzipFile, zlib.error) as exc:  # a truncated or corrupt .gz
        raise LogError(f"{p}: cannot read past line {n}: {exc} (truncated or corrupt compressed log)") from None


def iter_frames(path: str | Path) -> Iterator[Frame]:
    """Frames of any log python-can reads; candump logs (.log, .log.gz) through the fast reader.
    A log that cannot be read to its end raises :class:`LogError` (a ValueError) naming the file."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: log file not found")
    if p.name.endswith((".log", ".log.gz")):
        yield from iter_candump(p)
        return
    yield from _python_can_frames(p)


def _python_can_frames(p: Path) -> Iterator[Frame]:
    """A log through python-can's reader for its format, every failure of it said in one line."""
    import can

    fmt = p.suffixes[-2] if p.suffix == ".gz" and len(p.suffixes) > 1 else p.suffix
    if fmt.lower() not in LOG_FORMATS:
        raise LogError(f"{p}: unknown CAN log format {fmt or '(no suffix)'!r}; cmcan reads {', '.join(LOG_FORMATS)}")
    if fmt.lower() == ".blf":
        from cmcan.io.blf import check_blf

        try:
            check_blf(p)
        except ValueError as exc:
            raise LogError(str(exc)) from None
    n = 0
    try:
        with can.LogReader(str(p)) as reader:
            for m in reader:
                if not math.isfinite(m.timestamp):
                    raise LogError(f"{p}: frame {n + 1}: timestamp {m.timestamp!r} is not a time")
                if not 0 <= m.arbitration_id <= 0x1FFFFFFF or len(m.data) > 64:
                    raise LogError(
                        f"{p}: frame {n + 1}: not a CAN frame (identifier {m.arbitration_id}, {len(m.data)} data bytes)"
                    )
                n += 1
                yield from_message(m)
            if getattr(reader, "_tail", b""):  # BLFReader: an object left incomplete at the end
                raise LogError(f"{p}: truncated: the last frame of the file is incomplete")
    except CmcanError:
        raise
    except NotImplementedError as exc:  # python-can without the package for this format (.mf4: asammdf)
        how = "the 'mf4' extra: pip install 'cmcan[mf4]'" if fmt.lower() == ".mf4" else "a package python-can lacks"
        raise CmcanError(f"{p}: reading {fmt} logs needs {how} ({exc})", Kind.UNAVAILABLE) from None
    except Exception as exc:  # each reader has its own exceptions (BLFParseError, sqlite3, asammdf, struct, ...)
        where = f" after frame {n}" if n else ""
        raise LogError(f"{p}: cannot read as a {fmt} log{where}: {type(exc).__name__}: {exc}") from None
