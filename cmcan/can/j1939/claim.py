"""J1939-81 address claim: one controller application's state machine over frames with timestamps.

A node sends Address Claimed (PGN 60928, its NAME, to the global address) from the address it wants
before it sends anything else, and waits ``SETTLE_S`` (250 ms) for contending claims before normal
traffic; the Linux kernel's J1939 stack likewise takes a NAME's address as valid 250 ms after its
claim. When another node claims the same address:

- the lower NAME wins: a node whose NAME is lower claims its address again, at once; the other yields;
- a node that yields and is *arbitrary address capable* claims another address of its range, one no
  node with a lower NAME holds (a free one first, as can-utils' j1939acd chooses), and goes on there
  after its own 250 ms; with none left, and a node that is not arbitrary address capable at once,
  sends Cannot Claim Address (Address Claimed from the null address 254) and stops sending.

A Request for Address Claimed (PGN 59904 asking for 60928, to the global address or to the node's
address) is answered with Address Claimed from the address held, or, by a node that could not claim
one, with Cannot Claim after a pseudo-random delay of 0 to 153 ms (0.6 ms steps, J1939-81: several
nodes that cannot claim do not answer at the same instant); here the delay comes from the NAME, so a
replayed log gives the same frames every time. Every claim heard on the bus keeps a table of who
holds which address (the kernel's stack keeps the same), which the arbitrary address choice and the
"who cleared the DTCs" records read.

No clock: each method takes the frame time it happens at; frames out carry their time.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from cmcan.can.frame import Frame
from cmcan.can.j1939 import ids
from cmcan.can.j1939.name import Name
from cmcan.can.j1939.requests import CLAIM_PRIORITY, PGN_ADDRESS_CLAIMED

SETTLE_S = 0.25  # J1939-81: no normal traffic until 250 ms after the claim (contention window)
CANNOT_CLAIM_STEP_S = 0.0006  # the pseudo-random delay's step: 0..255 x 0.6 ms = 0..153 ms

# states
IDLE = "idle"  # not started: nothing sent
CLAIMING = "claiming"  # claimed, within the 250 ms contention window
CLAIMED = "claimed"  # the address is this node's: normal traffic
LOST = "lost"  # no address (Cannot Claim sent): silent but for Cannot Claim


@dataclass(frozen=True)
class ClaimParams:
    name: Name
    address: int  # the preferred address (the machine's address plan)
    # an arbitrary address capable node's other addresses, in the order tried (empty: none)
    addresses: tuple[int, ...] = ()
    channel: str = ""
    settle_s: float = SETTLE_S

    @property
    def arbitrary(self) -> bool:
        return self.name.arbitrary_address_capable and bool(self.addresses)


@dataclass
class Event:
    """A change of the claim's state, for the journal, the uplink and the status."""

    t_s: float
    state: str
    address: int | None
    detail: str = ""
    by_name: int | None = None  # the NAME that took the address, where one did


@dataclass
class AddressClaim:
    p: ClaimParams
    state: str = IDLE
    address: int | None = None  # the address claimed (or being claimed); None when lost or idle
    settle_at: float = float("inf")  # frame time from which the claim stands
    others: dict[int, int] = field(default_factory=dict)  # address -> NAME value, from claims heard
    events: list[Event] = field(default_factory=list)  # newest last, at most EVENTS_MAX
    contentions: int = 0
    n_events: int = 0  # events so far (the list keeps the newest EVENTS_MAX)

    EVENTS_MAX = 64

    @property
    def name_value(self) -> int:
        return self.p.name.value

    def _frame(self, t: float, source: int) -> Frame:
        fid = ids.make_id(CLAIM_PRIORITY, PGN_ADDRESS_CLAIMED, source, ids.GLOBAL_ADDRESS)
        return Frame(t, self.p.channel, fid, True, False, False, False, self.p.name.to_bytes())

    def _event(self, t: float, detail: str = "", by_name: int | None = None) -> None:
        self.events.append(Event(t, self.state, self.address, detail, by_name))
        del self.events[: -self.EVENTS_MAX]
        self.n_events += 1

    def may_send(self, t: float) -> bool:
        """Whether normal traffic may go out at frame time ``t`` (the claim stands by then)."""
        if self.state == CLAIMING and t >= self.settle_at:
            self.state = CLAIMED
            self._event(self.settle_at, "no contention within 250 ms")
        return self.state == CLAIMED and t >= self.settle_at

    @property
    def claiming(self) -> bool:
        """Within the 250 ms after the claim (nothing else may go out)."""
        return self.state == CLAIMING

    def on_air(self, t: float, frame: Frame) -> None:
        """``frame`` left at frame time ``t``: where it is this node's claim and left later than the
        time it was made for (a loop behind its bus), the 250 ms count from when the bus saw it."""
        if self.state != CLAIMING or self.address is None:
            return
        mine = self._frame(t, self.address)
        if frame.arbitration_id == mine.arbitration_id and frame.data == mine.data:
            self.settle_at = max(self.settle_at, t + self.p.settle_s)

    def start(self, t: float, detail: str = "start") -> list[Frame]:
        """Claim at ``t`` (at start, after a bus-off, when the link comes back): the address held
        before, else the preferred one (an address taken by a lower NAME is skipped where the node may
        choose another)."""
        want = self.address if self.address is not None else self.p.address
        holder = self.others.get(want)
        if holder is not None and holder < self.name_value and self.p.arbitrary:
            return self._move(t, want, holder, detail)
        return self._claim(t, want, detail)

    def _claim(self, t: float, address: int, detail: str) -> list[Frame]:
        self.state, self.address, self.settle_at = CLAIMING, address, t + self.p.settle_s
        self._event(t, detail)
        return [self._frame(t, address)]

    def on_claim(self, t: float, source: int, name_value: int) -> list[Frame]:
        """Another node's Address Claimed (or Cannot Claim, from 254) heard at ``t``."""
        if name_value == self.name_value:  # our own claim (a log that has it, or an echo): nothing new
            return []
        for a in [a for a, n in self.others.items() if n == name_value]:
            del self.others[a]  # a node that moves leaves its old address
        if source > ids.MAX_UNICAST_ADDRESS:
            return []
        self.others[source] = name_value
        if self.address is None or source != self.address or self.state in (IDLE, LOST):
            return []
        self.contentions += 1
        if self.name_value < name_value:  # we win: claim again, at once
            return [self._frame(t, source)]
        return self._move(t, source, name_value, f"address 0x{source:02X} taken by a lower NAME")

    def _move(self, t: float, lost: int, by_name: int, detail: str) -> list[Frame]:
        """This node yields ``lost``: another address of its range, or Cannot Claim."""
        nxt = self._choose(lost) if self.p.arbitrary else None
        if nxt is None:
            self.state, self.address, self.settle_at = LOST, None, float("inf")
            self._event(t, detail + ("; no free address in the range" if self.p.arbitrary else ""), by_name)
            return [self._frame(t, ids.NULL_ADDRESS)]
        self.address = None
        self._event(t, detail, by_name)
        return self._claim(t, nxt, f"moved from 0x{lost:02X}")

    def _choose(self, lost: int) -> int | None:
        """The next address to claim: the first of the range nobody holds, else the first one held by
        a higher NAME (which we would win), never the one just lost."""
        mine = self.name_value
        candidates: Sequence[int] = [a for a in self.p.addresses if a != lost]
        for a in candidates:
            if a not in self.others:
                return a
        for a in candidates:
            if self.others[a] > mine:
                return a
        return None

    def on_request(self, t: float, destination: int) -> list[Frame]:
        """A Request for Address Claimed to ``destination`` heard at ``t``."""
        if destination != ids.GLOBAL_ADDRESS and destination != self.address:
            return []
        if self.state in (CLAIMING, CLAIMED):
            assert self.address is not None
            return [self._frame(t, self.address)]
        if self.state == LOST and destination == ids.GLOBAL_ADDRESS:
            delay = (self.name_value % 256) * CANNOT_CLAIM_STEP_S
            return [self._frame(t + delay, ids.NULL_ADDRESS)]
        return []
