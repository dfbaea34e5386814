"""Assembly: a configuration, its DBC and a model, checked against each other, into a Monitor.

The one place that knows both the configuration's vocabulary and the core's parameter types. The
daemon, the replay, the demo and the tests build their monitors here.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cmcan.can import checksums, codec, units
from cmcan.can.dbc import DbcError, covers, describe_signal, message_problems, physical_range
from cmcan.can.dbccache import load_compiled
from cmcan.can.frame import Frame
from cmcan.can.j1939 import dm1 as j1939_dm1
from cmcan.can.j1939 import ids
from cmcan.can.j1939.claim import ClaimParams
from cmcan.config import Config
from cmcan.errors import Kind
from cmcan.model import GrayBoxModel, ModelError, default_model_path, load_model
from cmcan.monitor.baseline import BIN_ROLES, BaselineParams
from cmcan.monitor.core import Monitor, MonitorParams
from cmcan.monitor.diagnostics import Dm1Params
from cmcan.monitor.gating import GateLimits, RoleFit, fit_to_cycles, prediction_ok
from cmcan.monitor.health import HealthSpec
from cmcan.monitor.inputs import MEMO_MAX, Channels, InputMessage, Matcher, overlap
from cmcan.monitor.node import NodeParams
from cmcan.monitor.payloads import OutputMessage, Outputs, output_span, output_spans
from cmcan.monitor.prognosis import PrognosisParams
from cmcan.monitor.totals import Totals
from cmcan.monitor.windows import Affine, DpFromHighLow, dp_affine, role_affine
from cmcan.roles import (
    DP,
    HIGH_PRESSURE,
    LOW_PRESSURE,
    MODEL_INPUTS,
    OUTPUT_SIGNALS,
    PUMP_SPEED,
    QUANTITY_OUTPUT,
    QUANTITY_SIGNALS,
    TEMP,
    UNITS,
    SignalRef,
    gated_roles,
)
from cmcan.schema import SchemaError, carried

if TYPE_CHECKING:  # hints only; cmcan.can.dbc imports cantools where a DBC is read
    from cantools.database.can import Database as CantoolsDatabase
    from cantools.database.can import Message as CantoolsMessage

    from cmcan.can.dbcmodel import CompiledDatabase, CompiledMessage

    # either: a compiled database has the fields of cantools' that cmcan reads (cmcan.can.dbcmodel)
    Database = CompiledDatabase | CantoolsDatabase
    Message = CompiledMessage | CantoolsMessage

    from cmcan.sim.frames import BusPlan

log = logging.getLogger("cmcan.assemble")


def dbc_for(cfg: Config) -> Database:
    """The configuration's DBC (DbcError names the file and that the configuration named it), as cmcan
    reads it: compiled, from the cache when its bytes were read before (:mod:`cmcan.can.dbccache`)."""
    try:
        return load_compiled(cfg.dbc_path)
    except DbcError as exc:
        raise DbcError(f"{exc} (dbc: in {cfg.source})", exc.kind) from None


def model_file(cfg: Config) -> Path:
    return cfg.model_path if cfg.model_path is not None else default_model_path()


def load_model_for(cfg: Config, path: str | Path | None = None) -> GrayBoxModel:
    """The configuration's model (or ``path``), checked against its output quantity, motor
    displacement and oil."""
    expect = {"motor_disp_cc": cfg.motor_disp_cc, "quantity": cfg.quantity, "oil": cfg.oil}
    if path is not None:
        model = load_model(path, **expect)
        check_predictions(model, cfg.gate_limits)
        return model
    try:
        model = load_model(model_file(cfg), **expect)
        check_predictions(model, cfg.gate_limits)
        return model
    except ModelError as exc:  # the configuration named it: a configuration problem
        raise ModelError(f"{exc} (model: in {cfg.source})", Kind.CONFIG) from None


def check_predictions(model: GrayBoxModel, limits: GateLimits) -> None:
    """The model's predictions at a few points of its own training envelope (its centre, and each
    input at its minimum and its maximum with the others at the centre), alone and in one batch, are
    predictions the monitor accepts (:func:`cmcan.monitor.gating.prediction_ok`): a model that
    returns nonsense is refused before it is run, not reported on the bus tick after tick."""
    names = list(MODEL_INPUTS)
    x = model.probe_rows()  # the points the loader's bounded probe ran: they run within its budget
    points = x.tolist()
    try:
        batch, _ = model.predict(x)
        single = [model.predict_one(*row)[0] for row in points]
    except Exception as exc:  # onnxruntime's own errors on a graph that loads but does not run
        raise ModelError(f"{model.path}: the model does not run: {type(exc).__name__}: {exc}") from None
    unit = UNITS.get(limits.output_role, "")
    for row, a, b in zip(points, np.asarray(batch, dtype=np.float64).tolist(), single, strict=True):
        for v in (a, b):
            if not prediction_ok(v, limits):
                at = ", ".join(f"{r} {x:g}" for r, x in zip(names, row, strict=True))
                hi = limits.plausible.get(limits.output_role, (0.0, math.inf))[1]
                raise ModelError(
                    f"{model.path}: predicts {v!r} {unit} at {at} (inside its training envelope); "
                    f"expected a number in (0, {hi:g}] {unit}"
                )


def _message(cfg: Config, db: Database, name: str, field: str) -> Message:
    try:
        return db.get_message_by_name(name)
    except KeyError:
        names = ", ".join(sorted(m.name for m in db.messages))
        raise SchemaError(cfg.source, field, f"no message {name!r} in {cfg.dbc_path}; it has {names}") from None


def check_against_dbc(cfg: Config, db: Database) -> None:
    """Every mapped message and signal exists, can be decoded and is in a unit its scale turns into
    the role's (:mod:`cmcan.can.units`); outputs exist, have the signals cmcan sends and are not inputs;
    high and low pressure can be subtracted exactly."""
    for role, ref in cfg.signals.items():
        msg = _message(cfg, db, ref.message, f"signals.{role}.message")
        if ref.signal not in {s.name for s in msg.signals}:
            raise SchemaError(
                cfg.source,
                f"signals.{role}.signal",
                f"message {ref.message} in {cfg.dbc_path} has no signal {ref.signal!r}; "
                f"it has {', '.join(s.name for s in msg.signals)}",
            )
        problem = codec.check_codable(msg, [ref.signal])
        if problem:
            raise SchemaError(cfg.source, f"signals.{role}", f"{problem} (in {cfg.dbc_path})")
        _strict(cfg, db, msg, f"signals.{role}.message")
        sig = msg.get_signal_by_name(ref.signal)
        wrong = units.check_mapping(role, UNITS[role], ref.message, ref.signal, sig.unit, ref.scale, ref.offset)
        if wrong is not None:
            key = f"signals.{role}.{wrong.key}" if wrong.key else f"signals.{role}"
            raise SchemaError(cfg.source, key, f"{wrong.text} (units in {cfg.dbc_path})")
    inputs = {ref.message for ref in cfg.signals.values()}
    for key, out in cfg.output_items():
        msg = _message(cfg, db, out.message, f"outputs.{key}.message")
        if out.message in inputs:
            raise SchemaError(cfg.source, f"outputs.{key}.message", f"{out.message} is also an input message")
        missing = [s for s in OUTPUT_SIGNALS[key] if s not in {x.name for x in msg.signals}]
        if missing:
            raise SchemaError(
                cfg.source,
                f"outputs.{key}.message",
                f"message {out.message} in {cfg.dbc_path} lacks signal(s) {', '.join(missing)}",
            )
        problem = codec.check_codable(msg)
        if problem:
            raise SchemaError(cfg.source, f"outputs.{key}.message", f"{problem} (in {cfg.dbc_path})")
        _strict(cfg, db, msg, f"outputs.{key}.message")
    if HIGH_PRESSURE in cfg.signals and DP not in cfg.signals:
        high, low = _affine(db, cfg.signals[HIGH_PRESSURE]), _affine(db, cfg.signals[LOW_PRESSURE])
        if dp_affine(high, low) is None:
            raise SchemaError(
                cfg.source,
                f"signals.{LOW_PRESSURE}",
                f"its resolution ({low.a:g} bar) and high_pressure_bar's ({high.a:g} bar) are not in a small "
                "integer ratio, so dp cannot be formed exactly; map dp_bar or use the same resolution",
            )
    check_bus(cfg, db)
    ignored = dbc_warnings(cfg, db)
    if ignored and (str(cfg.dbc_path), tuple(sorted(ignored))) not in _WARNED:
        _WARNED.add((str(cfg.dbc_path), tuple(sorted(ignored))))
        log.warning(
            "%s: %d message(s) cmcan does not read fail cantools' strict check (ignored): %s",
            cfg.dbc_path,
            len(ignored),
            "; ".join(f"{k}: {v}" for k, v in sorted(ignored.items())),
        )


_WARNED: set[tuple[str, tuple[str, ...]]] = set()  # said once a process (check runs at several steps)


def _strict(cfg: Config, db: Database, msg: Message, field: str) -> None:
    """A message cmcan reads or sends passes cantools' strict check, even in a DBC loaded leniently."""
    why = message_problems(db).get(msg.name)
    if why is not None:
        raise SchemaError(cfg.source, field, f"message {msg.name} in {cfg.dbc_path}: {why}")


def read_messages(cfg: Config) -> set[str]:
    """The DBC messages cmcan reads (inputs) or sends (outputs) with this configuration."""
    return {ref.message for ref in cfg.signals.values()} | {out.message for _, out in cfg.output_items()}


def dbc_warnings(cfg: Config, db: Database) -> dict[str, str]:
    """Problems of DBC messages cmcan does not read or send (cantools' strict check, value tables
    without a signal), by message: warnings, not errors."""
    used = read_messages(cfg)
    return {k: v for k, v in message_problems(db).items() if k not in used}


def check_output_ranges(cfg: Config, db: Database) -> None:
    """Each output signal cmcan fills in can carry what it sends in normal operation
    (:func:`cmcan.monitor.payloads.output_spans`): a signal too narrow would saturate (or wrap) and
    show, say, a CM ratio of 2.55 % as valid. Resolution is not judged, only the range."""
    span = output_span(cfg.drive.nominal_flow_lpm, cfg.drive.lpm_per_unit)
    spans = output_spans(QUANTITY_SIGNALS[cfg.quantity], span, cfg.drive.nominal_flow_lpm)
    for key, out in cfg.output_items():
        msg = _message(cfg, db, out.message, f"outputs.{key}.message")
        for name in OUTPUT_SIGNALS[key]:
            sig, span = msg.get_signal_by_name(name), spans[name]
            carried = physical_range(sig)
            if not covers(carried, (span.lo, span.hi), float(sig.scale)):
                unit = f" {sig.unit}" if sig.unit else ""
                raise SchemaError(
                    cfg.source,
                    f"outputs.{key}.message",
                    f"{out.message}.{name} in {cfg.dbc_path} carries {carried[0]:g}..{carried[1]:g}{unit} "
                    f"({describe_signal(sig)}); cmcan sends {span.lo:g}..{span.hi:g}{unit} ({span.why}): "
                    "widen the signal (more bits, a coarser scale or a wider range)",
                )


# -- the machine's buses: channels, identifier formats, J1939, input health -----------------------------

# Signal names that mark an alive counter or a checksum when the configuration does not name them.
COUNTER_NAME = re.compile(r"(^|_)(alive_?|rolling_?|msg_?|message_?)?(counter|cnt|ctr)$|alivecounter$", re.I)
CHECKSUM_NAME = re.compile(r"(^|_)(checksum|chksum|crc8?)$", re.I)


def _first_role(cfg: Config, message: str) -> str:
    return next(role for role, ref in cfg.signals.items() if ref.message == message)


def _input_names(cfg: Config) -> list[str]:
    return list(dict.fromkeys(ref.message for ref in cfg.signals.values()))


def _channel_fd(cfg: Config) -> dict[str, bool]:
    return {c.name: c.fd for c in cfg.channel_list}


def _j1939_matched(cfg: Config, msg: Message) -> bool:
    return cfg.j1939.enabled and bool(msg.is_extended_frame)


@dataclass(frozen=True)
class Integrity:
    """A message's alive counter and checksum signals as resolved from configuration and DBC."""

    counter: str | None
    checksum: str | None
    algorithm: str | None


def integrity(cfg: Config, msg: Message) -> Integrity:
    """The counter and checksum of an input message; SchemaError names the field when unclear."""
    mc = cfg.message(msg.name)
    names = [s.name for s in msg.signals]
    multiplexed = {s.name for s in msg.signals if s.multiplexer_ids is not None}  # not in every frame
    where = f"messages.{msg.name}"

    def pick(given: str | None, pattern: re.Pattern[str], what: str, key: str) -> str | None:
        if given == "none":
            return None
        if given is not None:
            if given not in names:
                raise SchemaError(
                    cfg.source,
                    f"{where}.{key}",
                    f"message {msg.name} has no signal {given!r}; it has {', '.join(names)}",
                )
            if given in multiplexed:
                raise SchemaError(
                    cfg.source, f"{where}.{key}", f"{given} is multiplexed: the {what} must be in every frame"
                )
            return given
        found = [n for n in names if pattern.search(n) and n not in multiplexed]
        if len(found) > 1:
            raise SchemaError(
                cfg.source,
                f"{where}.{key}",
                f"message {msg.name} has several {what} signals ({', '.join(found)}): name one",
            )
        return found[0] if found else None

    counter = pick(mc.counter, COUNTER_NAME, "alive counter", "counter")
    checksum = pick(mc.checksum_signal, CHECKSUM_NAME, "checksum", "checksum_signal")
    mapped = {ref.signal: role for role, ref in cfg.signals.items() if ref.message == msg.name}
    for key, sig_name in (("counter", counter), ("checksum_signal", checksum)):
        if sig_name in mapped:
            raise SchemaError(
                cfg.source, f"{where}.{key}", f"{sig_name} carries {mapped[sig_name]}; it cannot also be the {key}"
            )
    if counter is not None:
        sig = msg.get_signal_by_name(counter)
        if sig.is_signed or sig.is_float or sig.length > 16:
            raise SchemaError(cfg.source, f"{where}.counter", f"{counter} is not an unsigned counter of up to 16 bits")
    algorithm = mc.checksum if mc.checksum is not None else cfg.input_health.checksum
    if algorithm == "none":
        return Integrity(counter, None, None)
    if checksum is not None and algorithm is None:
        raise SchemaError(
            cfg.source,
            f"{where}.checksum",
            f"message {msg.name} has the checksum signal {checksum}: name its algorithm "
            f"({', '.join(checksums.ALGORITHMS)}) or none, here or in input_health.checksum",
        )
    if checksum is None and mc.checksum is not None:
        raise SchemaError(cfg.source, f"{where}.checksum", f"message {msg.name} has no checksum signal to check")
    if checksum is None:
        return Integrity(counter, None, None)
    assert algorithm is not None
    lay = codec.layout(msg, checksum)
    problem = checksums.problem(algorithm, msg.length, lay, codec.layout(msg, counter) if counter is not None else None)
    if problem:
        raise SchemaError(cfg.source, f"{where}.checksum", f"{problem} (message {msg.name})")
    return Integrity(counter, checksum, algorithm)


def cycle_s(cfg: Config, msg: Message) -> float | None:
    """A message's cycle time: ``messages.NAME.cycle_ms``, else the DBC's GenMsgCycleTime; None when
    neither gives one."""
    ms = cfg.message(msg.name).cycle_ms or msg.cycle_time
    return ms / 1000.0 if ms else None


def timeout_s(cfg: Config, msg: Message) -> float:
    """How long a message may be missing before it is stale: timeout_cycles cycle times."""
    cycle = cycle_s(cfg, msg)
    return cfg.input_health.timeout_cycles * cycle if cycle else math.inf


def check_bus(cfg: Config, db: Database) -> None:
    """Every mapped input can be received and matched, every output sent: identifier formats, FD,
    channels, J1939 matching without ambiguity, counters and checksums. SchemaError names the field."""
    fd = _channel_fd(cfg)
    for name in _input_names(cfg):
        msg = db.get_message_by_name(name)
        field = f"signals.{_first_role(cfg, name)}.message"
        chan = cfg.message_channel(name)
        if msg.is_extended_frame and not cfg.frames.extended_ids:
            raise SchemaError(
                cfg.source,
                field,
                f"message {name} has a 29-bit identifier (0x{msg.frame_id:08X}) but 29-bit identifiers are off: "
                "set frames.extended_ids: true (and j1939.enabled for a J1939 machine)",
            )
        if is_fd_message(msg) and not fd[chan]:
            raise SchemaError(
                cfg.source,
                field,
                f"message {name} is a CAN FD message ({fd_why(msg)}) but channel {chan} is not a CAN FD bus: "
                "its frames would all be counted bad_fd (set frames.fd for bus.channel, fd: true in "
                "channels.extra)",
            )
        mc = cfg.message(name)
        if mc.source_addresses_set and not _j1939_matched(cfg, msg):
            why = "j1939.enabled is false" if not cfg.j1939.enabled else f"{name} has an 11-bit identifier"
            raise SchemaError(
                cfg.source, f"messages.{name}.source_addresses", f"source addresses are J1939's, but {why}"
            )
        integrity(cfg, msg)
    ins = input_messages(cfg, db)
    for i, a in enumerate(ins):
        for b in ins[:i]:
            if a.channel == b.channel and overlap(a, b):
                raise SchemaError(
                    cfg.source,
                    f"signals.{_first_role(cfg, a.name)}.message",
                    f"a frame of {a.name} could also be one of {b.name} on channel {a.channel} "
                    "(same identifier, or same PGN with overlapping source addresses): map one, or give "
                    "messages.NAME.source_addresses",
                )
    out_chan = cfg.output_channel
    for key, out in cfg.output_items():
        msg = db.get_message_by_name(out.message)
        if msg.is_extended_frame and not cfg.frames.extended_ids:
            raise SchemaError(
                cfg.source,
                f"outputs.{key}.message",
                f"message {out.message} has a 29-bit identifier but 29-bit identifiers are off (frames.extended_ids)",
            )
        if is_fd_message(msg) and not fd[out_chan]:
            raise SchemaError(
                cfg.source,
                f"outputs.{key}.message",
                f"message {out.message} is a CAN FD message ({fd_why(msg)}) but the output channel {out_chan} "
                "is not a CAN FD bus",
            )
        fid = output_id(cfg, msg)
        for m in ins:
            if m.channel == out_chan and m.matches(fid, bool(msg.is_extended_frame)):
                raise SchemaError(
                    cfg.source,
                    f"outputs.{key}.message",
                    f"cmcan would send {out.message} as 0x{fid:X}, which is also input {m.name} on {out_chan}",
                )


def is_fd_message(msg: Message) -> bool:
    """Whether a message travels in CAN FD frames: longer than 8 bytes, or declared FD by the DBC
    (``VFrameFormat`` StandardCAN_FD / ExtendedCAN_FD, as cantools reads it) at any length."""
    return msg.length > 8 or bool(msg.is_fd)


def fd_why(msg: Message) -> str:
    return f"{msg.length} bytes" if msg.length > 8 else f"declared FD in the DBC (VFrameFormat), {msg.length} bytes"


def output_id(cfg: Config, msg: Message) -> int:
    """The identifier cmcan sends a message with: on a J1939 machine from its own source address,
    with the DBC's priority and PGN."""
    if _j1939_matched(cfg, msg):
        assert cfg.j1939.source_address is not None
        return int(ids.with_source(msg.frame_id, cfg.j1939.source_address))
    return int(msg.frame_id)


def channels(cfg: Config, log_aliases: Mapping[str, str] | None = None) -> Channels:
    """The configured channels, FD flags and log-channel aliases (the configuration's, then the
    command line's)."""
    chans = cfg.channel_list
    aliases = {**cfg.channels.from_log, **(log_aliases or {})}
    return Channels(tuple(c.name for c in chans), tuple(c.fd for c in chans), aliases)


def _affine(db: Database, ref: SignalRef) -> Affine:
    return role_affine(db.get_message_by_name(ref.message), ref.signal, ref.scale, ref.offset)


def input_messages(cfg: Config, db: Database) -> list[InputMessage]:
    """The mapped input messages: decoders, roles, channel, matching and health checks."""
    by_msg: dict[str, list[tuple[str, SignalRef]]] = {}
    for role, ref in cfg.signals.items():
        by_msg.setdefault(ref.message, []).append((role, ref))
    out = []
    for name, items in by_msg.items():
        msg = db.get_message_by_name(name)
        mc = cfg.message(name)
        j1939 = _j1939_matched(cfg, msg)
        sources = mc.source_addresses if mc.source_addresses_set else cfg.j1939.source_addresses
        pgn = int(ids.pgn(msg.frame_id)) if j1939 else None
        integ = integrity(cfg, msg)
        check = (
            checksums.verifier(integ.algorithm, msg.length, codec.layout(msg, integ.checksum))
            if integ.checksum is not None and integ.algorithm is not None
            else None
        )
        accepted = frozenset(sources) if j1939 and sources is not None else None
        health = HealthSpec(
            counter=codec.layout(msg, integ.counter) if integ.counter is not None else None,
            max_step=cfg.input_health.max_counter_step,
            checksum=check,
            timeout_s=timeout_s(cfg, msg),
            nbytes=codec.frame_bytes(msg),
            checksum_name=f"{integ.checksum} ({integ.algorithm})" if check is not None else "",
            algorithm=integ.algorithm or "",
            checksum_layout=codec.layout(msg, integ.checksum) if check is not None else None,
            j1939=j1939,
            senders=j1939 and (accepted is None or len(accepted) > 1),
        )
        out.append(
            InputMessage(
                frame_id=msg.frame_id,
                length=msg.length,
                layouts=codec.message_layouts(msg, [ref.signal for _, ref in items]),
                size=codec.frame_bytes(msg),
                roles=tuple(role for role, _ in items),
                name=name,
                channel=cfg.message_channel(name),
                extended=bool(msg.is_extended_frame),
                pgn=pgn,
                sources=accepted,
                destinations=frozenset(mc.destinations) if j1939 and mc.destinations is not None else None,
                health=health,
            )
        )
    return out


def frame_matcher(cfg: Config, db: Database, log_aliases: Mapping[str, str] | None = None) -> FrameMatcher:
    """Which mapped input message a frame of a log is, by the monitor's matching rules (channels, CAN
    FD, 11/29-bit identifiers, J1939 PGN and source addresses), for readers of whole logs (training,
    gap diagnosis). They decode every matched frame; the health checks are the monitor's alone."""
    return FrameMatcher(cfg, db, log_aliases)


class FrameMatcher:
    """:func:`frame_matcher`'s matcher; ``seen`` maps each channel name of the log read so far to the
    configured channel it was read as (None: none), as ``Monitor.channels_seen`` does for a replay."""

    def __init__(self, cfg: Config, db: Database, log_aliases: Mapping[str, str] | None = None) -> None:
        self.chans = channels(cfg, log_aliases)
        self.matcher = Matcher(input_messages(cfg, db), self.chans)
        self.memo: dict[tuple[str, int, bool, bool], str | None] = {}
        self.seen: dict[str, str | None] = {}

    def __call__(self, f: Frame) -> str | None:
        key = (f.channel, f.arbitration_id, f.extended, f.fd)
        if key in self.memo:
            return self.memo[key]
        chans = self.chans
        i = chans.resolve(f.channel)
        if f.channel not in self.seen and len(self.seen) < MEMO_MAX:
            self.seen[f.channel] = chans.names[i] if i is not None else None
        spec = None if i is None or (f.fd and not chans.fd[i]) else self.matcher.match(i, f.arbitration_id, f.extended)
        name = spec.name if spec is not None else None
        if len(self.memo) < MEMO_MAX:
            self.memo[key] = name
        return name

    def merged_note(self, cfg: Config) -> str | None:
        """A note when the log's several channels were all read as the machine's one bus (a frame of
        another bus with a mapped identifier is then read as an input), as replay says it."""
        if len(self.seen) > 1 and len(cfg.channel_list) == 1 and not cfg.channels.from_log:
            return (
                f"the log's channels {', '.join(sorted(self.seen))} were all read as {cfg.bus.channel}; "
                f"name the one to read in the configuration's channels.from_log ({{LOG: {cfg.bus.channel}}})"
            )
        return None


def bus_plan(cfg: Config, db: Database) -> BusPlan:
    """How the simulator puts a run on this machine's bus: the mapping, each message's channel (bus.channel's
    as "", the default), its counter and checksum, J1939's padding with 1s."""
    from cmcan.sim.frames import BusPlan  # the simulator's: the monitor and the check do without it

    counters, sums, chans = {}, {}, {}
    for name in _input_names(cfg):
        msg = db.get_message_by_name(name)
        integ = integrity(cfg, msg)
        if integ.counter is not None:
            counters[name] = integ.counter
        if integ.checksum is not None and integ.algorithm is not None:
            sums[name] = (integ.checksum, integ.algorithm)
        chan = cfg.message_channel(name)
        if chan != cfg.bus.channel:  # bus.channel's messages carry "": the default channel
            chans[name] = chan
    return BusPlan(
        mapping={r: (ref.message, ref.signal, ref.scale, ref.offset) for r, ref in cfg.signals.items()},
        channel=chans,
        counter=counters,
        checksum=sums,
        fill_unused=cfg.j1939.enabled,
    )


def role_affines(cfg: Config, db: Database) -> tuple[dict[str, Affine], DpFromHighLow | None]:
    """Each gated role's raw-to-unit map, and how dp is formed when high and low pressure are mapped."""
    affine = {r: _affine(db, ref) for r, ref in cfg.signals.items() if r in gated_roles(cfg.quantity)}
    if DP in affine:
        return affine, None
    dp = dp_affine(_affine(db, cfg.signals[HIGH_PRESSURE]), _affine(db, cfg.signals[LOW_PRESSURE]))
    if dp is None:  # check_against_dbc refuses this configuration first
        raise SchemaError(cfg.source, f"signals.{LOW_PRESSURE}", "resolution not commensurate with high pressure")
    affine[DP], p, q = dp
    return affine, DpFromHighLow(p, q)


def outputs(cfg: Config, db: Database) -> Outputs:
    period_ms = 1000.0 / cfg.rate_hz

    def message(key: str) -> OutputMessage:
        out = dict(cfg.output_items())[key]
        msg = _message(cfg, db, out.message, f"outputs.{key}.message")
        return OutputMessage(
            frame_id=output_id(cfg, msg),
            extended=bool(msg.is_extended_frame),
            layouts=codec.message_layouts(msg),
            size=codec.frame_bytes(msg),
            length=msg.length,
            every_ticks=max(1, round(out.period_ms / period_ms)),
            # J1939 sends the bits of no signal as 1
            fill=codec.unused(msg) if _j1939_matched(cfg, msg) else b"",
        )

    q = cfg.quantity
    return Outputs(
        ratio=message("cm_ratio"),
        quantity=message(QUANTITY_OUTPUT[q]),
        warning=message("warning"),
        channel=cfg.output_channel,
        quantity_signals=QUANTITY_SIGNALS[q],
        baseline=message("cm_baseline") if cfg.baseline.enabled else None,
        prognosis=message("cm_prognosis") if cfg.prognosis.enabled else None,
    )


def envelope_for(cfg: Config, envelope: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
    """The model's training envelope widened (or narrowed) by the configuration's margin: beyond it a
    point is evaluated as ``EXTRAPOLATED``."""
    margin = cfg.gating.envelope_margin_pct / 100.0
    return {k: (lo - margin * (hi - lo), hi + margin * (hi - lo)) for k, (lo, hi) in envelope.items()}


def dm1_params(cfg: Config, db: Database) -> Dm1Params | None:
    """DM1 where the configuration enables it; priority from a DM1 message in the DBC, else 6."""
    d = cfg.j1939.dm1
    if not d.enabled:
        return None
    assert cfg.j1939.source_address is not None
    prio = next(
        (
            int(ids.priority(m.frame_id))
            for m in db.messages
            if m.is_extended_frame and ids.pgn(m.frame_id) == j1939_dm1.PGN_DM1
        ),
        j1939_dm1.DM1_PRIORITY,
    )
    th = cfg.thresholds
    return Dm1Params(
        spn=d.spn,
        input_spn=d.input_spn,
        low_severe_pct=d.low_severe_pct,
        high_severe_pct=d.high_severe_pct,
        hysteresis_pct=th.hysteresis_pct,
        every_ticks=max(1, round(d.period_ms / (1000.0 / cfg.rate_hz))),
        source=cfg.j1939.source_address,
        priority=prio,
        bam_gap_s=cfg.j1939.bam_packet_gap_ms / 1000.0,
        channel=cfg.output_channel,
        answers_waiting_max=cfg.j1939.answers.waiting_max,
    )


def _role_messages(cfg: Config) -> dict[str, str]:
    """Each gated role's message (dp's is high pressure's: it is formed at each high-pressure frame;
    a role the machine holds constant has none)."""
    msg_of = {r: ref.message for r, ref in cfg.signals.items()}
    if DP not in msg_of and HIGH_PRESSURE in msg_of:
        msg_of[DP] = msg_of[HIGH_PRESSURE]
    return {r: msg_of[r] for r in gated_roles(cfg.quantity) if r in msg_of}


def max_ages(cfg: Config, db: Database) -> dict[str, float]:
    """Each gated role's largest sample age: the configured one, at most its message's timeout."""
    ages = {r: cfg.max_age_s(r) for r in gated_roles(cfg.quantity)}
    for r, name in _role_messages(cfg).items():
        ages[r] = min(ages[r], timeout_s(cfg, db.get_message_by_name(name)))
    return ages


def fitted_limits(cfg: Config, db: Database) -> tuple[GateLimits, dict[str, float], dict[str, RoleFit]]:
    """The gate limits and maximum sample ages fitted to the cycle time of each role's message
    (:func:`cmcan.monitor.gating.fit_to_cycles`: a slow message's role gets its own window and
    sample count), and how each role was fitted."""
    cycles = {r: cycle_s(cfg, db.get_message_by_name(name)) for r, name in _role_messages(cfg).items()}
    return fit_to_cycles(cfg.gate_limits, max_ages(cfg, db), cycles)


def monitor_params(cfg: Config, db: Database, envelope: dict[str, tuple[float, float]] | None) -> MonitorParams:
    env = None if envelope is None else envelope_for(cfg, envelope)
    affine, dp = role_affines(cfg, db)
    limits, ages, _ = fitted_limits(cfg, db)
    return MonitorParams(
        rate_hz=cfg.rate_hz,
        limits=limits,
        max_age_s=ages,
        envelope=env,
        filter_samples=cfg.filter.samples,
        filter_min_samples=cfg.filter.min_samples,
        thresholds=cfg.thresholds,
        lpm_per_unit=cfg.lpm_per_unit,
        affine=affine,
        dp_from_high_low=dp,
        constants=dict(cfg.drive.fixed),
    )


def build_monitor(
    cfg: Config,
    db: Database,
    model: GrayBoxModel,
    totals: Totals | None = None,
    log_aliases: Mapping[str, str] | None = None,
) -> Monitor:
    """A monitor for the configuration, its DBC and a loaded model (its envelope gates the points);
    ``log_aliases`` map a log's channel names to configured channels (replay's --channel-map)."""
    check_against_dbc(cfg, db)
    check_output_ranges(cfg, db)
    return Monitor(
        monitor_params(cfg, db, model.envelope),
        input_messages(cfg, db),
        model,
        outputs(cfg, db),
        totals=totals or Totals(),
        channels=channels(cfg, log_aliases),
        dm1=dm1_params(cfg, db),
        own_address=cfg.j1939.source_address if cfg.j1939.enabled else None,
        node=node_params(cfg, db),
        baseline=baseline_params(cfg, model),
        prognosis=prognosis_params(cfg),
    )


def prognosis_params(cfg: Config) -> PrognosisParams | None:
    """The prognosis where the configuration enables it, on the warning's thresholds and the oil."""
    p = cfg.prognosis
    if not p.enabled:
        return None
    return replace(p.params, low_pct=cfg.thresholds.low_pct, high_pct=cfg.thresholds.high_pct, oil=cfg.oil)


# Bins along each role of the envelope the coverage counts over, where the configuration gives no
# edges: low / mid / high speed and pressure, cold and warm oil.
BASELINE_BINS = {PUMP_SPEED: 3, DP: 3, TEMP: 2}
# Without a configured allowance or the type's unit spread: a bin this share of the nominal flow away
# from the type model is no unit-to-unit difference (displacement and sensor tolerances give ~1 %).
SUSPECT_SHARE_OF_NOMINAL = 0.02


def suspect_allowance(cfg: Config, model: GrayBoxModel) -> tuple[float, str]:
    """The baseline guard's allowance (l/min) and where it comes from, in words."""
    b = cfg.baseline.settings
    if b.suspect_lpm is not None:
        return float(b.suspect_lpm), "configured (baseline.suspect_lpm)"
    spread = (model.meta.training or {}).get("unit_spread") or {}
    sd = spread.get("offset_sd_lpm") if isinstance(spread, dict) else None
    if isinstance(sd, (int, float)) and not isinstance(sd, bool) and math.isfinite(sd) and sd > 0:
        return b.suspect_sigmas * float(sd), (
            f"{b.suspect_sigmas:g} x the type's unit spread ({float(sd):.3g} l/min, the model's metadata)"
        )
    share = SUSPECT_SHARE_OF_NOMINAL
    return share * cfg.drive.nominal_flow_lpm, (
        f"{100 * share:g} % of the nominal flow (the model records no unit spread: fleet train writes one)"
    )


def baseline_params(cfg: Config, model: GrayBoxModel) -> BaselineParams | None:
    """The on-board baseline where the configuration enables it: the envelope's bins (configured, or the
    model's envelope split in :data:`BASELINE_BINS`), the guard's allowance (configured, or
    ``suspect_sigmas`` x the type's unit spread from the model's training metadata, or
    :data:`SUSPECT_SHARE_OF_NOMINAL` of the nominal flow)."""
    if not cfg.baseline.enabled:
        return None
    b = cfg.baseline.settings
    env = model.envelope
    gated = envelope_for(cfg, env)  # a tick outside this is not evaluated, so never learned
    edges = []
    for role in BIN_ROLES:
        if role in b.edges:
            e = tuple(b.edges[role])
            lo, hi = gated[role]
            if e[-1] <= lo or e[0] >= hi:
                raise SchemaError(
                    cfg.source,
                    f"baseline.edges.{role}",
                    f"[{e[0]:g}, {e[-1]:g}] lies outside the model's envelope [{lo:g}, {hi:g}] ({model.path}): "
                    "no tick there is evaluated, so the baseline would learn nothing",
                )
            edges.append(e)
        else:
            lo, hi = env[role]
            edges.append(tuple(float(v) for v in np.linspace(lo, hi, BASELINE_BINS[role] + 1)))
    suspect, _ = suspect_allowance(cfg, model)
    given = {"edges": tuple(edges), "suspect_lpm": float(suspect)}  # the settings' derived from the model
    return BaselineParams(
        **{**carried(b, BaselineParams), **given},
        lpm_per_unit=cfg.lpm_per_unit,
        period_s=1.0 / cfg.rate_hz,
        max_gap_s=cfg.prognosis.params.max_gap_h * 3600.0,  # the operating clock the prognosis counts on
        oil=cfg.oil,
        learning_thresholds=replace(cfg.thresholds, low_pct=b.learning_low_pct, high_pct=b.learning_high_pct),
        block_ticks=max(1, round(b.check_every_s * cfg.rate_hz)),
    )


def node_params(cfg: Config, db: Database) -> NodeParams | None:
    """cmcan as a J1939 node on its output channel, on a J1939 machine: it answers requests, and with
    a NAME it claims its address (and, arbitrary address capable, moves within j1939.addresses)."""
    j = cfg.j1939
    if not j.enabled or j.source_address is None:
        return None
    claim = None
    if j.name is not None:
        claim = ClaimParams(j.name, j.source_address, j.addresses, cfg.output_channel)
    out = [msg for _, o in cfg.output_items() if (msg := db.get_message_by_name(o.message)).is_extended_frame]
    return NodeParams(
        address=j.source_address,
        channel=cfg.output_channel,
        claim=claim,
        output_pgns=frozenset(int(ids.pgn(m.frame_id)) for m in out if _j1939_matched(cfg, m)),
        request_interval_s=j.request_interval_ms / 1000.0,
        trust=j.clears,
        answers=j.answers,
    )


@dataclass(frozen=True)
class Assembled:
    cfg: Config
    db: Database
    model: GrayBoxModel
    monitor: Monitor


def assemble(
    cfg: Config,
    model_path: str | Path | None = None,
    totals: Totals | None = None,
    log_aliases: Mapping[str, str] | None = None,
) -> Assembled:
    """DBC and model loaded and checked against the configuration, and the monitor built. Raises
    DbcError, SchemaError or ModelError naming the file and field (kinds: configuration, no input)."""
    db = dbc_for(cfg)
    check_against_dbc(cfg, db)
    check_output_ranges(cfg, db)  # before the model: a DBC's problem is not hidden behind a model's
    model = load_model_for(cfg, model_path)
    return Assembled(cfg, db, model, build_monitor(cfg, db, model, totals, log_aliases))
