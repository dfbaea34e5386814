"""``cmcan check --channel-check`` on a J1939 machine with a NAME: who holds cmcan's address now.

It asks the bus (a Request for Address Claimed from the null address 254 to all, as J1939-81 lets a
node without an address ask) and listens for the Address Claimed answers for 1.25 s (J1939-21's
response timeout), then says what cmcan's daemon holds or would get: its address claimed by its own
NAME (the daemon runs and holds it), Cannot Claim from its NAME (the daemon lost it), free, or held by
another NAME that wins (lower) or loses (higher) against cmcan's."""

from __future__ import annotations

import time
from typing import Any

from cmcan.can.j1939 import ids
from cmcan.can.j1939 import requests as rq
from cmcan.can.j1939.name import name_hex
from cmcan.config import Config

LISTEN_S = 1.25


def probe(cfg: Config, listen_s: float = LISTEN_S) -> dict[str, Any]:
    import can

    j = cfg.j1939
    assert j.name is not None and j.source_address is not None
    claims: dict[int, int] = {}  # address (254: cannot claim) -> NAME
    cannot: set[int] = set()
    flt = [{"can_id": 0x00EE0000, "can_mask": 0x03FF0000, "extended": True}]
    with can.Bus(interface=cfg.bus.interface, channel=cfg.output_channel, can_filters=flt) as bus:
        fid = ids.make_id(rq.REQUEST_PRIORITY, rq.PGN_REQUEST, ids.NULL_ADDRESS, ids.GLOBAL_ADDRESS)
        bus.send(can.Message(arbitration_id=fid, is_extended_id=True, data=rq.request_data(rq.PGN_ADDRESS_CLAIMED)))
        end = time.monotonic() + listen_s
        while (left := end - time.monotonic()) > 0:
            msg = bus.recv(timeout=left)
            if msg is None or not msg.is_extended_id or len(msg.data) != 8:
                continue
            if ids.pdu_format(msg.arbitration_id) != rq.PGN_ADDRESS_CLAIMED >> 8:
                continue
            sa, name = ids.source_address(msg.arbitration_id), int.from_bytes(bytes(msg.data), "little")
            if sa == ids.NULL_ADDRESS:
                cannot.add(name)
            else:
                claims[sa] = name
    return judge(j.name.value, j.source_address, claims, cannot, j.addresses)


def judge(
    mine: int, address: int, claims: dict[int, int], cannot: set[int], addresses: tuple[int, ...] = ()
) -> dict[str, Any]:
    """What the answers say about cmcan's NAME and address."""
    held = next((a for a, n in claims.items() if n == mine), None)
    holder = claims.get(address)
    if held is not None:
        state, text = "claimed", f"0x{held:02X} claimed by cmcan's NAME {name_hex(mine)} (its daemon holds it)"
    elif mine in cannot:
        state, text = "lost", f"cmcan's NAME {name_hex(mine)} answered Cannot Claim (its daemon lost its address)"
    elif holder is None:
        state, text = "free", f"0x{address:02X} is free: cmcan's daemon will claim it"
    elif holder < mine:
        where = "move within j1939.addresses" if addresses else "send Cannot Claim and stay silent"
        state, text = (
            "taken",
            f"0x{address:02X} is held by NAME {name_hex(holder)}, lower than cmcan's: cmcan would {where}",
        )
    else:
        state, text = (
            "contested",
            f"0x{address:02X} is held by NAME {name_hex(holder)}, higher than cmcan's: cmcan takes it",
        )
    return {
        "state": state,
        "text": text,
        "address": held if held is not None else address,
        "claims": {f"0x{a:02X}": name_hex(n) for a, n in sorted(claims.items())},
    }
