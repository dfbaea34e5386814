"""``cmcan baseline status|show|reset``: the machine's own baseline on the gateway (docs/commissioning.md).

``status`` and ``show`` read the state file (written atomically, so reading beside a running daemon is
safe). ``reset`` learns the baseline afresh after service, the old one kept in the history: with no
daemon on the state directory it takes the directory's lock and writes the state itself; with one
running it leaves the request in the state directory and asks that daemon to reload (SIGHUP), so the
daemon stays the state's only writer, and waits until it has carried it out.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from datetime import UTC, datetime
from typing import Any

from cmcan.cli.common import Subparsers, load_config
from cmcan.errors import CmcanError, Kind

WAIT_S = 10.0


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "baseline",
        help="the machine's own baseline learned on board: status, show, reset after service",
        description="The on-board baseline (the configuration's baseline section): its state, what it "
        "learned, and a reset after service that acts on the running daemon through its state and a reload.",
    )
    bsub = p.add_subparsers(dest="baseline_command", metavar="BASELINE_COMMAND", required=True)
    for name, text in (
        ("status", "state, learned hours, envelope covered, distance from the type model"),
        ("show", "everything learned: bins, correction, history of earlier baselines (JSON)"),
        ("reset", "learn afresh (after a repair or replacement); the old baseline goes into the history"),
    ):
        s = bsub.add_parser(name, help=text, description=text)
        s.add_argument("--config", help="configuration (default: the shipped config/cmcan.yaml)")
        if name == "status":
            s.add_argument("--json", action="store_true", help="print the status as JSON")
        if name == "reset":
            s.add_argument("--reason", required=True, help="why (kept in the history): e.g. 'pump replaced'")
            s.add_argument("--wait", type=float, default=WAIT_S, help=f"seconds to wait for the daemon ({WAIT_S:g})")
        s.set_defaults(func=run)


def _doc(cfg: Any) -> dict[str, Any] | None:
    from cmcan.service.statefile import StateStore

    if not cfg.baseline.enabled:
        raise CmcanError(f"{cfg.source}: baseline.enabled is false: this machine learns no baseline", Kind.CONFIG)
    return StateStore(cfg.state.directory).read().baseline


def _status(doc: dict[str, Any] | None) -> dict[str, Any]:
    if doc is None:
        return {"state": "learning", "learned_h": 0.0, "note": "nothing learned yet (no state saved)"}
    n = doc.get("n", [])
    return {
        "state": doc["state"],
        "learned_h": None,
        "learned_ticks": doc["learned_ticks"],
        "bins_with_points": sum(1 for v in n if v > 0),
        "bins": len(n),
        "theta": doc["theta"],
        "distance_lpm": doc["distance_lpm"],
        "pressure_part_lpm": doc.get("pressure_part_lpm"),
        "suspect_by": doc.get("suspect_by"),
        "finished_t_s": doc["finished_t_s"],
        "earlier_baselines": len(doc.get("history", [])),
    }


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config, check_dbc=False)
    if args.baseline_command == "reset":
        return _reset(cfg, args)
    doc = _doc(cfg)
    if args.baseline_command == "show":
        print(json.dumps(doc, indent=2))
        return 0
    st = _status(doc)
    if doc is not None:
        from cmcan.assemble import assemble

        mon = _monitor(cfg, assemble)
        st = {k: v for k, v in mon.baseline.describe().items() if k != "history"}
        st["earlier_baselines"] = len(mon.baseline.history)
    if args.json:
        print(json.dumps(st, indent=2))
        return 0
    print(f"baseline: {st['state']}")
    if "coverage_pct" in st:
        print(
            f"  learned {st['learned_h']:.2f} h (at least {st['min_hours']:g} h), envelope covered "
            f"{st['coverage_pct']:.0f} % ({st['bins_covered']} of {st['bins']} bins, {st['bins_needed']} needed)"
        )
        print(
            f"  distance from the type model {st['distance_lpm']:+.2f} l/min, pressure part "
            f"{st['pressure_part_lpm']:+.2f} l/min (suspect beyond {st['suspect_lpm']:.2f}, the pressure part below "
            f"minus it{'; suspect by its ' + ' and '.join(st['suspect_by']) if st['suspect_by'] else ''}); "
            f"earlier baselines: {st['earlier_baselines']}"
        )
    else:
        print(f"  {st['note']}")
    return 0


def _monitor(cfg: Any, assemble: Any) -> Any:
    from cmcan.service.statefile import StateStore

    return assemble(cfg, totals=StateStore(cfg.state.directory).read()).monitor


def _reset(cfg: Any, args: argparse.Namespace) -> int:
    from cmcan.errors import kind_of_oserror
    from cmcan.service.statefile import StateLock, StateStore

    _doc(cfg)  # enabled, and the state readable
    reason = args.reason.strip()
    if not reason:
        raise CmcanError("--reason: say why the baseline is reset (kept in the history)", Kind.USAGE)
    at = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    store = StateStore(cfg.state.directory)
    lock = StateLock(store.dir)
    pid = _lock_or_daemon(lock, args.wait)
    if pid is not None:
        return _reset_by_daemon(store, pid, reason, at, args.wait)
    try:
        from cmcan.assemble import assemble

        mon = _monitor(cfg, assemble)
        mon.reset_baseline(reason, at)
        store.save(mon.save_totals())  # a new file, the directory's owner's (run as root, too)
    except OSError as exc:
        raise CmcanError(f"{store.path}: cannot save the state: {exc.strerror}", kind_of_oserror(exc)) from None
    finally:
        lock.release()
    print(f"baseline reset in {store.path}: learning afresh at the next start ({reason})", file=sys.stdout)
    return 0


def _lock_or_daemon(lock: Any, wait_s: float) -> int | None:
    """The state directory's lock taken (None: no daemon runs, the reset is this command's), or the pid
    of the daemon holding it once that daemon handles SIGHUP: a daemon between its lock and its signal
    handlers (starting) would be killed by the reload asked for, and systemd takes that death for a
    clean stop. The pid must be the same twice in a row (the lock's file is written just after it is
    taken: an old pid there must not get the signal)."""
    from cmcan.service.statefile import LockHeld, takes_reload

    deadline = time.monotonic() + wait_s
    seen = None
    while True:
        try:
            lock.acquire()
            return None
        except LockHeld:
            pid = lock.holder()
        ready = pid is not None and pid > 0 and takes_reload(pid)
        if ready and pid == seen:
            return pid
        seen = pid if ready else None
        if time.monotonic() > deadline:
            who = f"pid {pid}" if pid and pid > 0 else "another process"
            raise CmcanError(
                f"{lock.path}: the state directory is locked by {who}, which takes no reload request yet "
                f"(a daemon starting, or another cmcan baseline reset) within {wait_s:g} s; nothing was changed, "
                "try again",
                Kind.TEMPFAIL,
            )
        time.sleep(0.1)


def _reset_by_daemon(store: Any, pid: int, reason: str, at: str, wait_s: float) -> int:
    """The request left in the state directory, the daemon asked to reload, and waited for: it removes
    the request once it has carried it out and saved."""
    from cmcan.service.statefile import BASELINE_REQUEST_FILE, write_baseline_request

    request = write_baseline_request(store.dir, reason, at)
    try:
        os.kill(pid, signal.SIGHUP)
    except ProcessLookupError:
        raise CmcanError(
            f"{request}: the daemon (pid {pid}) ended before it took the reset; it carries it out at its next start",
            Kind.TEMPFAIL,
        ) from None
    deadline = time.monotonic() + wait_s
    while os.path.lexists(store.dir / BASELINE_REQUEST_FILE):
        if time.monotonic() > deadline:
            raise CmcanError(
                f"{request}: the daemon (pid {pid}) did not take the reset within {wait_s:g} s; it carries it out "
                "at its next reload or start",
                Kind.TEMPFAIL,
            )
        time.sleep(0.1)
    print(f"baseline reset by the running daemon (pid {pid}): learning afresh ({reason})")
    return 0
