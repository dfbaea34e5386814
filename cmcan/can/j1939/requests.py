"""J1939-21 requests and acknowledgments, and the parameter groups of network management (J1939-81) and
diagnostics (J1939-73) a node answers: pure functions over integers and bytes.

- Request (PGN 59904, PDU1): 3 data bytes, the requested PGN least significant byte first; sent to one
  node (its address in the identifier's PS byte) or to all (255).
- Acknowledgment (PGN 59392): control byte (0 ACK, 1 NACK, 2 access denied, 3 cannot respond), group
  function value (0xFF: none), two bytes 0xFF, the address acknowledged (the requester), the PGN
  acknowledged in three bytes. J1939-21 sends it to the global address (255) even when the request was
  addressed to one node: byte 5 says whom it answers.
- Address Claimed (PGN 60928): the sender's NAME in 8 bytes (:mod:`cmcan.can.j1939.name`), to the global
  address; from the null address (254) it is "Cannot Claim Address".

J1939-21's rules for answering a request (section "Request"): a request to the global address is
answered to the global address, and a node that does not support the PGN stays silent (a NACK to a
global request is not allowed); a request to one node is answered, with a NACK where the PGN is not
supported. A PDU2 answer of up to 8 bytes has no destination and goes to all; longer answers go by the
transport protocol.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from cmcan.schema import Num, setting

PGN_REQUEST = 59904  # 0xEA00
PGN_ACK = 59392  # 0xE800
PGN_ADDRESS_CLAIMED = 60928  # 0xEE00
PGN_COMMANDED_ADDRESS = 65240  # 0xFED8
PGN_DM2 = 65227  # previously active DTCs
PGN_DM3 = 65228  # clear previously active DTCs
PGN_DM11 = 65235  # clear active DTCs
REQUEST_PRIORITY = 6
ACK_PRIORITY = 6
CLAIM_PRIORITY = 6

ACK, NACK, ACCESS_DENIED, CANNOT_RESPOND = 0, 1, 2, 3
CONTROL_NAMES = {ACK: "ACK", NACK: "NACK", ACCESS_DENIED: "access denied", CANNOT_RESPOND: "cannot respond"}


def request_data(pgn: int) -> bytes:
    """A request's 3 data bytes for ``pgn``."""
    return bytes((pgn & 0xFF, (pgn >> 8) & 0xFF, (pgn >> 16) & 0x03))


def requested_pgn(data: bytes) -> int | None:
    """The PGN a request asks for (None: fewer than 3 bytes, not a request J1939-21 knows)."""
    if len(data) < 3:
        return None
    return data[0] | data[1] << 8 | (data[2] & 0x03) << 16


def ack_data(control: int, pgn: int, address: int, group_function: int = 0xFF) -> bytes:
    """An Acknowledgment's 8 data bytes: ``control`` for ``pgn`` as requested by ``address``."""
    return bytes((control, group_function, 0xFF, 0xFF, address, pgn & 0xFF, (pgn >> 8) & 0xFF, (pgn >> 16) & 0x03))


@dataclass(frozen=True)
class Ack:
    control: int
    group_function: int
    address: int
    pgn: int


def decode_ack(data: bytes) -> Ack:
    if len(data) < 8:
        raise ValueError(f"an Acknowledgment has 8 bytes, got {len(data)}")
    return Ack(data[0], data[1], data[4], data[5] | data[6] << 8 | (data[7] & 0x03) << 16)


@dataclass(frozen=True)
class AnswerLimits:
    """How much answering cmcan does whatever the requesters (the YAML section ``j1939.answers``).

    A flood of requests from rotating source addresses passes any per-requester limit: a global rate
    in frame time caps the answers (a token bucket: ``burst`` at once, then ``rate_per_s``), and the
    answers that need the bus's one BAM session wait in a bounded queue, behind cmcan's own DM1."""

    rate_per_s: float = setting(
        Num(0.1, 1000, "/s", default=10.0),
        "answers to requests per second of frame time, from all requesters together (Address Claimed aside); "
        "requests beyond it are not answered and are counted",
    )
    burst: int = setting(
        Num(1, 1000, integer=True, default=10), "answers given at once before the rate applies (the bucket's size)"
    )
    waiting_max: int = setting(
        Num(0, 64, integer=True, default=4),
        "answers by BAM (DM1, DM2 with more than one DTC) waiting for the node's BAM session; more are dropped "
        "and counted",
    )


@dataclass
class RequestLimit:
    """How often one requester gets an answer for one PGN: at most once per ``interval_s`` of frame time;
    and all requesters together at most ``answers.rate_per_s`` (``answers.burst`` at once).

    J1939-21 asks a requester to keep its requests to a few a second (a request is not a polling
    mechanism; periodic data is broadcast); a node answering every request of a requester that floods
    the bus would double the flood, and one that answers every source address of a rotating flood
    the same. Requests refused are not answered (nor NACKed: silence costs the bus nothing). At most
    ``keys_max`` (requester, PGN) pairs are remembered; the oldest go."""

    interval_s: float = 0.3
    keys_max: int = 512
    answers: AnswerLimits = field(default_factory=AnswerLimits)
    last: dict[tuple[int, int], float] = field(default_factory=dict)
    refused: int = 0  # by the per-requester limit
    refused_global: int = 0  # by the global rate
    tokens: float = math.nan  # the bucket (NaN: full, before the first request)
    tokens_t: float = -math.inf  # the frame time it was filled to

    def allow(self, t: float, requester: int, pgn: int) -> bool:
        key = (requester, pgn)
        before = self.last.get(key)
        if before is not None and before <= t < before + self.interval_s:
            self.refused += 1
            return False
        if not self.take_token(t):
            self.refused_global += 1
            return False
        self.last.pop(key, None)
        self.last[key] = t
        if len(self.last) > self.keys_max:
            del self.last[next(iter(self.last))]
        return True

    def take_token(self, t: float) -> bool:
        """One answer from the global bucket at frame time ``t`` (a time earlier than the last, a step
        of the clock back, refills nothing and becomes the bucket's time)."""
        a = self.answers
        if self.tokens != self.tokens:
            self.tokens = float(a.burst)
        else:
            self.tokens = min(float(a.burst), self.tokens + max(0.0, t - self.tokens_t) * a.rate_per_s)
        self.tokens_t = t
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True
