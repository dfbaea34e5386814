"""One CAN frame as cmcan passes it around: from the bus or a log into the core, and out again."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray


class Frame(NamedTuple):
    """A received or emitted frame. ``timestamp_s`` is the frame's own time (epoch seconds from the
    kernel, a log or the core's tick), never read from a clock by the core; ``channel`` names the bus
    it was seen on or is sent to (``can0``), or is empty where a single bus is meant."""

    timestamp_s: float
    channel: str
    arbitration_id: int
    extended: bool
    remote: bool
    error: bool
    fd: bool
    data: bytes


_new_frame = tuple.__new__  # what Frame(...) calls, without its keyword handling: once per received frame


def from_message(m: Any, channel: str | None = None) -> Frame:
    """The one conversion from a python-can ``Message`` (read by attribute: no python-can import);
    ``channel`` names the bus it came from (default: the message's own channel)."""
    ch = m.channel if channel is None else channel
    return _new_frame(
        Frame,
        (
            float(m.timestamp),
            "" if ch is None else str(ch),
            int(m.arbitration_id),
            bool(m.is_extended_id),
            bool(m.is_remote_frame),
            bool(m.is_error_frame),
            bool(m.is_fd),
            bytes(m.data),
        ),
    )


def to_message_kwargs(f: Frame) -> dict[str, Any]:
    """Keyword arguments of ``can.Message`` for a frame to send."""
    return {
        "timestamp": f.timestamp_s,
        "arbitration_id": f.arbitration_id,
        "is_extended_id": f.extended,
        "is_remote_frame": f.remote,
        "is_error_frame": f.error,
        "is_fd": f.fd,
        "data": f.data,
        **({"channel": f.channel} if f.channel else {}),
    }


@dataclass(frozen=True)
class FrameColumns:
    """Many frames as arrays (the columnar replay's unit of work), in arrival order."""

    timestamp_s: NDArray[np.float64]
    channel: NDArray[np.int16]  # codes into channel_names
    channel_names: tuple[str, ...]
    arbitration_id: NDArray[np.uint32]
    extended: NDArray[np.bool_]
    remote: NDArray[np.bool_]
    error: NDArray[np.bool_]
    fd: NDArray[np.bool_]
    dlc: NDArray[np.int16]  # payload length in bytes
    data: NDArray[np.uint8]  # (n, 8): the first 8 bytes of every payload (a longer one's too), zero padded
    long_data: dict[int, bytes] = field(default_factory=dict)  # whole payloads beyond 8 bytes, by row

    def __len__(self) -> int:
        return len(self.timestamp_s)

    def payload(self, i: int) -> bytes:
        if i in self.long_data:
            return self.long_data[i]
        return self.data[i, : self.dlc[i]].tobytes()

    def frame(self, i: int) -> Frame:
        return Frame(
            float(self.timestamp_s[i]),
            self.channel_names[self.channel[i]] if len(self.channel_names) else "",
            int(self.arbitration_id[i]),
            bool(self.extended[i]),
            bool(self.remote[i]),
            bool(self.error[i]),
            bool(self.fd[i]),
            self.payload(i),
        )

    def frames(self) -> list[Frame]:
        return [self.frame(i) for i in range(len(self))]

    def take(self, rows: NDArray[np.int64]) -> FrameColumns:
        """The frames at ``rows``, in that order."""
        at = {int(r): i for i, r in enumerate(rows.tolist())} if self.long_data else {}
        return FrameColumns(
            timestamp_s=self.timestamp_s[rows],
            channel=self.channel[rows],
            channel_names=self.channel_names,
            arbitration_id=self.arbitration_id[rows],
            extended=self.extended[rows],
            remote=self.remote[rows],
            error=self.error[rows],
            fd=self.fd[rows],
            dlc=self.dlc[rows],
            data=self.data[rows],
            long_data={at[r]: d for r, d in self.long_data.items() if r in at},
        )

    @classmethod
    def concat(cls, parts: Sequence[FrameColumns]) -> FrameColumns:
        """The frames of ``parts`` one after the other (channel codes mapped onto the union of names)."""
        names = tuple(dict.fromkeys(n for p in parts for n in p.channel_names))
        chans, long, at = [], {}, 0
        for p in parts:
            code = np.array([names.index(n) for n in p.channel_names], dtype=np.int16)
            chans.append(code[p.channel] if len(code) else p.channel.astype(np.int16))
            long.update({at + r: d for r, d in p.long_data.items()})
            at += len(p)
        return cls(
            timestamp_s=np.concatenate([p.timestamp_s for p in parts]),
            channel=np.concatenate(chans),
            channel_names=names,
            arbitration_id=np.concatenate([p.arbitration_id for p in parts]),
            extended=np.concatenate([p.extended for p in parts]),
            remote=np.concatenate([p.remote for p in parts]),
            error=np.concatenate([p.error for p in parts]),
            fd=np.concatenate([p.fd for p in parts]),
            dlc=np.concatenate([p.dlc for p in parts]),
            data=np.concatenate([p.data for p in parts]),
            long_data=long,
        )

    @classmethod
    def from_frames(cls, frames: list[Frame]) -> FrameColumns:
        names: dict[str, int] = {}
        n = len(frames)
        data = np.zeros((n, 8), dtype=np.uint8)
        long: dict[int, bytes] = {}
        for i, f in enumerate(frames):
            d = f.data
            if len(d) > 8:
                long[i] = d
            if d:  # the first 8 bytes of any payload, a longer one's too
                data[i, : min(len(d), 8)] = np.frombuffer(d[:8], dtype=np.uint8)
        return cls(
            timestamp_s=np.fromiter((f.timestamp_s for f in frames), np.float64, n),
            channel=np.fromiter((names.setdefault(f.channel, len(names)) for f in frames), np.int16, n),
            channel_names=tuple(names),
            arbitration_id=np.fromiter((f.arbitration_id for f in frames), np.uint32, n),
            extended=np.fromiter((f.extended for f in frames), bool, n),
            remote=np.fromiter((f.remote for f in frames), bool, n),
            error=np.fromiter((f.error for f in frames), bool, n),
            fd=np.fromiter((f.fd for f in frames), bool, n),
            dlc=np.fromiter((len(f.data) for f in frames), np.int16, n),
            data=data,
            long_data=long,
        )
