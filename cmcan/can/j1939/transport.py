"""The J1939-21 transport protocol: a message of 9 to 1785 bytes to all nodes (BAM) or to one (RTS/CTS).

The sender announces the message with TP.CM (PGN 60416) carrying the BAM control byte (32), the total
size in bytes, the number of packets, 0xFF and the PGN of the packeted message; then sends the packets
as TP.DT (PGN 60160): a sequence number 1..n and 7 bytes of data, the last packet padded with 0xFF.
Both go to the global address with priority 7. J1939-21 wants 50 to 200 ms between the TP.CM and the
first TP.DT and between packets; a node has at most one BAM session of its own at a time.

``bam_frames`` gives the frames with their times from the start time and the gap, so the schedule is a
function of frame time alone (the daemon sends each at its time; a replay reproduces it).
``BamReceiver`` reassembles, for tests and for reading cmcan's own logs.

Connection mode (RTS/CTS) carries a message to one node, which paces it. The originator sends
TP.CM_RTS (control 16: size, packets, the most packets it sends per CTS, PGN) to the receiver; the
receiver answers TP.CM_CTS (17: how many packets it takes now, the next packet's number) and the
originator sends that window of TP.DT to it; a CTS with 0 packets holds the connection (the receiver
repeats it at least every Th = 500 ms); a CTS for a packet already sent asks for it again; after the
last packet the receiver sends TP.CM_EndOfMsgAck (19). Either side may end a connection with
TP.Conn_Abort (255, with a reason). The originator gives up (and aborts, reason "timeout") after
T3 = 1250 ms without a CTS or EndOfMsgAck after its RTS or a window's last packet, and after
T4 = 1050 ms without the next CTS after a hold. ``Sender`` is the originator as a state machine over
frame time (no clock): each TP.CM from the receiver and each instant it is told about (``expire``)
gives the frames to send then. ``ConnectionReceiver`` is the receiver, for tests.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from cmcan.can.frame import Frame
from cmcan.can.j1939 import ids

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


# -- connection mode (RTS/CTS) ---------------------------------------------------------------------------

CM_RTS = 16
CM_CTS = 17
CM_EOMA = 19  # End of Message Acknowledgment
CM_ABORT = 255
T1_S = 0.75  # receiver: at most this between packets
T2_S = 1.25  # receiver: at most this from its CTS to the first packet
T3_S = 1.25  # originator: at most this from its RTS or a window's last packet to a CTS or EndOfMsgAck
T4_S = 1.05  # originator: at most this from a hold (CTS with 0 packets) to the next CTS
TH_S = 0.5  # receiver: repeats a hold at least this often
TR_S = 0.2  # either side: answers within this
MAX_RETRANSMITS = 2  # CTS asking again for packets already sent, per connection
# Connection abort reasons (J1939-21)
ABORT_BUSY = 1  # already in a connection and cannot support another
ABORT_RESOURCES = 2  # resources needed for another task
ABORT_TIMEOUT = 3
ABORT_CTS_IN_TRANSFER = 4
ABORT_RETRANSMITS = 5  # the retransmit request limit reached
ABORT_UNEXPECTED_DT = 6
ABORT_BAD_SEQUENCE = 7
ABORT_DUPLICATE_SEQUENCE = 8
ABORT_TOO_LARGE = 9
ABORT_OTHER = 250

# The originator's states
WAIT_CTS = "wait_cts"  # after the RTS or a window's last packet (not the message's last)
HOLD = "hold"  # the receiver held the connection
WAIT_EOMA = "wait_eoma"  # every packet sent, waiting for the EndOfMsgAck (or a CTS asking again)
DONE = "done"  # the receiver acknowledged the whole message
ABORTED = "aborted"  # by the receiver, or by cmcan (timeout, a CTS it cannot follow)


def _pgn_bytes(pgn: int) -> bytes:
    return bytes((pgn & 0xFF, (pgn >> 8) & 0xFF, (pgn >> 16) & 0xFF))


def cm_pgn(data: bytes) -> int:
    """The PGN of the packeted message a TP.CM names (bytes 6-8)."""
    return data[5] | (data[6] << 8) | (data[7] << 16)


def rts_data(pgn: int, size: int, max_per_cts: int = 0xFF) -> bytes:
    """TP.CM_RTS: size, packets, the most packets per CTS (0xFF: no limit), PGN."""
    if not 9 <= size <= MAX_SIZE:
        raise ValueError(f"RTS/CTS carries 9..{MAX_SIZE} bytes, got {size}")
    return bytes((CM_RTS, size & 0xFF, size >> 8, (size + 6) // 7, max_per_cts)) + _pgn_bytes(pgn)


def cts_data(n_packets: int, next_packet: int, pgn: int) -> bytes:
    """TP.CM_CTS: packets to send now (0: hold), the next packet's number."""
    return bytes((CM_CTS, n_packets, next_packet, 0xFF, 0xFF)) + _pgn_bytes(pgn)


def eoma_data(size: int, pgn: int) -> bytes:
    return bytes((CM_EOMA, size & 0xFF, size >> 8, (size + 6) // 7, 0xFF)) + _pgn_bytes(pgn)


def abort_data(reason: int, pgn: int) -> bytes:
    """TP.Conn_Abort with its reason (byte 3: the role bits "not available")."""
    return bytes((CM_ABORT, reason, 0xFF, 0xFF, 0xFF)) + _pgn_bytes(pgn)


@dataclass
class Sender:
    """One RTS/CTS connection from ``source`` to ``dest`` (see the module). ``start`` gives the RTS;
    ``on_cm`` each TP.CM the receiver sends to ``source`` (the frames to send at its time);
    ``expire`` the abort due by a time. ``outcome`` says how it ended (None: open)."""

    pgn: int
    payload: bytes
    source: int
    dest: int
    channel: str = ""
    state: str = WAIT_CTS
    deadline_s: float = float("inf")
    sent: int = 0  # the highest packet number sent
    retransmits: int = 0
    holds: int = 0
    windows: int = 0
    outcome: str | None = None  # "sent", "aborted by receiver (reason N)", "timeout", "cmcan aborted (reason N)"

    def __post_init__(self) -> None:
        if not 9 <= len(self.payload) <= MAX_SIZE:
            raise ValueError(f"RTS/CTS carries 9..{MAX_SIZE} bytes, got {len(self.payload)}")
        self.packets = packets(self.payload)

    @property
    def open(self) -> bool:
        return self.state not in (DONE, ABORTED)

    def _frame(self, t: float, pgn: int, data: bytes) -> Frame:
        fid = ids.make_id(TP_PRIORITY, pgn, self.source, self.dest)
        return Frame(t, self.channel, fid, True, False, False, False, data)

    def start(self, t: float) -> list[Frame]:
        self.state, self.deadline_s = WAIT_CTS, t + T3_S
        return [self._frame(t, PGN_TP_CM, rts_data(self.pgn, len(self.payload)))]

    def abort(self, t: float, reason: int, outcome: str) -> list[Frame]:
        self.state, self.outcome, self.deadline_s = ABORTED, outcome, float("inf")
        return [self._frame(t, PGN_TP_CM, abort_data(reason, self.pgn))]

    def expire(self, t: float) -> list[Frame]:
        """The abort (reason timeout) when the connection's deadline passed by ``t``, sent at ``t``."""
        if self.open and t >= self.deadline_s:
            return self.abort(t, ABORT_TIMEOUT, "timeout")
        return []

    def on_cm(self, t: float, data: bytes) -> list[Frame]:
        """A TP.CM from the receiver at ``t``: the frames to send (a window of packets, an abort)."""
        if not self.open or len(data) < 8 or t != t:
            return []
        late = self.expire(t)
        if late:
            return late
        control, pgn = data[0], cm_pgn(data)
        if control == CM_ABORT:
            if pgn == self.pgn:
                self.state, self.outcome, self.deadline_s = (
                    ABORTED,
                    f"aborted by receiver (reason {data[1]})",
                    float("inf"),
                )
            return []
        if pgn != self.pgn:  # about another message: not this connection's
            return []
        if control == CM_EOMA:
            if self.state == WAIT_EOMA:
                self.state, self.outcome, self.deadline_s = DONE, "sent", float("inf")
            return []
        if control != CM_CTS:
            return []
        return self._cts(t, data[1], data[2])

    def _cts(self, t: float, n: int, nxt: int) -> list[Frame]:
        if n == 0:  # a hold: the next CTS within T4
            self.holds += 1
            self.state, self.deadline_s = HOLD, t + T4_S
            return []
        total = len(self.packets)
        if not 1 <= nxt <= total:
            return self.abort(t, ABORT_BAD_SEQUENCE, f"cmcan aborted (reason {ABORT_BAD_SEQUENCE})")
        if nxt <= self.sent:  # packets asked for again
            self.retransmits += 1
            if self.retransmits > MAX_RETRANSMITS:
                return self.abort(t, ABORT_RETRANSMITS, f"cmcan aborted (reason {ABORT_RETRANSMITS})")
        last = min(total, nxt + n - 1)
        self.windows += 1
        out = [self._frame(t, PGN_TP_DT, self.packets[i - 1]) for i in range(nxt, last + 1)]
        self.sent = max(self.sent, last)
        self.state = WAIT_EOMA if last == total else WAIT_CTS
        self.deadline_s = t + T3_S
        return out


@dataclass
class ConnectionReceiver:
    """The receiving side of RTS/CTS connections, for tests: takes an RTS and each packet, says what
    it would send (a CTS for ``window`` packets, the EndOfMsgAck) and gives the message when whole."""

    window: int = 255
    sessions: dict[int, _Session] = field(default_factory=dict)

    def feed(self, can_id: int, data: bytes) -> tuple[list[bytes], tuple[int, int, bytes] | None]:
        """(TP.CM data to send back, (source, PGN, payload) when ``data`` completes a message)."""
        pf, sa = ids.pdu_format(can_id), ids.source_address(can_id)
        if pf == PGN_TP_CM >> 8 and len(data) >= 8 and data[0] == CM_RTS:
            s = _Session(cm_pgn(data), data[1] | (data[2] << 8), data[3])
            self.sessions[sa] = s
            return [cts_data(min(self.window, s.count, data[4]), 1, s.pgn)], None
        if pf == PGN_TP_CM >> 8 and len(data) >= 8 and data[0] == CM_ABORT:
            self.sessions.pop(sa, None)
            return [], None
        if pf != PGN_TP_DT >> 8 or sa not in self.sessions or not data:
            return [], None
        s = self.sessions[sa]
        if data[0] != s.next_seq:
            del self.sessions[sa]
            return [abort_data(ABORT_BAD_SEQUENCE, s.pgn)], None
        s.data += data[1:8]
        s.next_seq += 1
        if s.next_seq > s.count:
            del self.sessions[sa]
            return [eoma_data(s.size, s.pgn)], (sa, s.pgn, bytes(s.data[: s.size]))
        if (s.next_seq - 1) % self.window == 0:
            return [cts_data(min(self.window, s.count - s.next_seq + 1), s.next_seq, s.pgn)], None
        return [], None
