"""Assembly: a configuration, its DBC and a model, checked against each other, into a Monitor.

The one place that knows both the configuration's vocabulary and the core's parameter types. The
daemon, the replay, the demo and the tests build their monitors here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from cantools.database.can import Database, Message

from cmcan import codec
from cmcan.config import Config
from cmcan.dbc import DbcError, load_dbc
from cmcan.errors import Kind
from cmcan.model import GrayBoxModel, ModelError, default_model_path, load_model
from cmcan.monitor.core import DpFromHighLow, InputMessage, Monitor, MonitorParams
from cmcan.monitor.gating import GateLimits, prediction_ok
from cmcan.monitor.payloads import OutputMessage, Outputs
from cmcan.monitor.totals import Totals
from cmcan.monitor.windows import Affine, dp_affine, role_affine
from cmcan.roles import (
    DP,
    HIGH_PRESSURE,
    LOW_PRESSURE,
    MODEL_INPUTS,
    OUTPUT_SIGNALS,
    QUANTITY_OUTPUT,
    QUANTITY_SIGNALS,
    UNITS,
    SignalRef,
    gated_roles,
)
from cmcan.schema import SchemaError


def dbc_for(cfg: Config) -> Database:
    """The configuration's DBC (DbcError names the file and that the configuration named it)."""
    try:
        return load_dbc(cfg.dbc_path)
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
    env = model.envelope
    names = list(MODEL_INPUTS)
    centre = [(env[r][0] + env[r][1]) / 2.0 for r in names]
    points = [centre]
    for i, r in enumerate(names):
        for bound in env[r]:
            x = list(centre)
            x[i] = bound
            points.append(x)
    x = np.array(points, dtype=np.float64)
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
    """Every mapped message and signal exists and can be decoded; outputs exist, carry what cmcan
    sends and are not inputs; high and low pressure can be subtracted exactly."""
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
            raise SchemaError(
                cfg.source, f"signals.{role}", f"{problem} in {cfg.dbc_path}: cmcan reads integer signals"
            )
    inputs = {ref.message for ref in cfg.signals.values()}
    for key, out in cfg.outputs.items(cfg.quantity):
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
            raise SchemaError(cfg.source, f"outputs.{key}.message", f"{problem} in {cfg.dbc_path}")
    if HIGH_PRESSURE in cfg.signals and DP not in cfg.signals:
        high, low = _affine(db, cfg.signals[HIGH_PRESSURE]), _affine(db, cfg.signals[LOW_PRESSURE])
        if dp_affine(high, low) is None:
            raise SchemaError(
                cfg.source,
                f"signals.{LOW_PRESSURE}",
                f"its resolution ({low.a:g} bar) and high_pressure_bar's ({high.a:g} bar) are not in a small "
                "integer ratio, so dp cannot be formed exactly; map dp_bar or use the same resolution",
            )


def _affine(db: Database, ref: SignalRef) -> Affine:
    return role_affine(db.get_message_by_name(ref.message), ref.signal, ref.scale, ref.offset)


def input_messages(cfg: Config, db: Database) -> dict[int, InputMessage]:
    by_msg: dict[str, list[tuple[str, SignalRef]]] = {}
    for role, ref in cfg.signals.items():
        by_msg.setdefault(ref.message, []).append((role, ref))
    frames = {}
    for name, items in by_msg.items():
        msg = db.get_message_by_name(name)
        frames[msg.frame_id] = InputMessage(
            frame_id=msg.frame_id,
            length=msg.length,
            layouts=codec.message_layouts(msg, [ref.signal for _, ref in items]),
            size=codec.frame_bytes(msg),
            roles=tuple(role for role, _ in items),
        )
    return frames


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
        out = dict(cfg.outputs.items(cfg.quantity))[key]
        msg = _message(cfg, db, out.message, f"outputs.{key}.message")
        return OutputMessage(
            frame_id=msg.frame_id,
            extended=bool(msg.is_extended_frame),
            layouts=codec.message_layouts(msg),
            size=codec.frame_bytes(msg),
            length=msg.length,
            every_ticks=max(1, round(out.period_ms / period_ms)),
        )

    q = cfg.quantity
    return Outputs(
        ratio=message("cm_ratio"),
        quantity=message(QUANTITY_OUTPUT[q]),
        warning=message("warning"),
        quantity_signals=QUANTITY_SIGNALS[q],
    )


def envelope_for(cfg: Config, envelope: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
    """The model's training envelope widened (or narrowed) by the configuration's margin: beyond it a
    point is evaluated as ``EXTRAPOLATED``."""
    margin = cfg.gating.envelope_margin_pct / 100.0
    return {k: (lo - margin * (hi - lo), hi + margin * (hi - lo)) for k, (lo, hi) in envelope.items()}


def monitor_params(cfg: Config, db: Database, envelope: dict[str, tuple[float, float]] | None) -> MonitorParams:
    env = None if envelope is None else envelope_for(cfg, envelope)
    affine, dp = role_affines(cfg, db)
    return MonitorParams(
        rate_hz=cfg.rate_hz,
        limits=cfg.gate_limits,
        max_age_s={r: cfg.max_age_s(r) for r in gated_roles(cfg.quantity)},
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
    keep_timeline: bool = False,
) -> Monitor:
    """A monitor for the configuration, its DBC and a loaded model (its envelope gates the points)."""
    check_against_dbc(cfg, db)
    return Monitor(
        monitor_params(cfg, db, model.envelope),
        input_messages(cfg, db),
        model,
        outputs(cfg, db),
        totals or Totals(),
        keep_timeline,
    )


@dataclass(frozen=True)
class Assembled:
    cfg: Config
    db: Database
    model: GrayBoxModel
    monitor: Monitor


def assemble(
    cfg: Config, model_path: str | Path | None = None, totals: Totals | None = None, keep_timeline: bool = False
) -> Assembled:
    """DBC and model loaded and checked against the configuration, and the monitor built. Raises
    DbcError, SchemaError or ModelError naming the file and field (kinds: configuration, no input)."""
    db = dbc_for(cfg)
    check_against_dbc(cfg, db)
    model = load_model_for(cfg, model_path)
    return Assembled(cfg, db, model, build_monitor(cfg, db, model, totals, keep_timeline))
