"""cmcan's J1939 connection mode and trusted clears on a real SocketCAN bus (vcan0), with the kernel's
J1939 stack as the requester. Collected into ``cases`` (one VM for all).

One daemon start for every check (a Python start in the guest costs 30-75 s): the example machine,
its state seeded with three previously active DTCs, the service tool at 0xF9 trusted to clear
(``j1939.clears.trusted_addresses``), a leak log playing (the low warning from about 15 s). Two kernel
CAN_J1939 sockets: the service tool at 0xF9 and another node at 0xF1 that nobody trusts."""

from __future__ import annotations

import socket
import subprocess
import time

import cantools
import pytest

from cmcan.can.j1939 import dm1, ids, transport
from cmcan.can.j1939 import requests as rq
from cmcan.io.candump import iter_frames
from cmcan.monitor.totals import Totals
from cmcan.service.statefile import StateStore
from tests.vcan.node_cases import (
    IFACE,
    ROOT,
    SA,
    SOL_CAN_J1939,
    TOOL,
    _j1939_available,
    drive_log,
    node_config,
    settled,
    write_log,
)
from tests.vcan.support import SocketListener

OTHER = 0xF1  # a node the configuration does not trust
DEBOUNCE_S = 2.0  # node_config's thresholds.debounce_s
SEEDED = {"520193:9": 3, "520193:2": 1, "520193:12": 2}  # three previously active DTCs: DM2 of 14 bytes


class Peer(SocketListener):
    """A node on the kernel's J1939 stack: a CAN_J1939 socket bound to ``address``, which sends
    requests and keeps what it receives (the kernel reassembles BAM and RTS/CTS and answers the CTS
    and EndOfMsgAck itself; a directed transfer reaches only the socket bound to its destination)."""

    def __init__(self, address: int) -> None:
        self.address = address
        sock = socket.socket(socket.PF_CAN, socket.SOCK_DGRAM, socket.CAN_J1939)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        sock.bind((IFACE, socket.J1939_NO_NAME, socket.J1939_NO_PGN, address))
        super().__init__(sock)

    def read(self) -> tuple[int, int, int, bytes]:
        data, anc, _, addr = self.sock.recvmsg(2048, 256)
        dest = next((c[2][0] for c in anc if c[0] == SOL_CAN_J1939 and c[1] == socket.SCM_J1939_DEST_ADDR), 255)
        return addr[2], addr[3], dest, data

    def request(self, pgn: int, dest: int) -> float:
        t = time.monotonic()
        self.sock.sendto(rq.request_data(pgn), (IFACE, socket.J1939_NO_NAME, rq.PGN_REQUEST, dest))
        return t

    def from_cmcan(self, pgn: int, after: float) -> list[tuple[float, int, bytes]]:
        return [(t, d, data) for t, p, s, d, data in self.got if p == pgn and s == SA and t >= after]


@pytest.fixture(scope="module")
def trust_run(work):
    from tests.vcan.cases import Daemon, stop

    _j1939_available()
    tmp = work["tmp"]
    cfg = node_config(tmp, "trust", clears={"trusted_addresses": [TOOL]})
    StateStore(tmp / "trust-state").save(Totals(dtc_occurrences=dict(SEEDED)))
    log = write_log(tmp / "trust.log", drive_log(cfg, 30.0, 15.0, 0x03))
    bus_log = open(tmp / "trust-bus.log", "w")  # noqa: SIM115 - candump writes it until stopped
    rec = subprocess.Popen(["candump", "-L", IFACE], stdout=bus_log, stderr=subprocess.DEVNULL)
    tool, other = Peer(TOOL), Peer(OTHER)
    d = Daemon(tmp, cfg, "trust")
    asked: dict[str, float] = {}
    try:
        time.sleep(2.0)  # the daemon claims at its first idle step on the silent bus
        # DM2 while the bus is quiet: an emulated guest's daemon runs seconds behind a playing log,
        # later than the kernel's T2 (1.25 s) for its answer to the kernel's CTS
        asked["dm2"] = tool.request(rq.PGN_DM2, SA)
        time.sleep(4.0)
        player = subprocess.Popen(["canplayer", "-I", str(log), f"{IFACE}=can0"], stderr=subprocess.PIPE, text=True)
        t_play = time.monotonic()
        plan = [
            (20.0, "untrusted_dm11", other, rq.PGN_DM11, SA),
            (21.0, "untrusted_dm11_all", other, rq.PGN_DM11, 255),
            (24.0, "dm11", tool, rq.PGN_DM11, SA),
        ]
        for at, key, peer, pgn, dest in plan:
            time.sleep(max(0.0, t_play + at - time.monotonic()))
            asked[key] = peer.request(pgn, dest)
        assert player.wait(timeout=180) == 0, player.stderr.read()
        settled(d)  # the daemon has taken every frame (and request) of the log
        time.sleep(3.0)
    finally:
        stop(rec)
        bus_log.close()
        tool.close()
        other.close()
        d.stop()
    return {
        "bus": list(iter_frames(tmp / "trust-bus.log")),
        "tool": tool,
        "other": other,
        "asked": asked,
        "stderr": d.stderr(),
        "state": StateStore(tmp / "trust-state").read(),
    }


def _seen(run: dict) -> str:
    interesting = (rq.PGN_DM2, rq.PGN_ACK, dm1.PGN_DM1)
    got = [
        (round(t, 2), p, hex(s), d, data.hex())
        for t, p, s, d, data in run["tool"].got + run["other"].got
        if p in interesting
    ]
    tp = [
        (round(f.timestamp_s, 2), hex(f.arbitration_id), f.data.hex())
        for f in run["bus"]
        if ids.pdu_format(f.arbitration_id) in (0xEB, 0xEC)
    ]
    return f"asked {run['asked']}; got {got[:80]}; TP on the bus {tp[:40]}; daemon: {run['stderr'][-3000:]}"


@pytest.mark.vcan
def test_j1939_a_directed_dm2_of_three_dtcs_reaches_the_requesters_kernel_socket_by_rts_cts(trust_run):
    run, tool, other = trust_run, trust_run["tool"], trust_run["other"]
    dm2 = tool.from_cmcan(rq.PGN_DM2, run["asked"]["dm2"])
    assert dm2, _seen(run)
    _t, dest, data = dm2[0]
    assert dest == TOOL and len(data) == 14, _seen(run)  # to the tool alone, whole: 2 + 3 x 4 bytes
    got = sorted((x.spn, x.fmi, x.occurrence) for x in dm1.decode(data)[1])
    assert got == [(520193, 2, 1), (520193, 9, 3), (520193, 12, 2)]
    assert not other.from_cmcan(rq.PGN_DM2, 0.0)  # a directed transfer: not for 0xF1
    # on the bus: cmcan's RTS to 0xF9, the kernel's CTS and EndOfMsgAck to 0x8C, no BAM
    cm = [f for f in run["bus"] if ids.pdu_format(f.arbitration_id) == transport.PGN_TP_CM >> 8]
    rts = [f for f in cm if ids.source_address(f.arbitration_id) == SA and f.data[0] == transport.CM_RTS]
    assert rts and ids.pdu_specific(rts[0].arbitration_id) == TOOL and transport.cm_pgn(rts[0].data) == rq.PGN_DM2
    from_tool = [f.data[0] for f in cm if ids.source_address(f.arbitration_id) == TOOL]
    assert transport.CM_CTS in from_tool and transport.CM_EOMA in from_tool, cm
    assert not [f for f in cm if f.data[0] == transport.CM_BAM and transport.cm_pgn(f.data) == rq.PGN_DM2]


@pytest.mark.vcan
def test_j1939_dm11_from_an_untrusted_node_is_refused_and_a_trusted_one_keeps_the_warning(trust_run):
    run, tool, other, asked = trust_run, trust_run["tool"], trust_run["other"], trust_run["asked"]
    # the untrusted directed DM11: "access denied" to 0xF1; to all: silence; nothing cleared.
    # J1939-21 sends an ACK to the global address, the requester named in its address byte: 0xF1's
    # socket also hears the trusted tool's ACK, told apart by that byte
    acks_heard = [rq.decode_ack(d) for _, _, d in other.from_cmcan(rq.PGN_ACK, asked["untrusted_dm11"])]
    denied = [a for a in acks_heard if a.address == OTHER]
    assert [(a.control, a.pgn) for a in denied] == [(rq.ACCESS_DENIED, rq.PGN_DM11)], _seen(run)
    clears = run["state"].dtc_clears
    assert [(c["kind"], c["by_address"]) for c in clears] == [("dm11", TOOL)], clears
    # the trusted one: ACK, and the low warning's DTC back at once (count 1, amber lamp on) within
    # one debounce of the acknowledgment, while the leak is there
    acks = [(t, rq.decode_ack(d)) for t, _, d in tool.from_cmcan(rq.PGN_ACK, asked["dm11"])]
    t_ack = min(
        (t for t, a in acks if a.control == rq.ACK and a.pgn == rq.PGN_DM11 and a.address == TOOL), default=None
    )
    assert t_ack is not None, _seen(run)
    dm1s = [(t - t_ack, dm1.decode(d)) for t, _, d in tool.from_cmcan(dm1.PGN_DM1, 0.0)]
    before = [dtcs for t, (_, dtcs) in dm1s if -3 < t < 0]
    back = [(t, lamps, dtcs) for t, (lamps, dtcs) in dm1s if 0 < t <= DEBOUNCE_S]
    assert before and before[-1] and before[-1][0].fmi in (17, 18), dm1s
    assert back and all(lamps.amber_warning == dm1.Lamp.ON for _, lamps, _ in back), dm1s
    assert any(d and d[0].spn == 520192 and d[0].occurrence == 1 for _, _, d in back), dm1s
    # CM_WARNING on the bus never says ok again after the warning rose (despite three DM11s)
    msg = cantools.database.load_file(str(ROOT / "dbc" / "j1939-example.dbc")).get_message_by_name("CM_WARNING")
    mine = [f for f in run["bus"] if ids.source_address(f.arbitration_id) == SA]
    warn = [f for f in mine if ids.pgn(f.arbitration_id) == ids.pgn(msg.frame_id)]
    levels = [int(msg.decode(f.data, decode_choices=False)["warning_level"]) for f in warn]
    assert 1 in levels and 0 not in levels[levels.index(1) :], levels
