"""``cmcan fleet ingest``: the gateways' uplink (MQTT) into the fleet data set, as a service."""

from __future__ import annotations

import argparse
import logging
import signal
import time
from pathlib import Path
from types import FrameType
from typing import Any
from urllib.parse import urlsplit

from cmcan.cli.common import Subparsers
from cmcan.cli.errors import require_extra
from cmcan.errors import CmcanError, Kind

log = logging.getLogger("cmcan")
SCHEMES = {"mqtt": False, "mqtts": True}  # scheme -> TLS
SOURCE = "cmcan fleet ingest"
# The uplink's settings the options are checked as, and the option each comes from (the messages name both).
OPTION_OF = {
    "uplink.mqtt.tls.enabled": "--broker mqtts://",
    "uplink.mqtt.tls.ca_file": "--ca-file",
    "uplink.mqtt.tls.cert_file": "--cert-file",
    "uplink.mqtt.tls.key_file": "--key-file",
    "uplink.mqtt.host": "--broker",
    "uplink.mqtt.port": "--broker",
    "uplink.mqtt.protocol": "--protocol",
    "uplink.mqtt.client_id": "--client-id",
    "uplink.mqtt.topic_prefix": "--topic-prefix",
    "uplink.mqtt.username": "--username",
    "uplink.mqtt.password_file": "--password-file",
    "uplink.mqtt.max_inflight": "--batch",
}


def as_options(exc: CmcanError) -> CmcanError:
    """An error of the uplink's rules with the option it concerns named first (same kind)."""
    text = str(exc)
    for field, option in OPTION_OF.items():
        if f"{field}:" in text:
            return CmcanError(text.replace(f"{field}:", f"{option} ({field}):", 1), exc.kind)
    return exc


def add_parser(fsub: Subparsers) -> None:
    p = fsub.add_parser(
        "ingest",
        help="receive the gateways' uplink (MQTT) into the data set, as a service",
        description="Subscribe to <prefix>/+/event|summary|dropped|status with a persistent session (QoS 1, "
        "clean start off, a stable client id) and write what arrives into the data set DATASET, by machine "
        "and day, deduplicated by the payloads' id. Each batch is committed (fsync'd, with its commit record) "
        "before its messages are acknowledged to the broker: a kill loses nothing, a restart doubles nothing. "
        "Bad payloads go to the uplink_quarantine table with the reason. TLS and the user name and password "
        "file are checked as `cmcan uplink` checks them (docs/fleet-telematics.md). Under systemd: READY, "
        "WATCHDOG, STATUS; SIGTERM or SIGINT commit what arrived and stop.",
    )
    p.add_argument("--broker", required=True, metavar="URL", help="mqtt://HOST[:PORT] or mqtts://HOST[:PORT] (TLS)")
    p.add_argument("--out", required=True, metavar="DATASET", help="data set folder (created if missing)")
    p.add_argument("--topic-prefix", default="cmcan", help="the gateways' uplink.mqtt.topic_prefix (default cmcan)")
    p.add_argument("--client-id", default="cmcan-fleet-ingest", help="the session's client id (keep it stable)")
    p.add_argument("--protocol", choices=("3.1.1", "5"), default="5", help="MQTT version (default 5)")
    p.add_argument("--username", help="user name at the broker")
    p.add_argument("--password-file", metavar="FILE", help="file holding the password alone (needs --username)")
    p.add_argument("--ca-file", metavar="FILE", help="CA certificate(s) the broker's is checked against (mqtts)")
    p.add_argument("--cert-file", metavar="FILE", help="client certificate (mqtts; with --key-file)")
    p.add_argument("--key-file", metavar="FILE", help="the client certificate's key")
    p.add_argument("--no-verify-hostname", action="store_true", help="do not match the broker's name (mqtts)")
    p.add_argument(
        "--batch",
        type=int,
        default=1000,
        metavar="N",
        help="messages per commit at most, and the broker's window of unacknowledged messages (MQTT 5; "
        "with 3.1.1 the broker's max_inflight_messages is the window); default 1000",
    )
    p.add_argument(
        "--batch-wait-s", type=float, default=0.5, help="commit a batch once its oldest message waited this long"
    )
    p.add_argument(
        "--fold-every",
        type=int,
        default=None,
        metavar="N",
        help="fold N commits of one level into one (default 20); a closed day's rows are folded into the "
        "machine/day partitions in any case (docs/fleet-telematics.md)",
    )
    p.set_defaults(func=run)


def mqtt_section(args: argparse.Namespace) -> dict[str, Any]:
    """The command line as the ``mqtt`` part of an ``uplink:`` section, so the uplink's schema and
    rules (host, strings MQTT can carry, TLS files, password file with a user name) check it."""
    url = urlsplit(args.broker)
    if url.scheme not in SCHEMES or not url.hostname or url.path not in ("", "/") or url.query or url.fragment:
        raise CmcanError(f"--broker {args.broker!r}: expected mqtt://HOST[:PORT] or mqtts://HOST[:PORT]", Kind.USAGE)
    if url.username is not None or url.password is not None:
        raise CmcanError(
            "--broker: no user name or password in the URL (every user sees a command line): use --username "
            "and --password-file",
            Kind.USAGE,
        )
    try:
        port = url.port
    except ValueError:
        raise CmcanError(f"--broker {args.broker!r}: the port is not a number from 1 to 65535", Kind.USAGE) from None
    return {
        "host": url.hostname,
        "port": port,
        "protocol": args.protocol,
        "client_id": args.client_id,
        "topic_prefix": args.topic_prefix,
        "username": args.username,
        "password_file": args.password_file,
        "max_inflight": args.batch,
        "tls": {
            "enabled": SCHEMES[url.scheme],
            "ca_file": args.ca_file,
            "cert_file": args.cert_file,
            "key_file": args.key_file,
            "verify_hostname": not args.no_verify_hostname,
        },
    }


def run(args: argparse.Namespace) -> int:
    require_extra("fleet", "pyarrow")
    from cmcan.fleet import dataset as ds
    from cmcan.fleet import uplinkstore as store
    from cmcan.fleet.ingest import FOLD_EVERY, Ingest, ingest_lock
    from cmcan.service.sdnotify import Notifier
    from cmcan.uplink.config import UplinkSettings
    from cmcan.uplink.setup import read_password, tls_context

    if args.verbose == 0:
        logging.getLogger().setLevel(logging.INFO)
    if not args.batch_wait_s > 0:
        raise CmcanError(f"--batch-wait-s: expected a positive number of seconds, got {args.batch_wait_s}", Kind.USAGE)
    fold_every = FOLD_EVERY if args.fold_every is None else args.fold_every
    if fold_every < 2:
        raise CmcanError(f"--fold-every: expected an integer of at least 2, got {fold_every}", Kind.USAGE)
    try:
        m = UplinkSettings.from_raw({"mqtt": mqtt_section(args)}, state_dir=".", source=SOURCE).mqtt
        tls = tls_context(m.tls, SOURCE)
        password = read_password(m, SOURCE)
    except CmcanError as exc:
        raise as_options(exc) from None
    root = ds.open_dataset(Path(args.out), create=True)
    with ingest_lock(root):
        removed = ds.remove_orphans(root) + store.prepare(root, time.time())  # what a kill left behind
        seen, records = store.load_seen(root)
        log.info(
            "%s: %d commit records%s; subscribing to %s/+/... at %s:%d",
            root,
            len(records),
            f", {removed} files of an interrupted commit or of a fold removed" if removed else "",
            m.topic_prefix,
            m.host,
            m.port,
        )
        ingest = Ingest(
            root,
            m,
            seen,
            records=records,
            fold_every=fold_every,
            password=password,
            tls=tls,
            notifier=Notifier(),
            batch_wait_s=args.batch_wait_s,
        )

        def on_signal(signum: int, _frame: FrameType | None) -> None:
            log.info("received %s, committing what arrived and stopping", signal.Signals(signum).name)
            ingest.stop()

        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)
        ingest.run()
        log.info("stopped: %s", ingest.stats.text())
    return 0
