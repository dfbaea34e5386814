"""Which mapped input message a received frame is: a pure function of the frame's channel name,
identifier and identifier format, so a batched reader can apply the very same rules.

1. The channel name resolves to a configured channel (:class:`Channels`): a name given in the
   aliases (a log's names, from the configuration or the command line) to its target; a configured
   channel's own name to itself; with exactly one configured channel and no aliases, any other name
   (a log recorded on can0 replayed with a configuration for vcan0; "" from a format without
   channels) to that one. Anything else is on no configured channel (``unknown_channel``).
2. A CAN FD frame on a channel that is not configured as an FD bus is counted (``bad_fd``), not used.
3. On its channel, a standard (11-bit) frame is the message with that identifier. An extended
   (29-bit) frame is the message with exactly that identifier, or, for a message matched as J1939,
   the one whose PGN equals the frame's, whose source addresses include the frame's (or are "any")
   and, for a PDU1 PGN, whose destinations include the frame's destination address. The priority
   bits are ignored. The configuration check refuses mappings where two messages could match one
   frame, so the order of the rules does not matter.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

from cmcan.codec import Layout, checked_decoder
from cmcan.j1939 import ids
from cmcan.monitor.health import HealthSpec

MEMO_MAX = 1 << 16  # identifiers remembered per channel (a flood of random ones is looked up anew)


@dataclass(frozen=True)
class InputMessage:
    """How to read one input message: the layouts of its mapped signals (read as ``size`` bytes), the
    role of each value in order, and where and how it is matched (see the module's rules) and checked
    (:mod:`cmcan.monitor.health`). ``decode`` gives the raw values of one frame, or None when a value
    is outside its DBC range (an implausible frame)."""

    frame_id: int
    length: int
    layouts: tuple[Layout, ...]
    size: int
    roles: tuple[str, ...]
    name: str = ""
    channel: str = ""  # a configured channel's name; "" is the first one
    extended: bool = False
    pgn: int | None = None  # matched as J1939 on this PGN
    sources: frozenset[int] | None = None  # J1939 source addresses accepted; None: any
    destinations: frozenset[int] = frozenset({ids.GLOBAL_ADDRESS})  # PDU1: destinations accepted
    health: HealthSpec = field(default_factory=HealthSpec)
    decode: Callable[[bytes], tuple[int, ...] | None] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "decode", checked_decoder(self.layouts, self.size))

    def matches(self, can_id: int, extended: bool) -> bool:
        """Rule 3 for a frame already on this message's channel."""
        if extended != self.extended:
            return False
        if self.pgn is None:
            return can_id == self.frame_id
        if ids.pgn(can_id) != self.pgn:
            return False
        if self.sources is not None and ids.source_address(can_id) not in self.sources:
            return False
        return not ids.is_pdu1(self.pgn) or ids.pdu_specific(can_id) in self.destinations


@dataclass(frozen=True)
class Channels:
    """The configured channels (the first is the default) and the aliases of rule 1."""

    names: tuple[str, ...] = ("",)
    fd: tuple[bool, ...] = (False,)
    aliases: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.names) != len(self.fd) or not self.names:
            raise ValueError("one FD flag per channel, at least one channel")

    def resolve(self, name: str) -> int | None:
        if name in self.aliases:
            target = self.aliases[name]
            return self.names.index(target) if target in self.names else None
        if name in self.names:
            return self.names.index(name)
        if len(self.names) == 1 and not self.aliases:
            return 0
        return None

    def index(self, name: str) -> int:
        """The index of a message's or output's channel ("" is the first)."""
        return self.names.index(name) if name else 0


class Matcher:
    """Rule 3 over a set of input messages, per channel index."""

    def __init__(self, inputs: Sequence[InputMessage], channels: Channels) -> None:
        self.channels = channels
        self.by_channel: list[list[InputMessage]] = [[] for _ in channels.names]
        for m in inputs:
            self.by_channel[channels.index(m.channel)].append(m)

    def match(self, channel: int, can_id: int, extended: bool) -> InputMessage | None:
        for m in self.by_channel[channel]:
            if m.matches(can_id, extended):
                return m
        return None


def overlap(a: InputMessage, b: InputMessage) -> bool:
    """True when some frame on their (common) channel could match both messages."""
    if a.extended != b.extended:
        return False
    if a.pgn is None and b.pgn is None:
        return a.frame_id == b.frame_id
    if a.pgn is None or b.pgn is None:
        exact, other = (a, b) if a.pgn is None else (b, a)
        return other.matches(exact.frame_id, exact.extended)
    if a.pgn != b.pgn:
        return False
    if ids.is_pdu1(a.pgn) and not (a.destinations & b.destinations):
        return False
    return a.sources is None or b.sources is None or bool(a.sources & b.sources)
