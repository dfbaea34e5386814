"""``cmcan run``: the daemon on the machine's bus."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from collections.abc import Callable, Sequence
from types import FrameType
from typing import TYPE_CHECKING

from cmcan.cli import signals
from cmcan.cli.common import Subparsers

if TYPE_CHECKING:  # the daemon's modules are imported when it runs: the parser starts without them
    import can

    from cmcan import config as cfgmod
    from cmcan.daemon.loop import Daemon, Reloaded
    from cmcan.monitor.inputs import InputMessage

log = logging.getLogger("cmcan")
_NAMED = frozenset(signal.Signals)


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "run",
        help="run the monitoring daemon on the CAN bus",
        description="Monitor the drive on the configured bus and broadcast CM ratio and warnings. "
        "Under systemd it reports READY, WATCHDOG and STATUS; SIGHUP reloads the configuration and model, "
        "SIGTERM or SIGINT stop it (other signals that would end it save the state first, exit 128+N). "
        "One daemon per state directory: a second one exits 75.",
    )
    p.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
    p.add_argument("--interface", help="python-can interface (overrides bus.interface)")
    p.add_argument("--channel", help="channel, e.g. can0 (overrides bus.channel, wherever the configuration names it)")
    p.add_argument("--state-dir", help="state directory (overrides state.directory)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cmcan.daemon.loop import Daemon, DaemonOptions
    from cmcan.daemon.preflight import check_channel, load_config, prepare, with_state
    from cmcan.service.sdnotify import Notifier
    from cmcan.uplink.feed import UplinkFeed

    if args.verbose == 0:
        logging.getLogger().setLevel(logging.INFO)
    cfg = load_config(args.config, args.interface, args.channel, args.state_dir)
    prep = prepare(cfg, need_state=False)  # files first (config, DBC, model), then the machine's channel,
    check_channel(cfg, extras_may_be_absent=True)
    # Signals are caught before the lock shows this process as the daemon: `cmcan baseline reset`
    # sends the lock's holder SIGHUP, whose default action would end it with a status systemd
    # takes for a clean stop.
    early = EarlySignals().install()
    prep = with_state(prep, lock=True)  # then the state: a second daemon on this directory stops here (75)
    try:
        uplink = UplinkFeed.open(cfg.uplink, prep.parts.monitor) if cfg.uplink.enabled else None
        opens = bus_openers(cfg, prep.parts.monitor.inputs)
        daemon = Daemon(cfg, prep.parts.monitor, prep.store, opens, Notifier(), DaemonOptions(), uplink=uplink)
        daemon.reloader = reloader(args)
        signals.install(daemon)
        early.hand_to(daemon)
        sys.stdout.flush()
        daemon.run()
    finally:
        assert prep.lock is not None
        prep.lock.release()
    return signals.exit_status(daemon)


class EarlySignals:
    """The daemon's signals (:mod:`cmcan.cli.signals`) while it starts, before it can act on them:
    each only noted, then handed to the daemon once its own handlers are in place (a reload or a
    stop as soon as it runs)."""

    def __init__(self) -> None:
        self.got: list[int] = []

    def install(self) -> EarlySignals:
        for s in (signals.RELOAD, *signals.STOP, *signals.FATAL):
            signal.signal(s, self.note)
        return self

    def note(self, signum: int, _frame: FrameType | None) -> None:
        self.got.append(signum)

    def hand_to(self, daemon: Daemon) -> None:
        """What came meanwhile, to ``daemon`` (whose handlers now take the signals)."""
        for s in self.got:
            log.info("received %s while starting", signal.Signals(s).name if s in _NAMED else f"signal {s}")
            if s == signals.RELOAD:
                daemon.request_reload()
            else:
                daemon.stop(s)
        self.got = []


def bus_openers(cfg: cfgmod.Config, inputs: Sequence[InputMessage]) -> dict[str, Callable[[], can.BusABC]]:
    """An opener per configured channel: its bus with kernel filters for the inputs it carries."""
    import can

    from cmcan.daemon.loop import bus_kwargs, tune_socketcan

    def opener(ch: cfgmod.ChannelConfig) -> Callable[[], can.BusABC]:
        def open_bus() -> can.BusABC:
            bus = can.Bus(**bus_kwargs(cfg, ch, inputs))
            if cfg.bus.interface == "socketcan":
                tune_socketcan(bus, cfg.bus.receive_buffer_bytes)
            return bus

        return open_bus

    return {ch.name: opener(ch) for ch in cfg.channel_list}


def reloader(args: argparse.Namespace) -> Callable[[], Reloaded]:
    """SIGHUP's work: the configuration file (with this command line's overrides), its DBC and model
    read and checked as at a start; any problem raises before anything of the running daemon changes."""
    from cmcan.assemble import assemble
    from cmcan.daemon.loop import Reloaded
    from cmcan.daemon.preflight import check_channel, load_config

    def reload() -> Reloaded:
        cfg = load_config(args.config, args.interface, args.channel, args.state_dir)
        parts = assemble(cfg)
        check_channel(cfg, extras_may_be_absent=True)
        return Reloaded(cfg, parts.monitor, bus_openers(cfg, parts.monitor.inputs))

    return reload
