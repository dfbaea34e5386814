"""``cmcan check``: configuration, DBC and model validated together, each problem said exactly."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cmcan.can import units
from cmcan.cli.common import Subparsers
from cmcan.cli.errors import exit_code
from cmcan.cli.jsonout import print_json
from cmcan.drives import config_files
from cmcan.errors import CmcanError, Kind
from cmcan.roles import UNITS

if TYPE_CHECKING:  # the rest is imported when the check runs: the parser starts without it
    from cmcan.config import Config


def add_subparser(sub: Subparsers) -> None:
    p = sub.add_parser(
        "check",
        help="validate configuration, DBC and model together",
        description="Exit 0 when the configuration, its DBC, the signal mapping, the model and "
        "(with --channel-check) the CAN channel fit together; otherwise print what is wrong and "
        "exit with a sysexits code.",
    )
    p.add_argument(
        "--config",
        action="append",
        help="configuration (default: the one shipped with cmcan, which cmcan run uses without --config; "
        "the file checked is printed); given more than once, or a directory of *.yaml files, the drives of "
        "one gateway: each checked, and refused when two would send the same identifier, claim the same "
        "J1939 address or NAME, or share a state directory",
    )
    p.add_argument("--channel-check", action="store_true", help="also check the bus channel exists on this machine")
    p.add_argument(
        "--state",
        action="store_true",
        help="also check the state directory is writable and its state file readable (changes nothing)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    files = config_files(args.config or [])
    if len(files) > 1:
        return run_drives(args, files)
    args.config = files[0] if files else None
    return run_one(args)


def run_drives(args: argparse.Namespace, files: list[str]) -> int:
    """Several drives of one gateway: each as ``cmcan check`` checks one, then what they would share."""
    from cmcan.daemon.preflight import load_config, prepare
    from cmcan.drives import conflicts

    parts = []
    for f in files:
        try:
            cfg = load_config(f)
            prep = prepare(cfg, need_state=False, read_only=True)
        except CmcanError as exc:
            if args.json:
                print_json({"ok": False, "error": str(exc), "exit_code": exit_code(exc), "config": f})
                return exit_code(exc)
            raise
        parts.append(prep.parts)
    problems = conflicts(parts)
    if problems:
        text = "; ".join(problems)
        if args.json:
            err = CmcanError(text, Kind.CONFIG)
            print_json({"ok": False, "error": text, "exit_code": exit_code(err), "configs": files})
            return exit_code(err)
        raise CmcanError(f"the drives cannot run on one gateway: {text}", Kind.CONFIG)
    drives = [_drive_summary(p) for p in parts]
    if args.json:
        print_json({"ok": True, "drives": drives})
    else:
        print(
            f"ok: {len(drives)} drives on one gateway: no identifier, J1939 address or NAME, uplink machine id, "
            "client id or outbox, or state directory shared"
        )
        for d in drives:
            sent = ", ".join(f"{i} ({m})" for i, m in zip(d["sends"], d["messages"], strict=True))
            print(f"  {d['config']}: sends {sent} on {d['channel']}{d['j1939']}; state {d['state']}")
    return 0


def _drive_summary(parts: Any) -> dict[str, Any]:
    from cmcan.drives import sends

    cfg = parts.cfg
    sent = sends(parts)
    ids_ = [f"0x{fid:0{8 if ext else 3}X}" for _ch, ext, fid in sent]
    j = cfg.j1939
    jt = ""
    if j.enabled:
        jt = f", J1939 address 0x{j.source_address:02X}" + (f" NAME {j.name.hex()}" if j.name is not None else "")
    return {
        "config": cfg.source,
        "sends": ids_,
        "messages": list(sent.values()),  # what each identifier of "sends" carries
        "channel": cfg.output_channel,
        "j1939": jt,
        "state": str(cfg.state.directory),
    }


def run_one(args: argparse.Namespace) -> int:
    from cmcan.assemble import check_against_dbc, check_output_ranges, dbc_for, dbc_warnings
    from cmcan.daemon.preflight import check_channel, load_config, prepare
    from cmcan.monitor.totals import StateError
    from cmcan.service.statefile import StateLock, read_node_status

    passed: list[str] = []  # what was checked before a failure, said with it
    try:
        cfg = load_config(args.config)
        passed.append(f"configuration {cfg.source}")
        db = dbc_for(cfg)
        passed.append(f"DBC {cfg.dbc_path}")
        check_against_dbc(cfg, db)
        check_output_ranges(cfg, db)
        passed.append("signal mapping and output ranges")
        try:
            prep = prepare(cfg, need_state=args.state, read_only=True)
        except StateError as exc:  # each damaged part named, and what the daemon would do with the file
            then = getattr(exc, "on_start", "cmcan run would keep it aside and start with fresh totals")
            raise StateError(f"{exc} ({then})") from None
        passed.append(f"model {prep.parts.model.path}")
        node = None
        if args.channel_check:
            check_channel(cfg)
            node = probe_node(cfg)
        check_uplink(cfg)
    except CmcanError as exc:
        if args.json:
            print_json({"ok": False, "error": str(exc), "exit_code": exit_code(exc), "passed": passed})
            return exit_code(exc)
        if passed:  # one line still: the error, then what passed before it
            raise CmcanError(f"{exc} [passed before it: {'; '.join(passed)}]", exc.kind) from None
        raise
    m = prep.parts.model.meta
    shipped = args.config is None
    result = {
        "ok": True,
        "config": cfg.source,
        "config_is_shipped": shipped,
        "dbc": str(cfg.dbc_path),
        "dbc_messages_ignored": dbc_warnings(cfg, prep.parts.db),
        "model": str(prep.parts.model.path),
        "model_version": m.model_version,
        "inputs": {r: f"{s.message}.{s.signal}" for r, s in cfg.signals.items()},
        "units_not_checked": unchecked_units(cfg, prep.parts.db),
        "envelope": m.envelope,
        "quantity": m.quantity_role,
        "motor_disp_cc": m.motor_disp_cc,
        "fixed": cfg.drive.fixed,
        "bus": f"{cfg.bus.interface}:{cfg.bus.channel}",
        "channels": [
            {"channel": c.name, "bitrate": c.bitrate or cfg.bus.bitrate, "fd": c.fd} for c in cfg.channel_list
        ],
        "outputs_channel": cfg.output_channel,
        "input_messages": [_describe(m) for m in prep.parts.monitor.inputs],
        "timing": _timing(cfg, prep.parts.db),
        "j1939": (
            {
                "source_address": cfg.j1939.source_address,
                "dm1": (
                    {
                        "spn": cfg.j1939.dm1.spn,
                        "input_spn": cfg.j1939.dm1.input_spn,
                        "period_ms": cfg.j1939.dm1.period_ms,
                    }
                    if cfg.j1939.dm1.enabled
                    else None
                ),
            }
            if cfg.j1939.enabled
            else None
        ),
    }
    result["baseline"] = learning_plan(cfg, prep.parts)
    result["prognosis"] = (
        {
            "end_of_life": cfg.prognosis.params.end_of_life_text,
            "imminent_h": cfg.prognosis.params.imminent_h,
            "max_gap_h": cfg.prognosis.params.max_gap_h,
        }
        if cfg.prognosis.enabled
        else None
    )
    if result["j1939"] is not None and cfg.j1939.name is not None:
        result["j1939"]["name"] = cfg.j1939.name.hex()
        result["j1939"]["bus"] = node  # who holds the address now (--channel-check)
    if prep.store is not None:
        t = prep.parts.monitor.totals
        result["state"] = {
            "file": str(prep.store.path),
            "exists": prep.store.path.exists(),
            "warning_count": t.warning_count,
            "condition": t.condition,
            "evaluated_h": t.evaluated_s / 3600.0,
            "locked_by_pid": StateLock(prep.store.dir).holder(),
            "j1939_node": read_node_status(prep.store.dir),
            "dtc_clears": t.dtc_clears[-5:],
            "notes": state_notes(prep.parts.monitor, prep.store.dir),
        }
    if args.json:
        print_json(result)
    else:
        print(
            f"ok: {cfg.source}"
            + (" (the configuration shipped with cmcan: pass --config FILE for another)" if shipped else "")
        )
        local = Path("config", "cmcan.yaml")
        if shipped and local.is_file() and local.resolve() != Path(cfg.source).resolve():
            print(
                f"  note   {local} is not the file checked (nor the one cmcan run uses without --config); "
                f"to check it: --config {local}"
            )
        ignored = result["dbc_messages_ignored"]
        note = (
            f" ({len(ignored)} message(s) cmcan does not read fail cantools' strict check: ignored)" if ignored else ""
        )
        print(f"  dbc    {result['dbc']}{note}")
        machine = f"V_M {m.motor_disp_cc:g} cm3/rev" if m.motor_disp_cc is not None else "delivered flow"
        print(f"  model  {result['model']} ({m.model_version}, predicts {m.quantity_role}: {machine})")
        for r, s in result["inputs"].items():
            lo, hi = m.envelope.get(r, (None, None))
            env = f"  envelope {lo:.1f}..{hi:.1f}" if lo is not None else ""
            unit = result["units_not_checked"].get(r)
            note = (
                ""
                if unit is None
                else f"  (DBC unit {unit!r} not recognized: scale not checked)"
                if unit
                else "  (no DBC unit: scale not checked)"
            )
            print(f"  {r:<18} <- {s}{env}{note}")
        for r, v in cfg.drive.fixed.items():
            print(f"  {r:<18} =  {v:g} (drive.fixed)")
        chans = ", ".join(
            f"{c['channel']} ({c['bitrate'] // 1000} kbit/s{', FD' if c['fd'] else ''})" for c in result["channels"]
        )
        print(f"  bus    {cfg.bus.interface}: {chans}; outputs on {cfg.output_channel}")
        j = result["j1939"]
        if j is not None:
            dm = j["dm1"]
            dm_text = f"DM1 SPN {dm['spn']} (drive) and {dm['input_spn']} (inputs)" if dm else "no DM1"
            named = f", NAME {j['name']} (claims its address)" if j.get("name") else ", no NAME (no address claim)"
            print(f"  j1939  source address 0x{j['source_address']:02X}{named}, {dm_text}")
            if j.get("bus"):
                print(f"  j1939  on the bus: {j['bus']['state']}: {j['bus']['text']}")
        for m in result["input_messages"]:
            print(f"  {m['message']:<18} {m['match']} on {m['channel']}; {m['health']}")
        bl = result["baseline"]
        if bl is None:
            print("  baseline  off (the type model judges alone: baseline.enabled)")
        else:
            print(
                f"  baseline  learns {bl['bins']} bins over {bl['envelope']}; ends with {bl['bins_needed']} of them "
                f"holding {bl['min_points']} ticks each and {bl['min_hours']:g} operating hours; judged meanwhile "
                f"at {bl['learning_low_pct']:g} / {bl['learning_high_pct']:g} %"
            )
            print(
                f"  baseline  suspect beyond {bl['suspect_lpm']:.3g} l/min from the type model in a bin's mean, or "
                f"with the pressure part of its learned correction below minus that: {bl['suspect_from']}"
            )
        pr = result["prognosis"]
        if pr is None:
            print("  prognosis off (no hours to service: prognosis.enabled)")
        else:
            print(f"  prognosis end of life: {pr['end_of_life']}; imminent within {pr['imminent_h']:g} h (p10)")
        for r, tm in result["timing"].items():
            print(f"  {r:<18} {tm['text']}")
        if "state" in result:
            st = result["state"]
            saved = (
                f"{st['warning_count']} warnings, condition {st['condition']}, {st['evaluated_h']:.1f} h evaluated"
                if st["exists"]
                else "no state saved yet"
            )
            held = f"; in use by the daemon (pid {st['locked_by_pid']})" if st["locked_by_pid"] else ""
            print(f"  state  {st['file']} ({saved}{held})")
            nd = st["j1939_node"]
            if nd:
                a = f"0x{nd['address']:02X}" if isinstance(nd.get("address"), int) else "no address"
                print(f"  state  J1939 node as the daemon last saw it: {nd.get('state')}, {a}")
            for note in st["notes"]:
                print(f"  state  note: {note}")
    return 0


def learning_plan(cfg: Config, parts: Any) -> dict[str, Any] | None:
    """What the on-board baseline will learn and when it ends (None: off)."""
    from cmcan.assemble import suspect_allowance
    from cmcan.monitor.baseline import BIN_ROLES

    bl = parts.monitor.baseline
    if bl is None:
        return None
    p = bl.p
    lo_hi = [f"{r} {e[0]:g}..{e[-1]:g}" for r, e in zip(BIN_ROLES, p.edges, strict=True)]
    b = cfg.baseline.settings
    return {
        "bins": "x".join(str(len(e) - 1) for e in p.edges),
        "edges": {r: list(e) for r, e in zip(BIN_ROLES, p.edges, strict=True)},
        "envelope": ", ".join(lo_hi),
        "bins_needed": p.bins_needed,
        "min_points": p.min_points,
        "min_hours": p.min_hours,
        "suspect_lpm": p.suspect_lpm,
        "suspect_from": suspect_allowance(cfg, parts.model)[1],
        "learning_low_pct": b.learning_low_pct,
        "learning_high_pct": b.learning_high_pct,
    }


def state_notes(monitor: Any, directory: Path) -> list[str]:
    """What of the saved state the monitor does not go on with, though the file is sound (a changed
    envelope learns the baseline afresh, other reference conditions begin a new prognosis history),
    and a baseline reset left for the daemon (or a file in its place it will refuse): ``cmcan run``
    says the same in the journal."""
    from cmcan.service.statefile import read_baseline_request

    pg = monitor.prognosis
    notes = [n for n in (monitor.baseline_note, pg.note if pg is not None else None) if n]
    req = read_baseline_request(directory)
    if req is not None and req.get("bad"):
        notes.append(f"baseline reset not carried out: {req['reason']}; the daemon removes it at its next reload")
    elif req is not None:
        notes.append(f"a baseline reset waits for the daemon's next reload or start ({req['reason']})")
    return notes


def probe_node(cfg: Config) -> dict[str, Any] | None:
    """On a J1939 machine with a NAME and a SocketCAN bus: who holds cmcan's address now."""
    if not cfg.j1939.enabled or cfg.j1939.name is None or cfg.bus.interface != "socketcan":
        return None
    from cmcan.daemon.claimprobe import probe

    try:
        return probe(cfg)
    except OSError as exc:
        raise CmcanError(
            f"{cfg.source}: cannot ask {cfg.output_channel} who holds the J1939 address: {exc}", Kind.UNAVAILABLE
        ) from None


def check_uplink(cfg: Config) -> None:
    """With the uplink enabled, what ``cmcan uplink`` checks before it connects: its TLS files and
    password file, by the uplink's own functions (a missing file: 66, naming it). The outbox and the
    broker are ``cmcan uplink --check``'s: checking them here would create the one or need the other."""
    if not cfg.uplink.enabled:
        return
    from cmcan.uplink.setup import read_password, tls_context

    tls_context(cfg.uplink.mqtt.tls, cfg.source)
    read_password(cfg.uplink.mqtt, cfg.source)


def unchecked_units(cfg: Config, db: Any) -> dict[str, str]:
    """Mapped roles whose DBC unit :mod:`cmcan.can.units` does not recognize (so their scale is taken as
    given), with that unit; roles without a unit (motor direction) are left out."""
    out = {}
    for role, ref in cfg.signals.items():
        if not UNITS.get(role):
            continue
        unit = db.get_message_by_name(ref.message).get_signal_by_name(ref.signal).unit or ""
        if not units.judged(UNITS[role], unit):
            out[role] = unit
    return out


def _timing(cfg: Config, db: Any) -> dict[str, dict[str, Any]]:
    """Per gated role, how its window, sample count and age fit its message's cycle time; said for
    the roles the fit changed or could not fit (no cycle time known)."""
    from cmcan.assemble import fitted_limits

    limits, _, fits = fitted_limits(cfg, db)
    out = {}
    for role, f in fits.items():
        if f.fitted and f.window_s == limits.window_s and f.min_samples == limits.min_samples:
            continue  # a message fast enough for the configured window: nothing to say
        if f.fitted:
            text = (
                f"sent every {f.cycle_s:g} s: judged over {f.window_s:g} s with at least {f.min_samples} "
                f"sample(s), stale after {f.max_age_s:g} s"
            )
        else:
            text = (
                f"no cycle time for its message (no GenMsgCycleTime in the DBC, no messages.NAME.cycle_ms): "
                f"assumed to bring {limits.min_samples} samples a {limits.window_s:g} s window; if it comes "
                "more slowly its points stay warming_up: give its cycle_ms"
            )
        out[role] = {
            "cycle_s": f.cycle_s,
            "window_s": f.window_s,
            "min_samples": f.min_samples,
            "max_age_s": f.max_age_s,
            "text": text,
        }
    return out


def _describe(m: Any) -> dict[str, Any]:
    """How an input message is matched and checked, for people."""
    from cmcan.can.j1939 import ids

    if m.pgn is not None:
        src = "any address" if m.sources is None else ", ".join(f"0x{a:02X}" for a in sorted(m.sources))
        match = f"PGN {m.pgn} (0x{m.pgn:04X}) from {src}"
        if ids.is_pdu1(m.pgn):  # a PDU1 PGN carries a destination address
            dest = "any" if m.destinations is None else ", ".join(f"0x{a:02X}" for a in sorted(m.destinations))
            match += f" to {dest} (destination address)"
    else:
        match = f"id 0x{m.frame_id:0{8 if m.extended else 3}X}"
    h = m.health
    parts = []
    if h.counter is not None:
        parts.append(f"counter {h.counter.name} (step <= {h.max_step})")
    if h.checksum is not None:
        parts.append(f"checksum {h.checksum_name}")
    parts.append(f"stale after {h.timeout_s:g} s" if h.timeout_s != float("inf") else "no cycle time: no timeout")
    return {"message": m.name, "channel": m.channel, "match": match, "health": ", ".join(parts)}
