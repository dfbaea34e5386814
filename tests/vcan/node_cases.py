"""cmcan as a J1939 node on a real SocketCAN bus (vcan0) with the kernel's J1939 stack and can-utils as
the other nodes: its address claim before anything else, a contender with a lower NAME (can-utils'
j1939acd) that silences it or (arbitrary address capable) moves it, a service tool on a CAN_J1939
socket (trusted to clear) asking for Address Claimed, DM1, DM2, an unsupported PGN, DM3 and DM11; and two drives on one
bus, each its own daemon, with their inputs interleaved. Collected into ``cases`` (one VM for all)."""

from __future__ import annotations

import json
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import yaml

from cmcan import config as cfgmod
from cmcan.assemble import assemble, bus_plan, dbc_for
from cmcan.can.j1939 import dm1, ids
from cmcan.can.j1939 import requests as rq
from cmcan.io.candump import iter_frames, write_candump
from cmcan.monitor.totals import Totals
from cmcan.replay import FrameCollector, replay
from cmcan.service.statefile import StateStore
from cmcan.sim.frames import frames_from_run, with_source_address
from cmcan.sim.run import simulate
from tests.vcan import warm
from tests.vcan.support import SocketListener

ROOT = Path(__file__).resolve().parents[2]
IFACE = "vcan0"
SA, TOOL = 0x8C, 0xF9
SOL_CAN_J1939 = 107  # SOL_CAN_BASE + CAN_J1939 (linux/can.h); Python names SCM_J1939_DEST_ADDR only
ACD_NAME = 0x0000000000000001  # j1939acd's NAME: lower than any cmcan NAME, it wins every contention
RATIO_PGN = 65312


def _j1939_available() -> None:
    try:
        socket.socket(socket.PF_CAN, socket.SOCK_DGRAM, socket.CAN_J1939).close()
    except OSError as exc:
        pytest.skip(f"this kernel has no J1939 stack (module can-j1939): {exc}")


def node_config(tmp: Path, stem: str, **j1939) -> Path:
    """The example J1939 machine on vcan0, windows short enough for a test; ``j1939`` overrides."""
    raw = yaml.safe_load((ROOT / "config" / "j1939-example.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "j1939-example.dbc")
    raw["bus"].update(interface="socketcan", channel=IFACE)
    raw.setdefault("filter", {}).update(samples=20, min_samples=10)
    raw.setdefault("thresholds", {}).update(debounce_s=2.0)
    raw["state"]["directory"] = str(tmp / f"{stem}-state")
    (tmp / f"{stem}-state").mkdir(exist_ok=True)
    for k, v in j1939.items():
        if isinstance(v, dict):
            raw["j1939"].setdefault(k, {}).update(v)
        else:
            raw["j1939"][k] = v
    p = tmp / f"{stem}.yaml"
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    return p


def drive_log(cfg_path: Path, seconds: float, leak_lpm: float, source: int) -> object:
    """A steady rig point of the example machine, its controller at ``source``; a leak from 12 s."""
    from tests.test_monitor_j1939 import leak_scenario

    cfg = cfgmod.rename_channels(cfgmod.load(cfg_path), {IFACE: "can0"})
    db = dbc_for(cfg)
    plan = bus_plan(cfg, db)
    f = frames_from_run(simulate(leak_scenario(seconds, leak_lpm), db, plan.mapping), db, plan=plan)
    t0 = float(f.timestamp_s[0])
    if source != 0x03:
        for name in ("HST_PUMP", "HST_MOTOR", "HST_LOOP_PRESSURE", "VF"):
            f = with_source_address(f, db, plan, name, source, t0)
    return f


def write_log(path: Path, *parts) -> Path:
    t = np.concatenate([p.timestamp_s for p in parts])
    order = np.argsort(t, kind="stable")
    cat = lambda name: np.concatenate([getattr(p, name) for p in parts])[order]  # noqa: E731
    ext = np.concatenate([p.is_extended() for p in parts])[order]
    write_candump(path, cat("timestamp_s"), cat("arbitration_id"), cat("dlc"), cat("data"), "can0", ext)
    return path


class Tool(SocketListener):
    """A service tool on the kernel's J1939 stack: a CAN_J1939 socket at address 0xF9 that sends
    requests and keeps what it receives (PGN, source, destination from the kernel's SCM_J1939_DEST_ADDR,
    data; the transport protocol reassembled by the kernel)."""

    def __init__(self) -> None:
        sock = socket.socket(socket.PF_CAN, socket.SOCK_DGRAM, socket.CAN_J1939)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        sock.bind((IFACE, socket.J1939_NO_NAME, socket.J1939_NO_PGN, TOOL))
        super().__init__(sock)

    def read(self) -> tuple[int, int, int, bytes]:
        data, anc, _, addr = self.sock.recvmsg(2048, 256)
        dest = next((c[2][0] for c in anc if c[0] == SOL_CAN_J1939 and c[1] == socket.SCM_J1939_DEST_ADDR), 255)
        return addr[2], addr[3], dest, data

    def request(self, pgn: int, dest: int) -> float:
        t = time.monotonic()
        self.sock.sendto(rq.request_data(pgn), (IFACE, socket.J1939_NO_NAME, rq.PGN_REQUEST, dest))
        return t

    def from_cmcan(self, pgn: int, after: float, source: int = SA) -> list[tuple[float, int, bytes]]:
        return [(t, d, data) for t, p, s, d, data in self.got if p == pgn and s == source and t >= after]


@contextmanager
def j1939acd(address: int = SA) -> Iterator[None]:
    """can-utils' address claiming daemon with a NAME lower than any cmcan NAME, claiming ``address``
    for as long as the block runs."""
    acd = subprocess.Popen(["j1939acd", "-r", f"0x{address:x}", f"{ACD_NAME:016x}", IFACE], stderr=subprocess.DEVNULL)
    try:
        yield
    finally:
        acd.terminate()
        acd.wait(timeout=10)


def cm_check(cfg: Path) -> dict:
    r = warm.run(["check", "--config", str(cfg), "--channel-check", "--json"], timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    return json.loads(r.stdout)["j1939"]["bus"]


@pytest.fixture(scope="module")
def service_run(work):
    """The example machine's daemon (state seeded with two previously active DTCs) while a leak log
    plays; a service tool's requests; then j1939acd takes 0x8C with a lower NAME."""
    from tests.vcan.cases import Daemon, stop

    _j1939_available()
    tmp = work["tmp"]
    cfg = node_config(tmp, "node", clears={"trusted_addresses": [TOOL]})  # the service tool may clear
    StateStore(tmp / "node-state").save(Totals(dtc_occurrences={"520193:9": 3, "520193:2": 1}))
    log = write_log(tmp / "node.log", drive_log(cfg, 30.0, 15.0, 0x03))
    bus_log = open(tmp / "node-bus.log", "w")  # noqa: SIM115 - candump writes it until stopped
    rec = subprocess.Popen(["candump", "-L", IFACE], stdout=bus_log, stderr=subprocess.DEVNULL)
    tool = Tool()
    d = Daemon(tmp, cfg, "node")
    asked: dict[str, float] = {}
    try:
        time.sleep(2.0)  # the daemon claims at its first idle step on the silent bus
        # DM2 (two DTCs: RTS/CTS to the tool) while the bus is quiet: an emulated guest's daemon runs
        # seconds behind a playing log, later than the kernel's T2 (1.25 s) for its answer to a CTS
        asked["dm2"] = tool.request(rq.PGN_DM2, SA)
        time.sleep(4.0)
        player = subprocess.Popen(["canplayer", "-I", str(log), f"{IFACE}=can0"], stderr=subprocess.PIPE, text=True)
        t_play = time.monotonic()
        plan = [
            (1.0, "ac", rq.PGN_ADDRESS_CLAIMED, 255),
            (2.0, "dm1", dm1.PGN_DM1, SA),
            (3.0, "nack", 65262, SA),
            (5.0, "dm3", rq.PGN_DM3, SA),
            (6.0, "dm2_after", rq.PGN_DM2, SA),
            (22.0, "dm11", rq.PGN_DM11, SA),
        ]
        for at, key, pgn, dest in plan:
            time.sleep(max(0.0, t_play + at - time.monotonic()))
            asked[key] = tool.request(pgn, dest)
        assert player.wait(timeout=180) == 0, player.stderr.read()
        time.sleep(1.0)
        asked["acd"] = time.monotonic()
        with j1939acd():
            time.sleep(4.0)
            probe = cm_check(cfg)
            time.sleep(0.5)
    finally:
        stop(rec)
        bus_log.close()
        tool.close()
        d.stop()
    return {
        "cfg": cfg,
        "log": log,
        "bus": list(iter_frames(tmp / "node-bus.log")),
        "tool": tool,
        "asked": asked,
        "probe": probe,
        "stderr": d.stderr(),
        "name": cfgmod.load(cfg).j1939.name,
    }


def _seen(tool: Tool, run: dict) -> str:
    """What the tool received and what the daemon said, for a failing assertion."""
    asked = {k: round(v - run["asked"].get("ac", 0.0), 2) for k, v in run["asked"].items()}
    got = [(round(t - run["asked"].get("ac", 0.0), 2), p, hex(s), d, data.hex()) for t, p, s, d, data in tool.got]
    return f"asked {asked}; got {got[:60]}; daemon: {run['stderr'][-2000:]}"


def _mine(frames, source=SA):
    return [f for f in frames if f.extended and ids.source_address(f.arbitration_id) == source]


@pytest.mark.vcan
def test_j1939_cmcan_claims_its_address_before_its_first_cm_frame(service_run):
    run = service_run
    mine = _mine(run["bus"])
    assert mine, "nothing from 0x8C on the bus"
    first = mine[0]
    assert ids.pgn(first.arbitration_id) == rq.PGN_ADDRESS_CLAIMED and first.data == run["name"].to_bytes()
    cm = [f for f in mine if ids.pgn(f.arbitration_id) == RATIO_PGN]
    assert cm and cm[0].timestamp_s >= first.timestamp_s + 0.25  # J1939-81: 250 ms for contenders
    assert "J1939: address 0x8C claimed" in run["stderr"], run["stderr"]


@pytest.mark.vcan
def test_j1939_a_tool_on_a_kernel_socket_gets_address_claimed_dm1_dm2_and_a_nack(service_run):
    run, tool, asked = service_run, service_run["tool"], service_run["asked"]
    ac_ = tool.from_cmcan(rq.PGN_ADDRESS_CLAIMED, asked["ac"])
    seen = _seen(tool, run)
    assert ac_ and ac_[0][2] == run["name"].to_bytes(), seen
    d1 = tool.from_cmcan(dm1.PGN_DM1, asked["dm1"])
    assert d1, seen
    nack = [x for x in tool.from_cmcan(rq.PGN_ACK, asked["nack"]) if rq.decode_ack(x[2]).pgn == 65262]
    assert nack, tool.got
    _t, dest, data = nack[0]
    a = rq.decode_ack(data)
    assert (a.control, a.address, dest) == (rq.NACK, TOOL, 255)  # to all, the tool named in byte 5
    dm2 = tool.from_cmcan(rq.PGN_DM2, asked["dm2"])
    assert dm2, tool.got
    _lamps, dtcs = dm1.decode(dm2[0][2])
    assert [(x.spn, x.fmi, x.occurrence) for x in dtcs] == [(520193, 2, 1), (520193, 9, 3)] and len(dm2[0][2]) == 10
    assert dm2[0][1] == TOOL  # asked by the tool alone: RTS/CTS to it (J1939-21 connection mode)


@pytest.mark.vcan
def test_j1939_dm3_and_dm11_clear_as_j1939_73_says(service_run):
    run, tool, asked = service_run, service_run["tool"], service_run["asked"]
    acks = [(t, rq.decode_ack(d)) for t, _, d in tool.from_cmcan(rq.PGN_ACK, asked["dm3"])]
    assert any(a.control == rq.ACK and a.pgn == rq.PGN_DM3 and a.address == TOOL for _, a in acks), acks
    after = tool.from_cmcan(rq.PGN_DM2, asked["dm2_after"])
    assert after and dm1.decode(after[0][2])[1] == [], _seen(tool, run)  # DM3 forgot the previously active DTCs
    assert any(a.control == rq.ACK and a.pgn == rq.PGN_DM11 for _, a in acks), acks
    # DM1 broadcasts: the low warning's DTC before DM11, right after it again at once with count 1
    # (still leaking: DM11 clears the count, not a condition that is there). "After" counts from
    # cmcan's acknowledgment: an emulated guest's daemon may take the request a second after it was sent.
    t_clear = min(t for t, a in acks if a.control == rq.ACK and a.pgn == rq.PGN_DM11)
    dm1s = [(t - t_clear, dm1.decode(d)[1]) for t, _, d in tool.from_cmcan(dm1.PGN_DM1, 0.0)]
    before = [x for t, x in dm1s if -3 < t < 0]
    right_after = [x for t, x in dm1s if 0 < t < 1.5]
    later = [x for t, x in dm1s if t > 3]
    assert before and before[-1] and before[-1][0].fmi in (17, 18), dm1s
    assert right_after and right_after[0] and right_after[0][0].occurrence == 1, dm1s
    assert later and later[-1] and later[-1][0].fmi in (17, 18) and later[-1][0].occurrence == 1, dm1s
    state = json.loads((Path(run["cfg"]).parent / "node-state" / "state.json").read_text())
    assert [(c["kind"], c["by_address"]) for c in state["dtc_clears"]] == [("dm3", TOOL), ("dm11", TOOL)]


@pytest.mark.vcan
def test_j1939_a_lower_name_from_j1939acd_silences_cmcan(service_run):
    run = service_run
    cannot = [
        f
        for f in run["bus"]
        if ids.source_address(f.arbitration_id) == ids.NULL_ADDRESS and f.data == run["name"].to_bytes()
    ]
    assert cannot, "no Cannot Claim from cmcan's NAME"
    # from its Cannot Claim on (the moment it took the contender's claim in: the emulated guest's
    # daemon runs behind the bus), nothing from 0x8C but j1939acd's claims
    late = [f for f in _mine(run["bus"]) if f.timestamp_s > cannot[0].timestamp_s]
    assert late and all(f.data == ACD_NAME.to_bytes(8, "little") for f in late), late[:5]
    t_acd = min(f.timestamp_s for f in run["bus"] if f.data == ACD_NAME.to_bytes(8, "little"))
    assert cannot[0].timestamp_s >= t_acd
    assert "J1939: cannot claim an address" in run["stderr"], run["stderr"]
    assert run["probe"]["state"] == "lost", run["probe"]  # cmcan check --channel-check sees it


@pytest.fixture(scope="module")
def arbitrary_run(work):
    """An arbitrary address capable daemon on the silent bus (its CM frames say no_input); j1939acd takes 0x8C."""
    from tests.vcan.cases import Daemon, stop

    _j1939_available()
    tmp = work["tmp"]
    cfg = node_config(
        tmp, "arb", name={"arbitrary_address_capable": True, "identity_number": 1003}, addresses=[0x8D, 0x8E]
    )
    bus_log = open(tmp / "arb-bus.log", "w")  # noqa: SIM115
    rec = subprocess.Popen(["candump", "-L", IFACE], stdout=bus_log, stderr=subprocess.DEVNULL)
    d = Daemon(tmp, cfg, "arb")
    try:
        time.sleep(3.0)
        with j1939acd():
            time.sleep(5.0)
            probe = cm_check(cfg)
    finally:
        stop(rec)
        bus_log.close()
        d.stop()
    return {"bus": list(iter_frames(tmp / "arb-bus.log")), "probe": probe, "stderr": d.stderr()}


@pytest.mark.vcan
def test_j1939_arbitrary_address_capable_moves_to_a_free_address_and_goes_on(arbitrary_run):
    run = arbitrary_run
    bus = run["bus"]
    t_acd = min(f.timestamp_s for f in bus if f.data == ACD_NAME.to_bytes(8, "little"))
    before = [f for f in _mine(bus, SA) if ids.pgn(f.arbitration_id) == RATIO_PGN]
    moved = [f for f in _mine(bus, 0x8D) if ids.pgn(f.arbitration_id) == RATIO_PGN]
    claim = [f for f in _mine(bus, 0x8D) if ids.pgn(f.arbitration_id) == rq.PGN_ADDRESS_CLAIMED]
    assert before and before[0].timestamp_s < t_acd and claim
    # J1939-81: nothing but the claim in the 250 ms after it was on the bus (the candump's time)
    assert moved and len(moved) > 20, (len(moved), claim[0].timestamp_s)
    assert moved[0].timestamp_s >= claim[0].timestamp_s + 0.25, moved[0].timestamp_s - claim[0].timestamp_s
    late = [f for f in _mine(bus, SA) if f.timestamp_s > t_acd + 1.5]
    assert all(f.data == ACD_NAME.to_bytes(8, "little") for f in late)
    assert run["probe"]["state"] == "claimed" and run["probe"]["address"] == 0x8D, run["probe"]
    assert "J1939: address 0x8D claimed" in run["stderr"], run["stderr"]


@pytest.fixture(scope="module")
def two_drives(work):
    """Left and right travel drives: their controllers at 0x03 and 0x13 send the same PGNs, one log
    with both interleaved; a daemon per drive (0x8C and 0x8D); only the left one leaks."""
    from tests.vcan.cases import Daemon, stop

    _j1939_available()
    tmp = work["tmp"]
    left = node_config(tmp, "left", source_addresses=[0x03])
    right = node_config(
        tmp,
        "right",
        source_address=0x8D,
        source_addresses=[0x13],
        name={"identity_number": 1004, "function_instance": 1},
    )
    log = write_log(tmp / "two.log", drive_log(left, 30.0, 15.0, 0x03), drive_log(right, 30.0, 0.0, 0x13))
    bus_log = open(tmp / "two-bus.log", "w")  # noqa: SIM115
    rec = subprocess.Popen(["candump", "-L", IFACE], stdout=bus_log, stderr=subprocess.DEVNULL)
    dl, dr = Daemon(tmp, left, "left"), Daemon(tmp, right, "right")
    try:
        time.sleep(1.0)
        player = subprocess.Popen(["canplayer", "-I", str(log), f"{IFACE}=can0"], stderr=subprocess.PIPE, text=True)
        assert player.wait(timeout=180) == 0, player.stderr.read()
        status = (settled(dl), settled(dr))
    finally:
        stop(rec)
        bus_log.close()
        dl.stop()
        dr.stop()
    return {"left": left, "right": right, "log": log, "bus": list(iter_frames(tmp / "two-bus.log")), "status": status}


def settled(daemon, timeout_s: float = 60.0) -> str:
    """The daemon's status line once it has taken every frame of the log: two reports in a row (2 s
    apart) with the same frame count. An emulated guest's daemon may still be working through the
    log when the player ends."""
    deadline = time.monotonic() + timeout_s
    last = daemon.fresh_status()["frames_total"]
    while time.monotonic() < deadline:
        now = daemon.fresh_status()["frames_total"]
        if now == last:
            return daemon.notify.status()
        last = now
    raise AssertionError(f"the daemon was still taking frames after {timeout_s} s: {daemon.notify.status()}")


@pytest.mark.vcan
def test_two_drives_on_one_bus_each_warns_from_its_own_inputs_only(two_drives):
    run = two_drives

    def levels(cfg_path, frames, source):
        parts = assemble(cfgmod.load(cfg_path))
        warn = ids.with_source(parts.monitor.outputs.warning.frame_id, source)
        msg = parts.db.get_message_by_name("CM_WARNING")
        return [
            int(msg.decode(f.data, decode_choices=False)["warning_level"]) for f in frames if f.arbitration_id == warn
        ]

    live_left, live_right = levels(run["left"], run["bus"], 0x8C), levels(run["right"], run["bus"], 0x8D)
    assert live_left and live_right
    assert 1 in live_left  # the leaking left drive: low
    assert set(live_right) == {0}  # the right one, on the same bus at the same time: ok throughout
    # each daemon used exactly the inputs a replay of the interleaved log with its configuration uses
    for cfg_path, status in zip((run["left"], run["right"]), run["status"], strict=True):
        parts = assemble(cfgmod.load(cfg_path))
        out = FrameCollector()
        replay(parts.monitor, iter_frames(run["log"]), [out])
        c = parts.monitor.counters
        assert f"inputs {c['accepted']}," in status, status
        assert c["unknown_id"] > 1000  # the other drive's frames are not inputs
