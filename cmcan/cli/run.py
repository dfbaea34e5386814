"""``cmcan run``: the daemon on the machine's bus."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from collections.abc import Callable
from types import FrameType

import can

from cmcan.config import ChannelConfig
from cmcan.daemon import Daemon, DaemonOptions, bus_kwargs, tune_socketcan
from cmcan.preflight import check_channel, load_config, prepare
from cmcan.sdnotify import Notifier
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
    p.add_argument("--channel", help="channel, e.g. can0 (overrides bus.channel, wherever the configuration names it)")
    p.add_argument("--state-dir", help="state directory (overrides state.directory)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.verbose == 0:
        logging.getLogger().setLevel(logging.INFO)
    cfg = load_config(args.config, args.interface, args.channel, args.state_dir)
    prep = prepare(cfg)  # files first (config, DBC, model, state), then the machine's channel
    check_channel(cfg)
    inputs = prep.parts.monitor.inputs

    def opener(ch: ChannelConfig) -> Callable[[], can.BusABC]:
        def open_bus() -> can.BusABC:
            bus = can.Bus(**bus_kwargs(cfg, ch, inputs))
            if cfg.bus.interface == "socketcan":
                tune_socketcan(bus, cfg.bus.receive_buffer_bytes)
            return bus

        return open_bus

    opens = {ch.name: opener(ch) for ch in cfg.channel_list}
    uplink = UplinkFeed.open(cfg.uplink, prep.parts.monitor) if cfg.uplink.enabled else None
    daemon = Daemon(cfg, prep.parts.monitor, prep.store, opens, Notifier(), DaemonOptions(), uplink=uplink)

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        log.info("received %s, stopping", signal.Signals(signum).name)
        daemon.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    sys.stdout.flush()
    daemon.run()
    return 0
