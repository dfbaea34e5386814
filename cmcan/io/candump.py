"""CAN logs: writing the ``candump -l`` format fast, reading any format python-can's LogReader reads.

Whatever the format, a log that cannot be read whole is an error naming the file and line
(:class:`LogError`): a truncated or corrupt file never replays its readable part as if it were all.
A log cut short by its writer (a logger killed, power lost: the last line of a text log without its
line end, a compressed stream or a BLF object that ends early) is refused the same way in every
format, unless the caller asks to keep it (``keep_truncated``): then the frames up to the last whole
one are read and the cut is reported (:class:`Cut`).

candump text logs are read in two layouts: ``candump -l`` files (``(1700000000.123456) can0
123#1122``, with python-can's optional direction flag) and candump's screen output saved to a file
where it carries absolute times (``candump -ta`` and ``-tA``: ``(1700000000.123456)  can0  123   [2]
11 22``). Screen output with relative times (``-td``, ``-tz``) or none is refused, saying how to
record or convert it.
"""

from __future__ import annotations

import gzip
import logging
import math
import re
import time
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can.frame import Frame, FrameColumns, from_message
from cmcan.errors import CmcanError, Kind
from cmcan.io import native
from cmcan.io import textcols as tc

log = logging.getLogger("cmcan.io")

# The formats python-can reads (by suffix, also gzipped text formats); .log is candump's.
LOG_FORMATS = (".log", ".asc", ".blf", ".trc", ".csv", ".db", ".mf4")
# Text formats whose lines end in a line end (a last line without one was cut).
TEXT_FORMATS = (".asc", ".trc", ".csv")
# A CAN FD frame carries at most 64 data bytes: a longer "frame" is not a CAN frame.
MAX_DATA_BYTES = 64
# Distinct channel (interface) names a log may have: a real log has a handful; far more is not a log.
MAX_CHANNELS = 1024


class LogError(CmcanError, ValueError):
    """A CAN log cannot be read (truncated, corrupt, not of its format); ``str()`` names the file."""

    kind = Kind.DATA


@dataclass(frozen=True)
class Cut:
    """Where a log read with ``keep_truncated`` was cut short: ``line`` (1-based) is the cut line of a
    text log (None for a binary one), ``frames`` the whole frames read before it, ``reason`` what was
    found."""

    path: str
    line: int | None
    frames: int
    reason: str

    def describe(self) -> str:
        where = f"line {self.line}" if self.line is not None else f"after frame {self.frames}"
        return f"{self.path}: {where}: {self.reason}; read up to the last whole frame ({self.frames} frames)"

    def to_dict(self) -> dict[str, object]:
        return {"file": self.path, "line": self.line, "frames_kept": self.frames, "reason": self.reason}


CutHandler = Callable[[Cut], None]


def report_cut(cut: Cut, on_cut: CutHandler | None) -> None:
    """A cut kept by ``keep_truncated``: logged as a warning and handed to the caller."""
    log.warning("%s", cut.describe())
    if on_cut is not None:
        on_cut(cut)


def truncated_error(path: Path | str, line: int | None, reason: str) -> LogError:
    """The error for a log cut short, the same in every format and reader."""
    where = f"line {line}: " if line is not None else ""
    return LogError(
        f"{path}: {where}{reason}: the log was cut short (a logger stopped mid-write?); "
        "pass --keep-truncated to read it up to its last whole frame"
    )


CUT_LINE = "the last line has no line end (cut mid-line)"


def too_many_channels(path: Path | str, line: int) -> LogError:
    return LogError(f"{path}: line {line}: more than {MAX_CHANNELS} channel names in one log: not a CAN log")


def not_frames(timestamp_s: Any, arbitration_id: Any, n_bytes: Any) -> Any:
    """Where a reader's record is no CAN frame (scalars or arrays alike): a time that is not finite,
    an identifier beyond 29 bits, more data bytes than CAN FD's 64."""
    return ~np.isfinite(timestamp_s) | (arbitration_id < 0) | (arbitration_id > 0x1FFFFFFF) | (n_bytes > MAX_DATA_BYTES)


def not_a_frame(p: Path, where: str, timestamp_s: float, arbitration_id: int, n_bytes: int) -> LogError:
    """The error for a record :func:`not_frames` refuses, naming the file and where in it."""
    if not math.isfinite(timestamp_s):
        return LogError(f"{p}: {where}: timestamp {timestamp_s!r} is not a time")
    return LogError(
        f"{p}: {where}: not a CAN frame (identifier {arbitration_id}, {n_bytes} data bytes; CAN FD carries at "
        f"most {MAX_DATA_BYTES})"
    )


def more_channels(names: set[str], new: Iterable[str]) -> bool:
    """Add a chunk's (or a frame's) channel names to those of the log so far: more than a CAN log has?"""
    names.update(new)
    return len(names) > MAX_CHANNELS


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
    n = len(timestamp_s)
    ids = np.asarray(arbitration_id)
    ext = (ids > 0x7FF) if extended is None else np.asarray(extended, dtype=bool)
    if isinstance(channel, str):
        names, codes = (channel,), np.zeros(n, dtype=np.int16)
    else:
        uniq, inv = np.unique(np.asarray(channel, dtype=str), return_inverse=True)
        names, codes = tuple(uniq.tolist()), inv.astype(np.int16)
    lengths = np.asarray(dlc, dtype=np.int16)
    data = np.asarray(data, dtype=np.uint8)
    # the first 8 bytes in the columns, longer payloads (CAN FD) whole beside them
    first8 = np.zeros((n, 8), dtype=np.uint8)
    first8[:, : min(8, data.shape[1])] = data[:, :8]
    tmp = p.with_name(p.name + ".tmp")
    no, fd = np.zeros(n, dtype=bool), lengths > 8
    with open(tmp, "w", encoding="ascii", newline="\n") as f:
        for a in range(0, n, _WRITE_ROWS):
            b = min(a + _WRITE_ROWS, n)
            cols = FrameColumns(
                timestamp_s=np.asarray(timestamp_s[a:b], dtype=np.float64),
                channel=codes[a:b],
                channel_names=names,
                arbitration_id=ids[a:b].astype(np.uint32),
                extended=ext[a:b],
                remote=no[a:b],
                error=no[a:b],
                fd=fd[a:b],
                dlc=lengths[a:b],
                data=first8[a:b],
                long_data={r - a: data[r, : lengths[r]].tobytes() for r in (np.flatnonzero(fd[a:b]) + a).tolist()},
            )
            f.write(candump_lines(cols))
    tmp.replace(p)
    return n


_WRITE_ROWS = 200_000  # frames formatted at a time: a bounded buffer, whatever the log's length


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
        # the channel: the one asked for, the log's only one, or each frame's own (a name per row)
        per_row = not channel and len(cols.channel_names) > 1
        one = cols.channel_names[0] if len(cols.channel_names) == 1 else ""
        ch = b"" if per_row else (channel or one or "can0").encode("ascii")
        codes = cols.channel[fast].astype(np.int64)
        names = [c.encode("ascii") for c in cols.channel_names]
        id_prefix = b" " if per_row else b") " + ch + b" "
        named = [native.TextColumn(native.NAME, codes, b") ", names=names)] if per_row else []
        if (
            native.LIB is not None
            and (
                got := native.format_rows(
                    len(fast),
                    [
                        native.TextColumn(native.FIXED, t[fast], b"(", 6),
                        *named,
                        native.TextColumn(
                            native.HEX_ID, cols.arbitration_id[fast], id_prefix, widths=cols.extended[fast]
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
            chan: list[tc.Column | bytes] = (
                [b") ", tc.Column.of_names(codes, dict(enumerate(cols.channel_names)))] if per_row else []
            )
            text = tc.rows([b"(", ts, *chan, id_prefix, id_col, b"#", data_col], end=b"\n").decode("ascii")
    if not slow.any():
        return text
    lines = text.splitlines(keepends=True)
    out: list[str] = []
    it = iter(lines)
    for i in range(n):
        out.append(candump_line(cols.frame(i), channel) if slow[i] else next(it))
    return "".join(out)


CAN_ERR_FLAG = 0x20000000
CAN_ERR_BUSERROR = 0x00000080
# A candump timestamp: seconds in parentheses, a plain decimal (an exponent is tolerated); python-can
# takes whatever sits between the first and last character, which turns a line without one into an
# invented time.
# No candump line comes near this (CAN FD's 64 bytes are 128 hex digits, 192 characters on screen):
# a longer one is not a log.
MAX_LINE_BYTES = 4096
_STAMP = re.compile(r"\(([0-9]+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)?)\)")
# candump's screen output (``candump -ta can0 > file``): a timestamp in parentheses (which -tA writes
# with a space: a date and a time), the channel, with -x a direction and two flags, the identifier, the
# length in brackets (two digits for CAN FD) and the bytes in hex, then -a's ASCII or -e's error text.
_SCREEN = re.compile(
    r"\s*(?:\((?P<stamp>[^()]*)\)\s+)?(?P<chan>\S+)\s+(?:(?:RX|TX)\s+\S\s+\S\s+)?"
    r"(?P<id>[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})\s+\[(?P<len>[0-9]{1,2})\](?P<rest>.*)"
)
_EPOCH = re.compile(r"[0-9]{10}\.[0-9]{1,9}")  # -ta: %010llu.%06llu
_WALL = re.compile(r"([0-9]{4}-[0-9]{2}-[0-9]{2} [0-9]{2}:[0-9]{2}:[0-9]{2})\.([0-9]{1,9})")  # -tA, local time
_HEXBYTE = re.compile(r"[0-9A-Fa-f]{2}")
RECORD_HINT = (
    "record with candump -l (a log file with absolute times: candump -l can0) or save candump -ta's "
    "screen output; docs/formats.md shows how to convert a -tz log whose start time you know"
)


def parse_candump_line(line: str, path: Path | str, n: int) -> Frame | None:
    """One line of a candump log as python-can's ``CanutilsLogReader`` reads a ``candump -l`` line
    (None for a blank line), except that the timestamp must be one, every error frame is one and
    nothing but the optional direction flag may follow the frame; or one line of candump's screen
    output with absolute times (``-ta``, ``-tA``). ValueError names the file and line."""
    if len(line) > MAX_LINE_BYTES:
        raise ValueError(f"{path}: line {n}: longer than {MAX_LINE_BYTES} bytes: not a candump log")
    parts = line.split()
    if not parts:
        return None
    if len(parts) >= 4 and "#" not in parts[2]:
        frame = _screen_line(line, path, n)
        if frame is not None:
            return frame
    try:
        # python-can's reader allows a trailing direction flag (R or T) and nothing else
        if not (len(parts) == 3 or (len(parts) == 4 and parts[3] in ("R", "T", "r", "t"))):
            raise ValueError(line)
        stamp, channel, frame_text = parts[0], parts[1], parts[2]
        m = _STAMP.fullmatch(stamp)
        if m is None:
            raise ValueError(stamp)
        t = float(m.group(1))
        if not math.isfinite(t):
            raise ValueError(stamp)
        cid_s, data = frame_text.split("#", 1)
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
        _check_length(len(payload), path, n)
    return _frame(t, channel, cid, len(cid_s) > 3, remote, fd, payload)


def _check_length(n_bytes: int, path: Path | str, n: int) -> None:
    if n_bytes > MAX_DATA_BYTES:
        raise ValueError(
            f"{path}: line {n}: {n_bytes} data bytes: not a CAN frame (CAN FD carries at most {MAX_DATA_BYTES})"
        )


def _frame(t: float, channel: str, cid: int, extended: bool, remote: bool, fd: bool, payload: bytes) -> Frame:
    if cid & CAN_ERR_FLAG:
        # SocketCAN marks an error frame by CAN_ERR_FLAG in its identifier, whatever its class (bus
        # error, controller problem, bus-off...), as the daemon receives it; python-can's reader takes
        # only bus errors for one and reads the others as frames of identifier 0x4, 0x40...
        return Frame(t, channel, 0, True, False, True, False, b"")
    return Frame(t, channel, cid & 0x1FFFFFFF, extended, remote, False, fd, payload)


def _screen_line(line: str, path: Path | str, n: int) -> Frame | None:
    """A line of candump's screen output, or None when the line is not of that shape."""
    m = _SCREEN.fullmatch(line.rstrip("\r\n"))
    if m is None:
        return None
    stamp = m.group("stamp")
    if stamp is None:
        raise ValueError(f"{path}: line {n}: candump screen output without timestamps: {RECORD_HINT}")
    stamp = stamp.strip()
    if _EPOCH.fullmatch(stamp):
        t = float(stamp)
    elif (w := _WALL.fullmatch(stamp)) is not None:
        # -tA: the recording machine's local time (the TZ environment variable names another zone)
        t = time.mktime(time.strptime(w.group(1), "%Y-%m-%d %H:%M:%S")) + float("0." + w.group(2))
    else:
        raise ValueError(
            f"{path}: line {n}: candump screen output with relative times ({stamp!r}: candump -td or -tz): "
            f"cmcan needs absolute times; {RECORD_HINT}"
        )
    length = int(m.group("len"))
    fd = len(m.group("len")) == 2  # candump writes a CAN FD frame's length with two digits
    rest = m.group("rest").split()
    remote = rest[:2] == ["remote", "request"]
    if remote:
        payload = b""
    else:
        _check_length(length, path, n)
        hex_bytes = rest[:length]
        if len(hex_bytes) < length or not all(_HEXBYTE.fullmatch(b) for b in hex_bytes):
            raise ValueError(f"{path}: line {n}: [{length}] data bytes expected, found {' '.join(rest[:length])!r}")
        tail = rest[length:]
        # after the bytes: -a's ASCII in quotes or -e's error frame text, nothing else
        if tail and not (tail[0].startswith("'") or tail[0] == "ERRORFRAME"):
            raise ValueError(f"{path}: line {n}: unexpected text after the data: {' '.join(tail)[:40]!r}")
        payload = bytes(int(b, 16) for b in hex_bytes)
    cid_s = m.group("id")
    return _frame(t, m.group("chan"), int(cid_s, 16), len(cid_s) > 3, remote, fd, payload)


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


def iter_candump(path: str | Path, keep_truncated: bool = False, on_cut: CutHandler | None = None) -> Iterator[Frame]:
    """Frames of a candump log (``candump -l``, or screen output with absolute times), with the
    semantics of python-can's ``CanutilsLogReader`` (tests check both agree) but about three times
    faster: it builds no ``can.Message``. A log cut short raises :class:`LogError` naming the line,
    or with ``keep_truncated`` ends at its last whole frame and reports the :class:`Cut`."""
    p = Path(path)
    n = frames = 0
    names: set[str] = set()
    try:
        with _open_text(p) as f:
            while line := f.readline(MAX_LINE_BYTES + 1):
                n += 1
                if len(line) > MAX_LINE_BYTES:
                    raise LogError(f"{p}: line {n}: longer than {MAX_LINE_BYTES} bytes: not a candump log")
                if not line.endswith("\n") and line.strip():  # the last line, without its line end
                    if not keep_truncated:
                        raise truncated_error(p, n, CUT_LINE)
                    report_cut(Cut(str(p), n, frames, CUT_LINE), on_cut)
                    return
                frame = parse_candump_line(line, p, n)
                if frame is not None:
                    if frame.channel not in names:
                        names.add(frame.channel)
                        if len(names) > MAX_CHANNELS:
                            raise too_many_channels(p, n)
                    frames += 1
                    yield frame
    except (EOFError, gzip.BadGzipFile, zlib.error) as exc:  # a truncated or corrupt .gz
        reason = f"cannot read past line {n}: {exc} (truncated or corrupt compressed log)"
        if not keep_truncated:
            raise LogError(f"{p}: {reason}; pass --keep-truncated to read it up to its last whole frame") from None
        report_cut(Cut(str(p), n + 1, frames, reason), on_cut)


def iter_frames(path: str | Path, keep_truncated: bool = False, on_cut: CutHandler | None = None) -> Iterator[Frame]:
    """Frames of any log python-can reads; candump logs (.log, .log.gz) through the fast reader.
    A log that cannot be read to its end raises :class:`LogError` (a ValueError) naming the file;
    one cut short (:func:`iter_candump`) is read up to its last whole frame with ``keep_truncated``,
    the :class:`Cut` handed to ``on_cut`` (and logged)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: log file not found")
    if p.name.endswith((".log", ".log.gz")):
        yield from iter_candump(p, keep_truncated, on_cut)
        return
    yield from _python_can_frames(p, keep_truncated, on_cut)


def log_format(p: Path) -> str:
    """The format suffix of a log (``.asc`` for ``x.asc.gz``), lower case."""
    return (p.suffixes[-2] if p.suffix == ".gz" and len(p.suffixes) > 1 else p.suffix).lower()


def _text_cut(p: Path) -> tuple[int, str] | None:
    """The cut last line of a text log: (its line number, the reason), or None when the file ends
    with a line end (an empty file too). A compressed file that ends early is cut at its last line."""
    opener = gzip.open if p.suffix == ".gz" else open
    lines = 0
    last = b"\n"
    try:
        with opener(p, "rb") as f:  # type: ignore[operator]
            while block := f.read(1 << 20):
                lines += block.count(b"\n")
                last = block[-1:]
    except (EOFError, OSError, zlib.error) as exc:
        return lines + 1, f"the compressed log ends early ({exc})"
    return (lines + 1, CUT_LINE) if last != b"\n" else None


# python-can's CSV layout: the header its CSVWriter writes and its CSVReader skips
CSV_HEADER = "timestamp,arbitration_id,extended,remote,error,dlc,data"


def _check_csv_header(p: Path) -> None:
    opener = gzip.open if p.suffix == ".gz" else open
    try:
        with opener(p, "rt", encoding="utf-8", errors="replace") as f:  # type: ignore[operator]
            first = f.readline(MAX_LINE_BYTES).strip()
    except (EOFError, OSError, zlib.error):
        return  # the reader says what is wrong with the file
    if first.replace(" ", "").lower() != CSV_HEADER:
        savvy = " (it looks like SavvyCAN's GVRET CSV)" if first.lower().startswith("time stamp,id,") else ""
        raise LogError(
            f"{p}: line 1: not a CAN log in python-can's CSV layout{savvy}: cmcan reads CSV logs with the header "
            f"{CSV_HEADER!r} (data in base64, as python-can writes them); got {first[:60]!r}. Export the log "
            "in another format (candump -l, Vector ASC or BLF) where the tool that wrote it offers one"
        )


class _Lines:
    """The first ``n`` lines of a text file, as python-can's text readers iterate their file."""

    def __init__(self, f, n: int) -> None:  # type: ignore[no-untyped-def]
        self.f, self.left = f, n

    def __iter__(self) -> _Lines:
        return self

    def __next__(self) -> str:
        if self.left <= 0:
            raise StopIteration
        self.left -= 1
        return next(self.f)

    def close(self) -> None:
        self.f.close()


def _python_can_frames(p: Path, keep_truncated: bool = False, on_cut: CutHandler | None = None) -> Iterator[Frame]:
    """A log through python-can's reader for its format, every failure of it said in one line, a log
    cut short refused or (``keep_truncated``) read to its last whole frame."""
    import can

    fmt = log_format(p)
    if fmt == ".mf4":
        from cmcan.io import mf4support

        mf4support.enable()
    if fmt not in LOG_FORMATS:
        raise LogError(f"{p}: unknown CAN log format {fmt or '(no suffix)'!r}; cmcan reads {', '.join(LOG_FORMATS)}")
    cut: Cut | None = None
    if fmt == ".blf":
        from cmcan.io.blf import check_blf

        try:
            check_blf(p)
        except ValueError as exc:
            truncated = "truncated" in str(exc)
            if not truncated:
                raise LogError(str(exc)) from None
            if not keep_truncated:
                raise LogError(f"{exc}; pass --keep-truncated to read it up to its last whole frame") from None
            cut = Cut(str(p), None, 0, str(exc).split(": ", 1)[-1])
    if fmt == ".csv":
        _check_csv_header(p)
    found = _text_cut(p) if fmt in TEXT_FORMATS else None
    if found is not None and found[1] == CUT_LINE:
        # a last line without its line end: cut, unless it holds a whole frame (some writers end
        # their last line without one); judged when it has been read
        yield from _last_line_judged(p, fmt, found[0], keep_truncated, on_cut)
        return
    reader = None
    if found is not None:  # a compressed text log that ends early
        line, reason = found
        if not keep_truncated:
            raise truncated_error(p, line, reason)
        cut = Cut(str(p), line, 0, reason)
        reader = _reader_up_to(p, fmt, line - 1)
    n = 0
    try:
        with reader if reader is not None else can.LogReader(str(p)) as messages:
            for f, _ in _checked(messages, p, fmt):
                n += 1
                yield f
            if getattr(messages, "_tail", b""):  # BLFReader: an object left incomplete at the end
                if not keep_truncated:
                    raise truncated_error(p, None, "the last frame of the file is incomplete")
                cut = cut or Cut(str(p), None, n, "the last frame of the file is incomplete")
    except CmcanError:
        raise
    except NotImplementedError as exc:  # python-can without the package for this format (.mf4: asammdf)
        how = "the 'mf4' extra: pip install 'cmcan[mf4]'" if fmt == ".mf4" else "a package python-can lacks"
        raise CmcanError(f"{p}: reading {fmt} logs needs {how} ({exc})", Kind.UNAVAILABLE) from None
    except Exception as exc:  # each reader has its own exceptions (BLFParseError, sqlite3, asammdf, struct, ...)
        if cut is not None and fmt == ".blf":  # a cut BLF: python-can stops where its data end
            report_cut(Cut(cut.path, None, n, cut.reason), on_cut)
            return
        raise _unreadable(p, fmt, n, exc) from None
    if cut is not None:
        report_cut(Cut(cut.path, cut.line, n, cut.reason), on_cut)


def _unreadable(p: Path, fmt: str, n: int, exc: Exception) -> LogError:
    where = f" at {_where(fmt, n)}" if fmt == ".csv" else f" after frame {n}" if n else ""
    return LogError(f"{p}: cannot read as a {fmt} log{where}: {type(exc).__name__}: {exc}")


def _reader_up_to(p: Path, fmt: str, n_lines: int):  # type: ignore[no-untyped-def]
    """python-can's reader of a text format over the first ``n_lines`` lines of the file."""
    import can

    text = gzip.open(p, "rt", errors="replace") if p.suffix == ".gz" else open(p, errors="replace")  # noqa: SIM115
    readers = {".asc": can.ASCReader, ".trc": can.TRCReader, ".csv": can.CSVReader}
    return readers[fmt](_Lines(text, n_lines))


def _checked(messages: Iterable, p: Path, fmt: str) -> Iterator[tuple[Frame, object]]:  # type: ignore[type-arg]
    """Frames of python-can's messages, each a CAN frame with a time (LogError otherwise)."""
    names: set[str] = set()
    for n, m in enumerate(messages):
        if not_frames(m.timestamp, m.arbitration_id, len(m.data)):
            raise not_a_frame(p, _where(fmt, n), m.timestamp, m.arbitration_id, len(m.data))
        f = from_message(m)
        if f.channel not in names and more_channels(names, (f.channel,)):
            raise LogError(f"{p}: {_where(fmt, n)}: more than {MAX_CHANNELS} channel names: not a CAN log")
        yield f, m


def _last_line_judged(p: Path, fmt: str, line: int, keep_truncated: bool, on_cut: CutHandler | None) -> Iterator[Frame]:
    """A text log whose last line has no line end, read one frame behind: the last frame is kept
    when the line held a whole one; the line is a cut when python-can cannot read it or its frame
    has fewer data bytes than its length says (a line cut inside its last byte cannot be told)."""
    import can

    held: tuple[Frame, object] | None = None
    n = 0
    failure: Exception | None = None
    try:
        with can.LogReader(str(p)) as messages:
            for item in _checked(messages, p, fmt):
                if held is not None:
                    n += 1
                    yield held[0]
                held = item
    except CmcanError:
        raise
    except Exception as exc:  # python-can could not read the last line (or another: said below)
        failure = exc
    short = False
    if held is not None and failure is None:
        m = held[1]
        short = not (m.is_remote_frame or m.is_error_frame) and len(m.data) < m.dlc  # type: ignore[attr-defined]
    # python-can's TRC reader skips a line it cannot parse with a log message: a last line that reads
    # as a frame line (it starts with a number) but gave no frame is a cut line too
    skipped = False
    if failure is None and not short and _starts_with_number(p):
        before = sum(1 for _ in _checked(_reader_up_to(p, fmt, line - 1), p, fmt))
        skipped = before == n + (held is not None)
    if failure is None and not short and not skipped:
        if held is not None:
            yield held[0]
        return
    if (failure is not None or skipped) and held is not None:  # the frame before the cut line is whole
        n += 1
        yield held[0]
    reason = CUT_LINE if failure is None else f"{CUT_LINE}; python-can: {type(failure).__name__}: {failure}"
    if not keep_truncated:
        raise truncated_error(p, line, reason)
    report_cut(Cut(str(p), line, n, CUT_LINE), on_cut)


def _starts_with_number(p: Path) -> bool:
    """Whether the last line of a file starts with a number (a frame line of ASC and TRC does)."""
    if p.suffix == ".gz":
        with gzip.open(p, "rb") as g:
            tail = b""
            while block := g.read(1 << 20):
                tail = (tail + block)[-MAX_LINE_BYTES:]
    else:
        with open(p, "rb") as f:
            f.seek(max(0, p.stat().st_size - MAX_LINE_BYTES))
            tail = f.read()
    tokens = tail.rsplit(b"\n", 1)[-1].split()
    try:
        float(tokens[0]) if tokens else float("x")
    except ValueError:
        return False
    return True


def _where(fmt: str, n: int) -> str:
    """Where frame ``n + 1`` of a log is: its line in a CSV log (one frame a line after the header),
    else its number."""
    return f"line {n + 2}" if fmt == ".csv" else f"frame {n + 1}"
