"""``cmcan run``: the daemon on the machine's bus."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path
from types import FrameType

import can

from cmcan.config import Config
from cmcan.daemon import Daemon, DaemonOptions, bus_kwargs, tune_socketcan
from cmcan.monitor.core import Monitor
from cmcan.preflight import check_channel, load_config, prepare
from cmcan.sdnotify import Notifier
from cmcan.uplink.config import UplinkSettings
from cmcan.uplink.feed import UplinkFeed

log = logging.getLogger("cmcan")


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run the monitoring daemon on the CAN bus",
        description="Monitor the drive on the configured bus and broadcast CM ratio and warnings. "
        "Under systemd it reports READY, WATCHDOG and STATUS; SIGTERM or SIGINT stop it.",
    )
    p.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
    p.add_argument("--interface", help="python-can interface (overrides bus.interface)")
    p.add_argument("--channel", help="channel, e.g. can0 (overrides bus.channel)")
    p.add_argument("--state-dir", help="state directory (overrides state.directory)")
    p.set_defaults(func=run)


def open_uplink_feed(cfg: Config, monitor: Monitor) -> UplinkFeed | None:
    """The daemon's side of the telematics uplink (issue 15): the outbox writer, when enabled."""
    settings = UplinkSettings.from_raw(
        cfg.raw["uplink"], cfg.raw["state"]["directory"], Path(cfg.source).resolve().parent, cfg.source
    )
    return UplinkFeed.open(settings, monitor) if settings.enabled else None


def run(args: argparse.Namespace) -> int:
    if args.verbose == 0:
        logging.getLogger().setLevel(logging.INFO)
    cfg = load_config(args.config, args.interface, args.channel, args.state_dir)
    prep = prepare(cfg)  # files first (config, DBC, model, state), then the machine's channel
    check_channel(cfg)
    ids = list(prep.monitor.inputs)
    rcvbuf = int(cfg.raw["bus"]["receive_buffer_bytes"])

    def open_bus() -> can.BusABC:
        bus = can.Bus(**bus_kwargs(cfg, ids))
        if cfg.raw["bus"]["interface"] == "socketcan":
            tune_socketcan(bus, rcvbuf)
        return bus

    uplink = open_uplink_feed(cfg, prep.monitor)  # issue 15: None unless uplink.enabled
    daemon = Daemon(cfg, prep.monitor, prep.store, open_bus, Notifier(), DaemonOptions(), uplink=uplink)

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        log.info("received %s, stopping", signal.Signals(signum).name)
        daemon.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    sys.stdout.flush()
    daemon.run()
    return 0
