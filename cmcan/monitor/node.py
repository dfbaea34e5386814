"""cmcan as a J1939 node: its address claim, the requests it answers, and what it may send when.

A stage of the core like the others: driven by frames with timestamps (no clock), the same code for
both replay engines (the columnar engine hands the few network-management frames of a chunk to the
per-frame path, and gates its output with :meth:`Node.outgoing_columns` beside :meth:`Node.outgoing`).

What reaches it (the router hands it every J1939 Request, PGN 59904, and Address Claimed, PGN 60928,
on the output channel, whatever their destination):

- Address Claimed from other nodes: the contention rules of :mod:`cmcan.j1939.claim`;
- a Request (J1939-21) to cmcan's address or to all, each (requester, PGN) answered at most once per
  ``request_interval_s`` (:class:`cmcan.j1939.requests.RequestLimit`):

  | requested | answer |
  |---|---|
  | Address Claimed | Address Claimed (or Cannot Claim), by the claim |
  | DM1, DM2 (with DM1 on) | the active / previously active DTCs (:meth:`Dm1Producer.answer`) |
  | DM3, DM11 (with DM1 on) | the clear (the monitor carries it out), then ACK when addressed to cmcan |
  | a CM output's PGN | its last frame sent, at the request's time; NACK "cannot respond" before the first |
  | anything else | NACK when addressed to cmcan; nothing for a request to all |

  Until the claim stands (and after it is lost) only requests for Address Claimed are answered.

What leaves: every output frame of the monitor passes :meth:`Node.outgoing`: with a NAME configured,
nothing but Address Claimed goes out before the claim stands (250 ms after it) or after it was lost,
and a node that moved to another address sends from that address (the frames are made with the
configured one). The last frame of each CM output is kept for requests.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from cmcan.frame import Frame, FrameColumns
from cmcan.j1939 import claim as ac
from cmcan.j1939 import dm1, ids
from cmcan.j1939 import requests as rq
from cmcan.j1939.name import name_hex
from cmcan.monitor.diagnostics import Dm1Producer

CLEARS = {rq.PGN_DM3: "dm3", rq.PGN_DM11: "dm11"}
_AC_PF = rq.PGN_ADDRESS_CLAIMED >> 8


@dataclass(frozen=True)
class NodeParams:
    address: int  # the configured source address (every output frame is made with it)
    channel: str = ""  # the output channel, where the node lives
    claim: ac.ClaimParams | None = None  # None: no NAME, no claim (a fixed address from the address plan)
    output_pgns: frozenset[int] = frozenset()  # the PGNs of the CM output messages
    request_interval_s: float = 0.3


@dataclass
class Clear:
    """A DM3 or DM11 asked for: the monitor carries it out and records it."""

    kind: str  # "dm3" or "dm11"
    t_s: float
    by_address: int
    by_name: int | None  # the requester's NAME, where it claimed its address on this bus


class Node:
    def __init__(self, p: NodeParams) -> None:
        self.p = p
        self.claim = ac.AddressClaim(p.claim) if p.claim is not None else None
        self.limit = rq.RequestLimit(p.request_interval_s)
        self.started = False
        self.last_out: dict[int, Frame] = {}  # per CM output PGN: its last frame sent
        self.counts = {"node_frames": 0, "requests": 0, "answered": 0, "nack": 0, "held": 0}

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

    def handle(self, f: Frame, dm: Dm1Producer | None) -> tuple[list[Frame], Clear | None]:
        """A Request or Address Claimed at ``f``'s time: the frames answering it (at that time or
        later), and a clear the monitor is to carry out first."""
        self.counts["node_frames"] += 1
        t, fid, data = f.timestamp_s, f.arbitration_id, f.data
        if t != t:  # a frame without a readable time: nothing to answer when
            return [], None
        sa = ids.source_address(fid)
        if ids.pdu_format(fid) == _AC_PF:
            if self.claim is None or len(data) != 8:
                return [], None
            return self.claim.on_claim(t, sa, int.from_bytes(data, "little")), None
        pgn, dest = rq.requested_pgn(data), ids.pdu_specific(fid)
        if pgn is None or (dest != ids.GLOBAL_ADDRESS and dest != self.address):
            return [], None
        if pgn == rq.PGN_ADDRESS_CLAIMED and self.claim is not None:
            return self.claim.on_request(t, dest), None
        if not self.may_send(t) or not self.limit.allow(t, sa, pgn):
            return [], None
        self.counts["requests"] += 1
        return self._answer(t, sa, pgn, dest != ids.GLOBAL_ADDRESS, dm)

    def _answer(
        self, t: float, sa: int, pgn: int, direct: bool, dm: Dm1Producer | None
    ) -> tuple[list[Frame], Clear | None]:
        if dm is not None and pgn in (dm1.PGN_DM1, rq.PGN_DM2):
            self.counts["answered"] += 1
            return dm.answer(pgn, t), None
        if dm is not None and pgn in CLEARS:
            by = self.claim.others.get(sa) if self.claim is not None else None
            return ([self._ack(t, rq.ACK, pgn, sa)] if direct else []), Clear(CLEARS[pgn], t, sa, by)
        if pgn in self.p.output_pgns:
            last = self.last_out.get(pgn)
            if last is not None:
                self.counts["answered"] += 1
                return [last._replace(timestamp_s=t)], None
            return ([self._ack(t, rq.CANNOT_RESPOND, pgn, sa)] if direct else []), None
        return ([self._ack(t, rq.NACK, pgn, sa)] if direct else []), None

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
        }
        if c is not None:
            out["name"] = name_hex(c.name_value)
            out["contentions"] = c.contentions
            out["others"] = {f"0x{a:02X}": name_hex(n) for a, n in sorted(c.others.items())}
        return out


def _fields(cols: FrameColumns) -> dict[str, Any]:
    return {k: getattr(cols, k) for k in FrameColumns.__dataclass_fields__}
