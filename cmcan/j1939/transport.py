"""The J1939-21 transport protocol's broadcast form (BAM): a message of 9 to 1785 bytes to all nodes.

The sender announces the message with TP.CM (PGN 60416) carrying the BAM control byte (32), the total
size in bytes, the number of packets, 0xFF and the PGN of the packeted message; then sends the packets
as TP.DT (PGN 60160): a sequence number 1..n and 7 bytes of data, the last packet padded with 0xFF.
Both go to the global address with priority 7. J1939-21 wants 50 to 200 ms between the TP.CM and the
first TP.DT and between packets; a node has at most one BAM session of its own at a time.

``bam_frames`` gives the frames with their times from the start time and the gap, so the schedule is a
function of frame time alone (the daemon sends each at its time; a replay reproduces it).
``BamReceiver`` reassembles, for tests and for reading cmcan's own logs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from cmcan.frame import Frame
from cmcan.j1939 import ids

PGN_TP_CM = 60416  # 0xEC00
PGN_TP_DT = 60160  # 0xEB00
TP_PRIORITY = 7
CM_BAM = 32
MAX_SIZE = 1785  # 255 packets of 7 bytes
BAM_GAP_MIN_S = 0.05
BAM_GAP_MAX_S = 0.2


def packets(payload: bytes) -> list[bytes]:
    """The TP.DT data of each packet: sequence number and 7 bytes, the last padded with 0xFF."""
    n = (len(payload) + 6) // 7
    return [bytes((i + 1,)) + payload[7 * i : 7 * i + 7].ljust(7, b"\xff") for i in range(n)]


def bam_announce(pgn: int, payload: bytes) -> bytes:
    """The TP.CM_BAM data for ``payload`` of parameter group ``pgn``."""
    if not 9 <= len(payload) <= MAX_SIZE:
        raise ValueError(f"BAM carries 9..{MAX_SIZE} bytes, got {len(payload)}")
    n = (len(payload) + 6) // 7
    size = len(payload)
    return bytes((CM_BAM, size & 0xFF, size >> 8, n, 0xFF, pgn & 0xFF, (pgn >> 8) & 0xFF, pgn >> 16))


def bam_frames(t0_s: float, gap_s: float, pgn: int, payload: bytes, source: int, channel: str = "") -> list[Frame]:
    """TP.CM at ``t0_s`` and each TP.DT ``gap_s`` after the one before, from ``source`` to all."""
    if not BAM_GAP_MIN_S <= gap_s <= BAM_GAP_MAX_S:
        raise ValueError(f"J1939-21 wants 50..200 ms between BAM packets, got {gap_s * 1000:g} ms")
    cm_id = ids.make_id(TP_PRIORITY, PGN_TP_CM, source, ids.GLOBAL_ADDRESS)
    dt_id = ids.make_id(TP_PRIORITY, PGN_TP_DT, source, ids.GLOBAL_ADDRESS)
    out = [Frame(t0_s, channel, cm_id, True, False, False, False, bam_announce(pgn, payload))]
    for i, data in enumerate(packets(payload), 1):
        out.append(Frame(t0_s + i * gap_s, channel, dt_id, True, False, False, False, data))
    return out


@dataclass
class _Session:
    pgn: int
    size: int
    count: int
    data: bytearray = field(default_factory=bytearray)
    next_seq: int = 1


@dataclass
class BamReceiver:
    """Reassembles BAM sessions per source address, as a J1939 receiver does: a new TP.CM_BAM from a
    source aborts its unfinished session, a packet out of sequence drops the session."""

    sessions: dict[int, _Session] = field(default_factory=dict)
    aborted: int = 0

    def feed(self, can_id: int, data: bytes) -> tuple[int, int, bytes] | None:
        """(source, PGN, payload) when ``data`` completes a message, else None."""
        pf, sa = ids.pdu_format(can_id), ids.source_address(can_id)
        if pf == PGN_TP_CM >> 8 and len(data) >= 8 and data[0] == CM_BAM:
            if sa in self.sessions:
                self.aborted += 1
            size = data[1] | (data[2] << 8)
            self.sessions[sa] = _Session(data[5] | (data[6] << 8) | (data[7] << 16), size, data[3])
            return None
        if pf != PGN_TP_DT >> 8 or sa not in self.sessions or not data:
            return None
        s = self.sessions[sa]
        if data[0] != s.next_seq:
            del self.sessions[sa]
            self.aborted += 1
            return None
        s.data += data[1:8]
        s.next_seq += 1
        if s.next_seq > s.count:
            del self.sessions[sa]
            return sa, s.pgn, bytes(s.data[: s.size])
        return None
