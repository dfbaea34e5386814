"""Everything ``cmcan run`` and ``cmcan check`` verify before the bus is touched."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from cmcan import config as cfgmod
from cmcan.cli.errors import EX_CANTCREAT, EX_CONFIG, EX_NOINPUT, EX_UNAVAILABLE, CliError
from cmcan.dbc import DbcError
from cmcan.model import GrayBoxModel, ModelError, load_model
from cmcan.monitor.build import build_monitor
from cmcan.monitor.core import Monitor
from cmcan.schema import SchemaError
from cmcan.statefile import StateStore

_IFNAME = re.compile(r"^[A-Za-z0-9_.:-]{1,15}$")
ARPHRD_CAN = "280"


@dataclass
class Prepared:
    cfg: cfgmod.Config
    model: GrayBoxModel
    monitor: Monitor
    store: StateStore | None


def apply_overrides(raw: dict[str, Any], interface: str | None, channel: str | None, state_dir: str | None) -> None:
    if interface:
        raw["bus"]["interface"] = interface
    if channel:
        raw["bus"]["channel"] = channel
    if state_dir:
        raw["state"]["directory"] = state_dir


def load_config(
    path: str | None, interface: str | None = None, channel: str | None = None, state_dir: str | None = None
) -> cfgmod.Config:
    if path is not None and not Path(path).exists():
        raise CliError(f"{path}: configuration file not found", EX_NOINPUT)
    try:
        cfg = cfgmod.load(path)
    except SchemaError as exc:
        raise CliError(str(exc), EX_CONFIG) from None
    apply_overrides(cfg.raw, interface, channel, state_dir)
    return cfg


def check_channel(cfg: cfgmod.Config, sys_class_net: Path = Path("/sys/class/net")) -> None:
    """The interface is one python-can knows, and for SocketCAN the channel is an existing CAN link."""
    iface = cfg.raw["bus"]["interface"]
    chan = cfg.raw["bus"]["channel"]
    valid = sorted(can.interfaces.VALID_INTERFACES)
    if iface not in valid:
        raise CliError(
            f"{cfg.source}: bus.interface: unknown python-can interface {iface!r}; known: {', '.join(valid)}", EX_CONFIG
        )
    if iface != "socketcan":
        return
    if not _IFNAME.match(chan):
        raise CliError(
            f"{cfg.source}: bus.channel: {chan!r} is not a network interface name "
            "(1-15 letters, digits, '_', '.', ':', '-')",
            EX_CONFIG,
        )
    dev = sys_class_net / chan
    if not dev.exists():
        raise CliError(
            f"{cfg.source}: bus.channel: no network interface {chan!r} on this machine "
            f"(bring it up first, e.g. ip link set {chan} up type can bitrate "
            f"{cfg.raw['bus']['bitrate']})",
            EX_UNAVAILABLE,
        )
    kind = (dev / "type").read_text().strip() if (dev / "type").exists() else ARPHRD_CAN
    if kind != ARPHRD_CAN:
        raise CliError(f"{cfg.source}: bus.channel: {chan!r} is not a CAN interface (link type {kind})", EX_CONFIG)


def prepare(cfg: cfgmod.Config, need_state: bool = True, keep_timeline: bool = False) -> Prepared:
    """Load and cross-check DBC, mapping, model and state directory; build the monitor."""
    try:
        db = cfg.dbc()
        cfgmod.check_against_dbc(cfg, db)
    except DbcError as exc:
        raise CliError(f"{exc} (dbc: in {cfg.source})", EX_CONFIG) from None
    except SchemaError as exc:
        raise CliError(str(exc), EX_CONFIG) from None
    try:
        model = load_model(cfg.model_path, motor_disp_cc=cfg.motor_disp_cc)
    except ModelError as exc:
        raise CliError(f"{exc} (model: in {cfg.source})", EX_CONFIG) from None
    store = None
    if need_state:
        store = StateStore(cfg.raw["state"]["directory"])
        problem = store.check_writable()
        if problem is not None:
            raise CliError(f"{problem} (state.directory in {cfg.source})", EX_CANTCREAT)
    totals = store.load() if store is not None else None
    try:
        monitor = build_monitor(cfg, db, model, model.envelope, totals=totals, keep_timeline=keep_timeline)
    except SchemaError as exc:
        raise CliError(str(exc), EX_CONFIG) from None
    return Prepared(cfg, model, monitor, store)
