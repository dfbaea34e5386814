"""cmcan as a J1939 node: its address claim, the requests it answers, and what it may send when.

A stage of the core like the others: driven by frames with timestamps (no clock), the same code for
both replay engines (the columnar engine hands the few network-management frames of a chunk to the
per-frame path, and gates its output with :meth:`Node.outgoing_columns` beside :meth:`Node.outgoing`).

What reaches it (the router hands it every J1939 Request, PGN 59904, Address Claimed, PGN 60928, and
transport connection management, TP.CM, PGN 60416, on the output channel, whatever their destination):

- Address Claimed from other nodes: the contention rules of :mod:`cmcan.can.j1939.claim`;
- a Request (J1939-21) to cmcan's address or to all, each (requester, PGN) answered at most once per
  ``request_interval_s`` (:class:`cmcan.can.j1939.requests.RequestLimit`):

  | requested | answer |
  |---|---|
  | Address Claimed | Address Claimed (or Cannot Claim), by the claim |
  | DM1, DM2 (with DM1 on) | the DTCs: one frame, or BAM to all, or RTS/CTS to a requester who asked alone |
  | DM3, DM11 (with DM1 on) | trusted (below): the clear, then ACK; else "access denied" (silence to all) |
  | a CM output's PGN | its last frame at the request's time, with the alive counter's next value |
  | anything else | NACK when addressed to cmcan; nothing for a request to all |

  A clear is carried out by the monitor before its ACK; an answer for a CM output before its first
  frame is NACK "cannot respond"; a DM1 or DM2 asked by one node and longer than 8 bytes goes by
  RTS/CTS to it (from the null address 254, which can hold no connection, by BAM to all). Until the
  claim stands (and after it is lost) only requests for Address Claimed are answered.
- the transport protocol's connection management (TP.CM, PGN 60416) addressed to cmcan: the CTS,
  EndOfMsgAck and Conn_Abort of its RTS/CTS connections (:class:`cmcan.can.j1939.transport.Sender`, at most
  one per requester and ``MAX_CONNECTIONS`` at a time; a request while the requester's connection is
  open gets "cannot respond"); a connection's timeout is noticed at the next node frame or
  :meth:`Node.expire`, and cmcan aborts it then.

Who may clear (:class:`ClearTrust`): J1939-73 leaves it to the OEM. By default nobody; the configuration
names the service tool's source addresses or NAMEs (a NAME as claimed on this bus, at whatever address).
The null address 254 and cmcan's own address are never trusted. Clears carried out and refused are
counted (:meth:`Node.describe`).

What leaves: every output frame of the monitor passes :meth:`Node.outgoing`: with a NAME configured,
nothing but Address Claimed goes out before the claim stands (250 ms after it) or after it was lost,
and a node that moved to another address sends from that address (the frames are made with the
configured one). The last frame of each CM output is kept for requests.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cmcan.can.frame import Frame, FrameColumns
from cmcan.can.j1939 import claim as ac
from cmcan.can.j1939 import dm1, ids, transport
from cmcan.can.j1939 import requests as rq
from cmcan.can.j1939.name import name_hex
from cmcan.monitor.diagnostics import Dm1Producer, dm_payload
from cmcan.monitor.payloads import Payloads
from cmcan.schema import Num, Seq, setting

CLEARS = {rq.PGN_DM3: "dm3", rq.PGN_DM11: "dm11"}
_AC_PF = rq.PGN_ADDRESS_CLAIMED >> 8
_TP_CM_PF = transport.PGN_TP_CM >> 8
MAX_CONNECTIONS = 4  # RTS/CTS connections open at a time (one per requester)
MAX_NAME = (1 << 64) - 1


@dataclass(frozen=True)
class ClearTrust:
    """Who may clear DTCs with DM3 or DM11 (the YAML section ``j1939.clears``): nobody by default."""

    addresses: tuple[int, ...] = setting(
        Seq(Num(0, 253, integer=True), default=[]),
        "source addresses whose DM3/DM11 cmcan carries out (the service tool's); never 254 or cmcan's own",
        "trusted_addresses",
    )
    names: tuple[int, ...] = setting(
        Seq(Num(0, MAX_NAME, integer=True), default=[]),
        "J1939 NAMEs (64-bit integers, e.g. 0xA00C81045A20021B) whose DM3/DM11 cmcan carries out, from the "
        "address each claimed on the bus",
        "trusted_names",
    )

    def __post_init__(self) -> None:  # a YAML list in, a hashable and comparable tuple kept
        object.__setattr__(self, "addresses", tuple(self.addresses))
        object.__setattr__(self, "names", tuple(self.names))


@dataclass(frozen=True)
class NodeParams:
    address: int  # the configured source address (every output frame is made with it)
    channel: str = ""  # the output channel, where the node lives
    claim: ac.ClaimParams | None = None  # None: no NAME, no claim (a fixed address from the address plan)
    output_pgns: frozenset[int] = frozenset()  # the PGNs of the CM output messages
    request_interval_s: float = 0.3
    trust: ClearTrust = ClearTrust()
    answers: rq.AnswerLimits = field(default_factory=rq.AnswerLimits)  # all requesters together (j1939.answers)


@dataclass
class Clear:
    """A DM3 or DM11 asked for: the monitor carries it out and records it."""

    kind: str  # "dm3" or "dm11"
    t_s: float
    by_address: int
    by_name: int | None  # the requester's NAME, where it claimed its address on this bus


COUNTS = (
    "node_frames",
    "requests",
    "answered",
    "nack",
    "held",
    "clears_dm3",
    "clears_dm11",
    "clears_refused",
    "connections",
    "connections_sent",
    "connections_aborted",
    "connections_timed_out",
)


class Node:
    def __init__(self, p: NodeParams) -> None:
        self.p = p
        self.claim = ac.AddressClaim(p.claim) if p.claim is not None else None
        self.limit = rq.RequestLimit(p.request_interval_s, answers=p.answers)
        self.started = False
        self.last_out: dict[int, Frame] = {}  # per CM output PGN: its last frame sent
        self.names: dict[int, int] = {}  # the NAME each other node claimed its address with
        self.connections: dict[int, transport.Sender] = {}  # open RTS/CTS connections, per requester
        self.counts = dict.fromkeys(COUNTS, 0)

    @property
    def address(self) -> int | None:
        """The address cmcan sends from now (None: it has none: lost, or not started)."""
        if self.claim is None:
            return self.p.address
        return self.claim.address

    @property
    def state(self) -> str:
        if self.claim is None:
            return "fixed"
        return self.claim.state

    def start(self, t: float, why: str = "start") -> list[Frame]:
        """At start and when the link is back (after a bus-off): claim (no frames without a NAME)."""
        self.started = True
        return self.claim.start(t, why) if self.claim is not None else []

    def may_send(self, t: float) -> bool:
        return self.claim is None or self.claim.may_send(t)

    # -- frames in ---------------------------------------------------------------------------------

    def handle(
        self, f: Frame, dm: Dm1Producer | None, payloads: Payloads | None = None
    ) -> tuple[list[Frame], Clear | None]:
        """A Request, Address Claimed or TP.CM at ``f``'s time: the frames answering it (at that time
        or later), and a clear the monitor is to carry out first. ``payloads``: the CM frames' maker,
        whose alive counter an answer to a request for a CM output takes its next value from."""
        self.counts["node_frames"] += 1
        t, fid, data = f.timestamp_s, f.arbitration_id, f.data
        if t != t:  # a frame without a readable time: nothing to answer when
            return [], None
        late = self.expire(t)
        sa, pf = ids.source_address(fid), ids.pdu_format(fid)
        if pf == _AC_PF:
            if len(data) != 8:
                return late, None
            self._note_name(sa, int.from_bytes(data, "little"))
            if self.claim is None:
                return late, None
            return late + self.claim.on_claim(t, sa, int.from_bytes(data, "little")), None
        if pf == _TP_CM_PF:
            return late + self._connection(t, sa, ids.pdu_specific(fid), data), None
        pgn, dest = rq.requested_pgn(data), ids.pdu_specific(fid)
        if pgn is None or (dest != ids.GLOBAL_ADDRESS and dest != self.address):
            return late, None
        if pgn == rq.PGN_ADDRESS_CLAIMED and self.claim is not None:
            return late + self.claim.on_request(t, dest), None
        if not self.may_send(t) or not self.limit.allow(t, sa, pgn):
            return late, None
        self.counts["requests"] += 1
        out, clear = self._answer(t, sa, pgn, dest != ids.GLOBAL_ADDRESS, dm, payloads)
        return late + out, clear

    def _answer(
        self, t: float, sa: int, pgn: int, direct: bool, dm: Dm1Producer | None, payloads: Payloads | None
    ) -> tuple[list[Frame], Clear | None]:
        if dm is not None and pgn in (dm1.PGN_DM1, rq.PGN_DM2):
            payload = dm_payload(dm.p, dm.active, dm.totals.dtc_occurrences, pgn)
            if direct and len(payload) > 8 and sa <= ids.MAX_UNICAST_ADDRESS:
                return self._connect(t, sa, pgn, payload), None  # J1939-21: to the requester alone
            self.counts["answered"] += 1
            return dm.answer(pgn, t), None
        if dm is not None and pgn in CLEARS:
            return self._clear(t, sa, pgn, direct)
        if pgn in self.p.output_pgns:
            last = self.last_out.get(pgn)
            if last is not None:
                self.counts["answered"] += 1
                return [payloads.answer(last, t) if payloads is not None else last._replace(timestamp_s=t)], None
            return ([self._ack(t, rq.CANNOT_RESPOND, pgn, sa)] if direct else []), None
        return ([self._ack(t, rq.NACK, pgn, sa)] if direct else []), None

    def trusted(self, sa: int) -> bool:
        """Whether a clear from source address ``sa`` is carried out (see the module)."""
        if sa > ids.MAX_UNICAST_ADDRESS or sa in (self.p.address, self.address):
            return False
        name = self.names.get(sa)
        return sa in self.p.trust.addresses or (name is not None and name in self.p.trust.names)

    def _clear(self, t: float, sa: int, pgn: int, direct: bool) -> tuple[list[Frame], Clear | None]:
        if not self.trusted(sa):  # nothing cleared; a request to all is not answered
            self.counts["clears_refused"] += 1
            return ([self._ack(t, rq.ACCESS_DENIED, pgn, sa)] if direct else []), None
        kind = CLEARS[pgn]
        self.counts[f"clears_{kind}"] += 1
        return ([self._ack(t, rq.ACK, pgn, sa)] if direct else []), Clear(kind, t, sa, self.names.get(sa))

    def _note_name(self, sa: int, name: int) -> None:
        """Who holds which address: a NAME's newest claim (Cannot Claim from 254: it holds none)."""
        for a in [a for a, n in self.names.items() if n == name]:
            del self.names[a]
        if sa <= ids.MAX_UNICAST_ADDRESS:
            self.names[sa] = name

    # -- RTS/CTS connections (J1939-21) ----------------------------------------------------------------

    def _connect(self, t: float, sa: int, pgn: int, payload: bytes) -> list[Frame]:
        """An RTS/CTS connection to the requester; "cannot respond" while it has one open or too many are."""
        if sa in self.connections or len(self.connections) >= MAX_CONNECTIONS:
            return [self._ack(t, rq.CANNOT_RESPOND, pgn, sa)]
        s = transport.Sender(pgn, payload, self.p.address, sa, self.p.channel)
        self.connections[sa] = s
        self.counts["connections"] += 1
        return s.start(t)

    def _connection(self, t: float, sa: int, dest: int, data: bytes) -> list[Frame]:
        """A TP.CM to cmcan: its connection's next frames; an RTS (cmcan takes no messages) is refused."""
        if dest != self.address or len(data) < 8:
            return []
        s = self.connections.get(sa)
        if s is None:
            if data[0] == transport.CM_RTS and sa <= ids.MAX_UNICAST_ADDRESS and self.may_send(t):
                fid = ids.make_id(transport.TP_PRIORITY, transport.PGN_TP_CM, self.p.address, sa)
                abort = transport.abort_data(transport.ABORT_RESOURCES, transport.cm_pgn(data))
                return [Frame(t, self.p.channel, fid, True, False, False, False, abort)]
            return []
        out = s.on_cm(t, data)
        self._closed(sa, s)
        return out

    def expire(self, t: float) -> list[Frame]:
        """The aborts of the connections whose time ran out by ``t`` (sent at ``t``)."""
        out: list[Frame] = []
        for sa, s in list(self.connections.items()):
            out += s.expire(t)
            self._closed(sa, s)
        return out

    @property
    def deadline_s(self) -> float:
        """When the next connection times out (inf: none open): a timer may call :meth:`expire` then."""
        return min((s.deadline_s for s in self.connections.values()), default=float("inf"))

    def _closed(self, sa: int, s: transport.Sender) -> None:
        if s.open:
            return
        del self.connections[sa]
        key = {"sent": "connections_sent", "timeout": "connections_timed_out"}.get(s.outcome or "")
        self.counts[key or "connections_aborted"] += 1

    def _ack(self, t: float, control: int, pgn: int, requester: int) -> Frame:
        self.counts["nack" if control else "answered"] += 1
        fid = ids.make_id(rq.ACK_PRIORITY, rq.PGN_ACK, self.p.address, ids.GLOBAL_ADDRESS)
        return Frame(t, self.p.channel, fid, True, False, False, False, rq.ack_data(control, pgn, requester))

    # -- frames out --------------------------------------------------------------------------------

    def outgoing(self, frames: list[Frame]) -> list[Frame]:
        """The monitor's output frames as they may go out now (see the module)."""
        if not frames:
            return frames
        c = self.claim
        if c is not None:
            own, cur = self.p.address, c.address
            out = []
            for f in frames:
                fid = f.arbitration_id
                if f.extended and (fid >> 16) & 0xFF == _AC_PF:
                    out.append(f)
                elif not c.may_send(f.timestamp_s):
                    self.counts["held"] += 1
                elif cur != own and f.extended and fid & 0xFF == own:
                    out.append(f._replace(arbitration_id=(fid & ~0xFF) | cur))  # type: ignore[operator]
                else:
                    out.append(f)
            frames = out
        pgns = self.p.output_pgns
        for f in frames:
            if f.extended and ids.pgn(f.arbitration_id) in pgns:
                self.last_out[ids.pgn(f.arbitration_id)] = f
        return frames

    def outgoing_columns(self, cols: FrameColumns | None) -> FrameColumns | None:
        """:meth:`outgoing` over a piece of output frames as columns."""
        if cols is None or not len(cols):
            return cols
        c = self.claim
        if c is not None:
            fid = cols.arbitration_id.astype(np.int64)
            t = cols.timestamp_s
            claims = cols.extended & (((fid >> 16) & 0xFF) == _AC_PF)
            if c.state == ac.CLAIMING and t.max() >= c.settle_at:
                c.may_send(float(t.max()))  # the claim stands from settle_at
            standing = c.state in (ac.CLAIMING, ac.CLAIMED)
            keep = claims | (t >= c.settle_at) if standing else claims
            self.counts["held"] += int(len(cols) - keep.sum())
            if not keep.all():
                cols = cols.take(np.flatnonzero(keep))
                fid = fid[keep]
            if c.address is not None and c.address != self.p.address:
                moved = cols.extended & ((fid & 0xFF) == self.p.address) & ~(((fid >> 16) & 0xFF) == _AC_PF)
                if moved.any():
                    new = np.where(moved, (fid & ~0xFF) | c.address, fid).astype(np.uint32)
                    cols = FrameColumns(**{**_fields(cols), "arbitration_id": new})
        if len(cols):
            self._remember(cols)
        return cols

    def _remember(self, cols: FrameColumns) -> None:
        fid = cols.arbitration_id.astype(np.int64)
        pgn = ids.pgn(fid)
        for p in self.p.output_pgns:
            rows = np.flatnonzero(cols.extended & (pgn == p))
            if len(rows):
                self.last_out[p] = cols.frame(int(rows[-1]))

    # -- what it says about itself -------------------------------------------------------------------

    def describe(self) -> dict[str, Any]:
        c = self.claim
        out: dict[str, Any] = {
            "state": self.state,
            "address": self.address,
            "configured_address": self.p.address,
            **self.counts,
            "requests_refused_rate": self.limit.refused,
            "requests_refused_global": self.limit.refused_global,
            "connections_open": len(self.connections),
            "trusted_addresses": [f"0x{a:02X}" for a in self.p.trust.addresses],
            "trusted_names": [name_hex(n) for n in self.p.trust.names],
        }
        if c is not None:
            out["name"] = name_hex(c.name_value)
            out["contentions"] = c.contentions
            out["others"] = {f"0x{a:02X}": name_hex(n) for a, n in sorted(c.others.items())}
        return out


def _fields(cols: FrameColumns) -> dict[str, Any]:
    return {k: getattr(cols, k) for k in FrameColumns.__dataclass_fields__}
