"""Assembling a Monitor from a configuration, its DBC and a model (checked against each other)."""

from __future__ import annotations

from cantools.database.can import Database

from cmcan import codec
from cmcan.config import Config
from cmcan.monitor.core import InputFrame, Monitor, MonitorParams, Outputs, Predictor
from cmcan.monitor.gating import GATED_ROLES
from cmcan.monitor.totals import Totals
from cmcan.monitor.warnings import Thresholds
from cmcan.schema import SchemaError

OUTPUT_SIGNALS = {
    "cm_ratio": (
        "cm_ratio_raw_pct",
        "cm_ratio_filt_pct",
        "extra_leakage_lpm",
        "cm_raw_valid",
        "cm_filt_valid",
        "cm_gate",
        "cm_alive_counter",
    ),
    "cm_speed": (
        "motor_speed_meas_rpm",
        "motor_speed_pred_rpm",
        "motor_speed_whitebox_rpm",
        "cm_speed_valid",
        "cm_alive_counter",
    ),
    "warning": ("warning_level", "warning_reason", "time_below_threshold_s", "warning_count"),
}


def input_frames(cfg: Config, db: Database) -> dict[int, InputFrame]:
    by_msg: dict[str, list[tuple[str, str, float, float]]] = {}
    for role, ref in cfg.signals.items():
        by_msg.setdefault(ref.message, []).append((role, ref.signal, ref.scale, ref.offset))
    frames = {}
    for mname, items in by_msg.items():
        msg = db.get_message_by_name(mname)
        names = [sig for _, sig, _, _ in items]
        conv = [(sc, off) for _, _, sc, off in items]
        frames[msg.frame_id] = InputFrame(
            frame_id=msg.frame_id,
            length=msg.length,
            decode=codec.compile_checked_decoder(msg, names, conv),
            roles=tuple(role for role, _, _, _ in items),
        )
    return frames


def outputs(cfg: Config, db: Database, rate_hz: float) -> Outputs:
    msgs = {}
    for key, signals in OUTPUT_SIGNALS.items():
        name = cfg.raw["outputs"][key]["message"]
        try:
            msg = db.get_message_by_name(name)
        except KeyError:
            raise SchemaError(cfg.source, f"outputs.{key}.message", f"no message {name!r} in {cfg.dbc_path}") from None
        have = {s.name for s in msg.signals}
        missing = [s for s in signals if s not in have]
        if missing:
            raise SchemaError(
                cfg.source,
                f"outputs.{key}.message",
                f"message {name} in {cfg.dbc_path} lacks signal(s) {', '.join(missing)}",
            )
        msgs[key] = msg
    period_ms = 1000.0 / rate_hz

    def every(key: str) -> int:
        return max(1, round(cfg.raw["outputs"][key]["period_ms"] / period_ms))

    return Outputs(
        ratio_id=msgs["cm_ratio"].frame_id,
        speed_id=msgs["cm_speed"].frame_id,
        warning_id=msgs["warning"].frame_id,
        encode_ratio=codec.compile_encoder(msgs["cm_ratio"]),
        encode_speed=codec.compile_encoder(msgs["cm_speed"]),
        encode_warning=codec.compile_encoder(msgs["warning"]),
        cm_every_ticks=every("cm_ratio"),
        speed_every_ticks=every("cm_speed"),
        warning_every_ticks=every("warning"),
    )


def params(cfg: Config, envelope: dict[str, tuple[float, float]] | None) -> MonitorParams:
    margin = cfg.raw["gating"]["envelope_margin_pct"] / 100.0
    env = None
    if envelope is not None:
        env = {k: (lo - margin * (hi - lo), hi + margin * (hi - lo)) for k, (lo, hi) in envelope.items()}
    th = cfg.raw["thresholds"]
    flt = cfg.raw["filter"]
    return MonitorParams(
        rate_hz=float(cfg.raw["evaluation"]["rate_hz"]),
        limits=cfg.gate_limits,
        max_age_s={r: cfg.max_age_s(r) for r in GATED_ROLES},
        envelope=env,
        filter_samples=int(flt["samples"]),
        filter_min_samples=int(flt["min_samples"]),
        thresholds=Thresholds(
            th["low_pct"], th["high_pct"], th["hysteresis_pct"], th["debounce_s"], th["fault_after_s"]
        ),
        motor_disp_cc=cfg.motor_disp_cc,
        dp_from_high_low="dp_bar" not in cfg.signals,
    )


def build_monitor(
    cfg: Config,
    db: Database,
    model: Predictor,
    envelope: dict[str, tuple[float, float]] | None,
    totals: Totals | None = None,
    keep_timeline: bool = False,
) -> Monitor:
    p = params(cfg, envelope)
    return Monitor(p, input_frames(cfg, db), model, outputs(cfg, db, p.rate_hz), totals or Totals(), keep_timeline)
