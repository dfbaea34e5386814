"""One CAN frame as cmcan passes it around: from the bus or a log into the core, and out again."""

from __future__ import annotations

from typing import Any, NamedTuple


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


def from_message(m: Any, channel: str | None = None) -> Frame:
    """The one conversion from a python-can ``Message`` (read by attribute: no python-can import);
    ``channel`` names the bus it came from (default: the message's own channel)."""
    ch = m.channel if channel is None else channel
    return Frame(
        float(m.timestamp),
        "" if ch is None else str(ch),
        int(m.arbitration_id),
        bool(m.is_extended_id),
        bool(m.is_remote_frame),
        bool(m.is_error_frame),
        bool(m.is_fd),
        bytes(m.data),
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
