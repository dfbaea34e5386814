"""``cmcan uplink``: publishes the daemon's outbox to the site's MQTT broker (a process of its own)."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

from cmcan.cli.common import Subparsers
from cmcan.cli.jsonout import print_json
from cmcan.errors import CmcanError, Kind
from cmcan.service.sdnotify import Notifier

if TYPE_CHECKING:  # imported when run: the command line starts without the uplink's modules
    import ssl

    from cmcan.uplink.config import UplinkSettings
    from cmcan.uplink.outbox import Outbox

log = logging.getLogger("cmcan")


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "uplink",
        help="publish the daemon's outbox to the MQTT broker",
        description="Publish warning events, periodic summaries and drop notices from the daemon's outbox "
        "(state directory) to the configured MQTT broker with QoS 1; an entry is deleted only after the "
        "broker's PUBACK. Retries an unreachable broker with back-off. Under systemd it reports READY, "
        "WATCHDOG and STATUS; SIGTERM or SIGINT stop it.",
    )
    p.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
    p.add_argument("--state-dir", help="state directory holding the outbox (overrides state.directory)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true", help="connect once to the broker and exit (0: it works)")
    mode.add_argument("--status", action="store_true", help="print the outbox's backlog as JSON and exit")
    mode.add_argument("--drain", action="store_true", help="exit 0 once the outbox is empty and acknowledged")
    p.add_argument(
        "--timeout", type=float, metavar="S", help="with --drain: give up after S seconds (exit 75, entries kept)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cmcan.daemon.preflight import load_config
    from cmcan.uplink.outbox import Usage, describe
    from cmcan.uplink.setup import OutboxLock, open_for_uplink, read_password, require_folder, tls_context

    if args.verbose == 0:
        logging.getLogger().setLevel(logging.INFO)
    if args.timeout is not None and not args.drain:
        raise CmcanError("--timeout goes with --drain", Kind.USAGE)
    if args.timeout is not None and not args.timeout > 0:
        raise CmcanError(f"--timeout: expected a positive number of seconds, got {args.timeout}", Kind.USAGE)
    cfg = load_config(args.config, state_dir=args.state_dir)
    settings = cfg.uplink
    if args.status:  # a query: it creates nothing, a corrupt outbox is reported, not moved; no lock
        require_folder(settings.outbox.path, cfg.source)
        if not settings.outbox.path.exists():  # the daemon has not written one yet
            print_json(
                {"outbox": str(settings.outbox.path), "stream_id": None, **describe(Usage(0, 0, None, None), None)}
            )
            return 0
        box = open_for_uplink(settings.outbox.path, keep_aside=False, source=cfg.source)
        out = {"outbox": str(box.path), "stream_id": box.stream_id, **describe(box.usage(), box.clock())}
        box.close()
        print_json(out)
        return 0
    if not settings.enabled:
        raise CmcanError(
            f"{cfg.source}: uplink.enabled: the uplink is disabled; set it to true (and uplink.machine_id)",
            Kind.CONFIG,
        )
    # Each problem is a CmcanError with its kind: the command line's table gives the exit code.
    tls = tls_context(settings.mqtt.tls, cfg.source)
    password = read_password(settings.mqtt, cfg.source)
    require_folder(settings.outbox.path, cfg.source)
    # One uplink per outbox, --check included: it connects with the same client id, which would take
    # the running uplink's session from it.
    lock = OutboxLock(settings.outbox.path).acquire()
    try:
        box = open_for_uplink(settings.outbox.path, source=cfg.source)
        return _publish(args, settings, box, password, tls, cfg.state.directory)
    finally:
        lock.release()


def _publish(
    args: argparse.Namespace,
    settings: UplinkSettings,
    box: Outbox,
    password: str | None,
    tls: ssl.SSLContext | None,
    state_dir: Path | None = None,
) -> int:
    from cmcan.uplink.publisher import Publisher

    notifier = Notifier() if not args.check else Notifier(env={})
    pub = Publisher(settings, box, password=password, tls=tls, notifier=notifier)
    pub.node_dir = state_dir  # the daemon's J1939 node file, for the health messages
    if args.check:
        try:
            print(f"ok: {pub.check_connection()}; outbox {box.path} holds {box.usage().entries} entries")
        finally:
            box.close()
        return 0

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        log.info("received %s, stopping", signal.Signals(signum).name)
        pub.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    sys.stdout.flush()
    try:
        done = pub.run(drain=args.drain, timeout_s=args.timeout)
    finally:
        pub.box.close()
    if args.drain and not done:
        raise CmcanError(
            f"outbox not empty after {args.timeout:g} s ({pub.last_problem or 'still publishing'}); entries kept",
            Kind.TEMPFAIL,
        )
    return 0
