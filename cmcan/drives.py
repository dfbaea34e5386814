"""Several drives on one gateway: each drive its own configuration (its model, state directory,
outputs, J1939 address and NAME), run as one instance of the templated unit ``cmcan@.service`` each.
What must not overlap between them is checked here, before any of them runs: two daemons sending the
same identifier on one bus (any output message, DM1), claiming the same J1939 address (their own or one
they may move to) or NAME, publishing with the same uplink machine id, MQTT client id or outbox, or
sharing a state directory."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from cmcan.errors import CmcanError, Kind

if TYPE_CHECKING:  # hints only: cmcan check's parser imports this module
    from cmcan.assemble import Assembled
    from cmcan.config import Config


def config_files(given: Sequence[str]) -> list[str]:
    """The configuration files named: a directory stands for the ``*.yaml`` files in it (sorted)."""
    out: list[str] = []
    for g in given:
        p = Path(g)
        if p.is_dir():
            found = sorted(str(f) for f in p.glob("*.yaml") if f.is_file())
            if not found:
                raise CmcanError(f"{g}: no drive configurations (*.yaml) in this directory", Kind.NO_INPUT)
            out += found
        else:
            out.append(g)
    return out


def sends(a: Assembled) -> dict[tuple[str, bool, int], str]:
    """Every identifier the drive's daemon sends, on its channel, with the message it carries: the
    output messages its configuration declares (:meth:`cmcan.config.Config.output_items`, the list
    the monitor's outputs are built from, CM_BASELINE and CM_PROGNOSIS included where enabled), with
    the identifiers the daemon gives them, and DM1."""
    from cmcan.assemble import output_id

    cfg = a.cfg
    out = {}
    for _key, item in cfg.output_items():
        msg = a.db.get_message_by_name(item.message)
        out[(cfg.output_channel, bool(msg.is_extended_frame), output_id(cfg, msg))] = item.message
    if a.monitor.dm1_producer is not None:
        out[(cfg.output_channel, True, a.monitor.dm1_producer.frame_id)] = "DM1"
    return out


def _addresses(cfg: Config) -> set[int]:
    """The J1939 source addresses the drive may claim: its own and those it may move to."""
    j = cfg.j1939
    if not j.enabled or j.source_address is None:
        return set()
    return {j.source_address, *j.addresses}


def conflicts(drives: Sequence[Assembled]) -> list[str]:
    """What two of the drives would both do on one gateway (empty: nothing)."""
    problems: list[str] = []
    for i, a in enumerate(drives):
        for b in drives[i + 1 :]:
            problems += _pair(a, b)
    return problems


def _pair(a: Assembled, b: Assembled) -> list[str]:
    """What drives ``a`` and ``b`` would share: identifiers sent on one channel, J1939 addresses and
    NAME, uplink machine id, client id and outbox, the state directory."""
    problems: list[str] = []
    pair = f"{a.cfg.source} and {b.cfg.source}"
    sa, sb = sends(a), sends(b)
    for key in sorted(set(sa) & set(sb)):
        ch, ext, fid = key
        problems.append(f"{pair} both send identifier 0x{fid:0{8 if ext else 3}X} on {ch} ({sa[key]} / {sb[key]})")
    ja, jb = a.cfg.j1939, b.cfg.j1939
    if ja.enabled and jb.enabled and a.cfg.output_channel == b.cfg.output_channel:
        if ja.source_address == jb.source_address:
            problems.append(f"{pair} both claim J1939 address 0x{ja.source_address:02X} on {a.cfg.output_channel}")
        elif both := sorted(_addresses(a.cfg) & _addresses(b.cfg)):
            listed = ", ".join(f"0x{x:02X}" for x in both)
            problems.append(
                f"{pair} may both claim J1939 address {listed} on {a.cfg.output_channel} "
                "(j1939.source_address and j1939.addresses overlap)"
            )
        if ja.name is not None and ja.name == jb.name:
            problems.append(f"{pair} have the same J1939 NAME {ja.name.hex()}: give each its own")
    problems += _uplinks(pair, a.cfg, b.cfg)
    if a.cfg.state.directory == b.cfg.state.directory:
        problems.append(f"{pair} share the state directory {a.cfg.state.directory}: give each its own")
    return problems


def _uplinks(pair: str, a: Config, b: Config) -> list[str]:
    """Two uplinks with one machine id mix their machines' topics; with one MQTT client id, the broker
    drops one connection for the other, over and over; with one outbox, one writer is refused."""
    ua, ub = a.uplink, b.uplink
    if not (ua.enabled and ub.enabled):
        return []
    out = []
    if ua.machine_id == ub.machine_id:
        out.append(f"{pair} have the same uplink.machine_id {ua.machine_id!r}: give each its own")
    if ua.mqtt.client_id == ub.mqtt.client_id:
        out.append(f"{pair} have the same uplink.mqtt.client_id {ua.mqtt.client_id!r}: give each its own")
    if ua.outbox.path == ub.outbox.path:
        out.append(f"{pair} share the uplink outbox {ua.outbox.path}: give each its own")
    return out
