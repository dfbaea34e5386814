"""Everything ``cmcan run`` and ``cmcan check`` verify before the bus is touched."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, replace
from pathlib import Path

from cmcan import config as cfgmod
from cmcan.assemble import Assembled, assemble, build_monitor
from cmcan.errors import CmcanError, Kind
from cmcan.service.statefile import StateLock, StateStore

log = logging.getLogger("cmcan.preflight")

_IFNAME = re.compile(r"[A-Za-z0-9_.:-]{1,15}")
ARPHRD_CAN = "280"


@dataclass(frozen=True)
class Prepared:
    parts: Assembled
    store: StateStore | None
    lock: StateLock | None = None  # the daemon's hold on the state directory

    @property
    def cfg(self) -> cfgmod.Config:
        return self.parts.cfg


def load_config(
    path: str | None, interface: str | None = None, channel: str | None = None, state_dir: str | None = None
) -> cfgmod.Config:
    """The configuration file (the shipped one if None) with the command line's overrides."""
    if path is not None and not Path(path).exists():
        raise CmcanError(f"{path}: configuration file not found", Kind.NO_INPUT)
    return cfgmod.with_overrides(cfgmod.load(path), interface, channel, state_dir)


def check_channel(
    cfg: cfgmod.Config, sys_class_net: Path = Path("/sys/class/net"), *, extras_may_be_absent: bool = False
) -> list[str]:
    """The interface is one python-can knows, and for SocketCAN every configured channel is an
    existing CAN link (a CAN FD bus with the FD MTU).

    With ``extras_may_be_absent`` (the daemon, at a start and a reload) an extra channel that does not
    exist yet is not an error but a link that is down: a USB CAN adapter may enumerate after the
    service started. It is logged as a warning and returned; the daemon opens it when it appears, with
    the back-off of a lost link. The first channel (bus.channel) must exist (the unit waits for its
    device), and every name must be a valid interface name. ``cmcan check`` leaves the flag off: an
    absent channel is reported to the operator, exit 69."""
    import can

    iface = cfg.bus.interface
    valid = sorted(can.interfaces.VALID_INTERFACES)
    if iface not in valid:
        raise CmcanError(
            f"{cfg.source}: bus.interface: unknown python-can interface {iface!r}; known: {', '.join(valid)}",
            Kind.CONFIG,
        )
    if iface != "socketcan":
        return []
    absent: list[str] = []
    for i, ch in enumerate(cfg.channel_list):
        field = "bus.channel" if i == 0 else f"channels.extra[{i - 1}].channel"
        bitrate = ch.bitrate or cfg.bus.bitrate
        try:
            _check_link(cfg, field, ch.name, ch.fd, bitrate, sys_class_net)
        except _Absent as exc:
            if i == 0 or not extras_may_be_absent:
                raise CmcanError(str(exc), Kind.UNAVAILABLE) from None
            log.warning(
                "%s: %s: no network interface %r yet; running without it and opening it when it appears "
                "(expected: a CAN link, e.g. ip link set %s up type can bitrate %d)",
                cfg.source,
                field,
                ch.name,
                ch.name,
                bitrate,
            )
            absent.append(ch.name)
    return absent


class _Absent(Exception):
    """A well-named channel with no interface on this machine (yet)."""


CANFD_MTU = 72


def _check_link(cfg: cfgmod.Config, field: str, chan: str, fd: bool, bitrate: int, sys_class_net: Path) -> None:
    if not _IFNAME.fullmatch(chan):
        raise CmcanError(
            f"{cfg.source}: {field}: {chan!r} is not a network interface name "
            "(1-15 letters, digits, '_', '.', ':', '-')",
            Kind.CONFIG,
        )
    dev = sys_class_net / chan
    if not dev.exists():
        raise _Absent(
            f"{cfg.source}: {field}: no network interface {chan!r} on this machine "
            f"(bring it up first, e.g. ip link set {chan} up type can bitrate {bitrate})"
        )
    kind = (dev / "type").read_text().strip() if (dev / "type").exists() else ARPHRD_CAN
    if kind != ARPHRD_CAN:
        raise CmcanError(f"{cfg.source}: {field}: {chan!r} is not a CAN interface (link type {kind})", Kind.CONFIG)
    mtu = (dev / "mtu").read_text().strip() if (dev / "mtu").exists() else ""
    if fd and mtu.isdigit() and int(mtu) < CANFD_MTU:
        raise CmcanError(
            f"{cfg.source}: {field}: {chan!r} is configured as CAN FD but the link is classic CAN (MTU {mtu}); "
            f"set it up with fd on (ip link set {chan} type can ... fd on, or mtu 72 for a vcan)",
            Kind.CONFIG,
        )


def state_store(cfg: cfgmod.Config) -> StateStore:
    store = StateStore(cfg.state.directory)
    problem = store.check_writable()
    if problem is not None:
        named = cfg.state.origin or f"state.directory in {cfg.source}"
        raise CmcanError(f"{problem} ({named})", Kind.CANT_CREATE)
    return store


def prepare(cfg: cfgmod.Config, need_state: bool = True, read_only: bool = False) -> Prepared:
    """DBC, mapping, model and state directory checked against each other; the monitor built with
    the saved totals. ``read_only`` (``cmcan check``) changes nothing: a state file that cannot be
    used is an error naming it instead of being kept aside as the daemon does."""
    prep = Prepared(assemble(cfg), None)
    return with_state(prep, read_only=read_only) if need_state else prep


def with_state(prep: Prepared, read_only: bool = False, lock: bool = False) -> Prepared:
    """The state directory added to what is prepared, last, so that a problem found before leaves it
    as it was: with ``lock`` the daemon's exclusive hold on it is taken first (a second daemon on the
    same directory stops there with a temporary failure naming the lock and its holder), then the
    saved totals are read (the daemon keeps a corrupt file aside; ``read_only`` refuses it)."""
    cfg, parts = prep.cfg, prep.parts
    store = state_store(cfg)
    held = StateLock(store.dir).acquire() if lock else None
    try:
        totals = store.read() if read_only else store.load()
        monitor = build_monitor(cfg, parts.db, parts.model, totals)
    except BaseException:
        if held is not None:
            held.release()
        raise
    return Prepared(replace(parts, monitor=monitor), store, held)
