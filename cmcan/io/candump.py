"""CAN logs: writing the ``candump -l`` format fast, reading any format python-can's LogReader reads."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
from numpy.typing import NDArray


def write_candump(
    path: str | Path,
    timestamp_s: NDArray[np.float64],
    arbitration_id: NDArray[np.int64],
    dlc: NDArray[np.int64],
    data: NDArray[np.uint8],
    channel: str = "can0",
) -> int:
    """Write frames as ``candump -l`` does: ``(1436509052.249713) can0 100#0011223344556677``.

    Written to a temporary file then renamed, so an existing log is never left half-written.
    """
    p = Path(path)
    hexdata = _hex_rows(data, dlc)
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "w", encoding="ascii", newline="\n") as f:
        chunk = 200_000
        for a in range(0, len(timestamp_s), chunk):
            b = min(a + chunk, len(timestamp_s))
            lines = [
                f"({ts:017.6f}) {channel} {cid:03X}#{hx}\n"
                if cid <= 0x7FF
                else f"({ts:017.6f}) {channel} {cid:08X}#{hx}\n"
                for ts, cid, hx in zip(
                    timestamp_s[a:b].tolist(), arbitration_id[a:b].tolist(), hexdata[a:b], strict=True
                )
            ]
            f.writelines(lines)
    tmp.replace(p)
    return len(timestamp_s)


def _hex_rows(data: NDArray[np.uint8], dlc: NDArray[np.int64]) -> list[str]:
    full = [bytes(r).hex().upper() for r in data]
    if np.all(dlc == data.shape[1]):
        return full
    return [h[: 2 * int(n)] for h, n in zip(full, dlc.tolist(), strict=True)]


def read_messages(path: str | Path) -> Iterator[can.Message]:
    """Every frame of a log in any format python-can's LogReader reads (by extension, .gz too)."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: log file not found")
    yield from can.LogReader(str(p))
