"""CAN logs: writing the ``candump -l`` format fast, reading any format python-can's LogReader reads."""

from __future__ import annotations

import gzip
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cmcan.frame import Frame, from_message


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


def candump_line(f: Frame, default_channel: str = "can0") -> str:
    """One frame as a ``candump -l`` line (CAN FD as ``##`` with its flags digit, remote as ``R``)."""
    cid = f"{f.arbitration_id:08X}" if f.extended else f"{f.arbitration_id:03X}"
    if f.error:
        cid = f"{CAN_ERR_FLAG | CAN_ERR_BUSERROR:08X}"
    body = "R" if f.remote else ("#0" if f.fd else "") + f.data.hex().upper()
    return f"({f.timestamp_s:017.6f}) {f.channel or default_channel} {cid}#{body}\n"


def write_frames(path: str | Path, frames: Iterable[Frame], default_channel: str = "can0") -> int:
    """Write :class:`Frame` objects as a ``candump -l`` log, each on its own channel (frames with no
    channel on ``default_channel``); a temporary file renamed into place."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    n = 0
    with open(tmp, "w", encoding="ascii", newline="\n") as out:
        for f in frames:
            out.write(candump_line(f, default_channel))
            n += 1
    tmp.replace(p)
    return n


def _hex_rows(data: NDArray[np.uint8], dlc: NDArray[np.int64]) -> list[str]:
    full = [bytes(r).hex().upper() for r in data]
    if np.all(dlc == data.shape[1]):
        return full
    return [h[: 2 * int(n)] for h, n in zip(full, dlc.tolist(), strict=True)]


CAN_ERR_FLAG = 0x20000000
CAN_ERR_BUSERROR = 0x00000080


def iter_candump(path: str | Path) -> Iterator[Frame]:
    """Frames of a ``candump -l`` log, with the semantics of python-can's ``CanutilsLogReader``
    (tests check both agree) but about three times faster: it builds no ``can.Message``."""
    p = Path(path)
    opener = gzip.open if p.suffix == ".gz" else open
    with opener(p, "rt", encoding="ascii", errors="replace") as f:  # type: ignore[operator]
        for n, line in enumerate(f, 1):
            parts = line.split()
            if not parts:
                continue
            try:
                stamp, channel, frame = parts[0], parts[1], parts[2]
                t = float(stamp[1:-1])
                cid_s, data = frame.split("#", 1)
                cid = int(cid_s, 16)
            except (IndexError, ValueError):
                raise ValueError(f"{p}: line {n}: not a candump -l line: {line.strip()[:80]!r}") from None
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
                    raise ValueError(f"{p}: line {n}: bad data {data[:40]!r}") from None
            if cid & CAN_ERR_FLAG and cid & CAN_ERR_BUSERROR:
                # as python-can builds it: Message(is_error_frame=True)
                yield Frame(t, channel, 0, True, False, True, False, b"")
            else:
                yield Frame(t, channel, cid & 0x1FFFFFFF, len(cid_s) > 3, remote, False, fd, payload)


def iter_frames(path: str | Path) -> Iterator[Frame]:
    """Frames of any log python-can reads; candump logs (.log, .log.gz) through the fast reader."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: log file not found")
    if p.name.endswith((".log", ".log.gz")):
        yield from iter_candump(p)
        return
    import can

    for m in can.LogReader(str(p)):
        yield from_message(m)
