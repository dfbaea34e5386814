"""Operating points for training and evaluation: measured data in, gated window means out.

Measured data is a run CSV (columns named as ``cmcan simulate`` writes them) or a CAN log decoded
through the DBC and the role mapping. Either becomes per-role time series, then trailing-window
statistics at the evaluation rate, then the monitor's gate.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from cantools.database.can import Database
from numpy.typing import NDArray

from cmcan import codec
from cmcan.errors import CmcanError, Kind
from cmcan.frame import Frame
from cmcan.io.candump import iter_frames
from cmcan.io.runcsv import read_run_csv
from cmcan.monitor.gating import Gate, GateLimits, WindowStats, eval_times, gate, window_stats
from cmcan.monitor.windows import dp_affine, dp_raw, role_affine
from cmcan.roles import DEFAULT_INPUTS, DP, GATED, HIGH_PRESSURE, LOW_PRESSURE, MODEL_INPUTS, MOTOR_SPEED, SignalRef

Series = dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]
CSV_REQUIRED = ("time_s", *GATED)
LOG_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".mf4", ".db", ".gz")


class DataError(CmcanError, ValueError):
    """Measured data cannot be used; ``str()`` names the file and what is missing or wrong."""

    kind = Kind.DATA


@dataclass(frozen=True)
class OperatingPoints:
    t_s: NDArray[np.float64]  # evaluation times (the data's own time base)
    x: NDArray[np.float64]  # (n, 4) model inputs in MODEL_INPUTS order: window means
    motor_speed_rpm: NDArray[np.float64]
    gate: NDArray[np.int64]
    stats: WindowStats
    truth: dict[str, NDArray[np.float64]]  # ground-truth columns at t_s where the data has them
    t0_s: float  # time of the first sample, for hours since start

    @property
    def steady(self) -> NDArray[np.bool_]:
        return self.gate == Gate.EVALUATING

    @property
    def hours(self) -> NDArray[np.float64]:
        return (self.t_s - self.t0_s) / 3600.0

    def select(self, mask: NDArray[np.bool_]) -> OperatingPoints:
        st = self.stats
        sub = WindowStats(*({k: v[mask] for k, v in d.items()} for d in (st.mean, st.std, st.count, st.age_s)))
        return OperatingPoints(
            self.t_s[mask],
            self.x[mask],
            self.motor_speed_rpm[mask],
            self.gate[mask],
            sub,
            {k: v[mask] for k, v in self.truth.items()},
            self.t0_s,
        )


def is_log(path: str | Path) -> bool:
    return Path(path).suffix.lower() in LOG_SUFFIXES


def series_from_csv(path: str | Path) -> tuple[Series, dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]]:
    try:
        cols = read_run_csv(path, required=CSV_REQUIRED)
    except ValueError as exc:
        raise DataError(str(exc), getattr(exc, "kind", Kind.DATA)) from None
    return series_from_columns(cols, str(path))


def series_from_columns(
    cols: Mapping[str, NDArray[np.float64]], source: str = "<run>"
) -> tuple[Series, dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]]:
    """Per-role series (and ground truth) from run columns, as a CSV or ``simulate()`` holds them."""
    path = source
    t = cols["time_s"]
    if len(t) < 2:
        raise DataError(f"{path}: fewer than two rows of data")
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 2
        raise DataError(f"{path}: time_s must increase from row to row (row {k + 1} does not)")
    series = {r: (t, cols[r]) for r in GATED}
    truth = {k: (t, v) for k, v in cols.items() if k.startswith("true_") or k == "operating_h"}
    return series, truth


def as_refs(mapping: Mapping[str, Any] | None) -> dict[str, SignalRef]:
    """Role mapping as SignalRefs (from a config, or (message, signal) pairs; DBC defaults if None)."""
    mapping = mapping if mapping is not None else DEFAULT_INPUTS
    return {r: v if isinstance(v, SignalRef) else SignalRef(*v) for r, v in mapping.items()}


def _affine(db: Database, ref: SignalRef) -> Any:
    return role_affine(db.get_message_by_name(ref.message), ref.signal, ref.scale, ref.offset)


def series_from_log(
    path: str | Path,
    db: Database,
    mapping: Mapping[str, Any] | None = None,
    match: Callable[[Frame], str | None] | None = None,
) -> Series:
    """Decode a CAN log into per-role series (vectorized per message), in each role's unit; dp from
    high and low pressure is formed as the monitor forms it. ``match`` says which mapped message a
    frame is (the monitor's rules: channels, 29-bit and J1939 identifiers; see
    :func:`cmcan.assemble.frame_matcher`); by default a standard frame with the message's identifier."""
    refs = as_refs(mapping)
    by_name = {r.message: db.get_message_by_name(r.message) for r in refs.values()}
    by_id = {m.frame_id: name for name, m in by_name.items() if not m.is_extended_frame}
    stamps: dict[str, list[float]] = {n: [] for n in by_name}
    payloads: dict[str, list[bytes]] = {n: [] for n in by_name}
    try:
        for f in iter_frames(path):
            if f.remote or f.error:
                continue
            name = match(f) if match is not None else (None if f.extended else by_id.get(f.arbitration_id))
            if name is not None and len(f.data) >= by_name[name].length:
                stamps[name].append(f.timestamp_s)
                payloads[name].append(f.data[:8].ljust(8, b"\0"))
    except FileNotFoundError as exc:
        raise DataError(str(exc), Kind.NO_INPUT) from None
    except (ValueError, OSError) as exc:
        raise DataError(f"{path}: cannot read CAN log: {exc}") from None
    raws: dict[str, tuple[NDArray[np.float64], NDArray[np.int64]]] = {}
    series: Series = {}
    for role, ref in refs.items():
        m = db.get_message_by_name(ref.message)
        ts = np.asarray(stamps[m.name], dtype=float)
        if len(ts) == 0:
            continue
        data = np.frombuffer(b"".join(payloads[m.name]), dtype=np.uint8).reshape(-1, 8)
        order = np.argsort(ts, kind="stable")
        raw = codec.decode_raw(m, data[order], [ref.signal])[ref.signal]
        raws[role] = (ts[order], raw)
        f = _affine(db, ref)
        series[role] = (ts[order], raw * f.a + f.b)
    if DP not in series and HIGH_PRESSURE in raws and LOW_PRESSURE in raws:
        hl = dp_affine(_affine(db, refs[HIGH_PRESSURE]), _affine(db, refs[LOW_PRESSURE]))
        if hl is None:
            raise DataError(f"{path}: high and low pressure resolutions are not commensurate; map dp_bar", Kind.CONFIG)
        f, p, q = hl
        t, r = dp_raw(*raws[HIGH_PRESSURE], *raws[LOW_PRESSURE], p, q)
        series[DP] = (t, r * f.a + f.b)
    missing = [r for r in GATED if r not in series]
    if missing:
        expected = sorted({refs[r].message for r in missing if r in refs})
        raise DataError(f"{path}: no frames for {', '.join(missing)} (expected messages {', '.join(expected)})")
    return series


def contiguous_spans(t: NDArray[np.float64], max_gap_s: float) -> list[tuple[float, float]]:
    """[first, last] time of each stretch of data without a gap longer than ``max_gap_s``."""
    cuts = np.flatnonzero(np.diff(t) > max_gap_s)
    firsts = np.r_[t[0], t[cuts + 1]]
    lasts = np.r_[t[cuts], t[-1]]
    return list(zip(firsts.tolist(), lasts.tolist(), strict=True))


def operating_points(
    series: Series,
    limits: GateLimits,
    rate_hz: float = 10.0,
    envelope: dict[str, tuple[float, float]] | None = None,
    truth: dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]] | None = None,
) -> OperatingPoints:
    t_motor = series[MOTOR_SPEED][0]
    spans = contiguous_spans(t_motor, max_gap_s=max(limits.window_s, 1.0))
    t_eval = np.concatenate([eval_times(a, b, rate_hz) for a, b in spans]) if spans else np.empty(0)
    stats = window_stats(series, t_eval, limits.window_s)
    codes = gate(stats, limits, envelope=envelope)
    x = np.column_stack([stats.mean[r] for r in MODEL_INPUTS])
    tr = {}
    for k, (tt, vv) in (truth or {}).items():
        idx = np.clip(np.searchsorted(tt, t_eval, side="right") - 1, 0, len(tt) - 1)
        tr[k] = vv[idx]
    return OperatingPoints(t_eval, x, stats.mean[MOTOR_SPEED], codes, stats, tr, float(t_motor[0]))


def load_operating_points(
    path: str | Path,
    limits: GateLimits,
    db: Database | None = None,
    mapping: Mapping[str, Any] | None = None,
    rate_hz: float = 10.0,
    match: Callable[[Frame], str | None] | None = None,
) -> OperatingPoints:
    """Operating points of a run CSV or a CAN log (chosen by the file's extension)."""
    p = Path(path)
    if not p.exists():
        raise DataError(f"{p}: file not found", Kind.NO_INPUT)
    if is_log(p):
        if db is None:
            from cmcan.dbc import load_dbc

            db = load_dbc()
        return operating_points(series_from_log(p, db, mapping, match), limits, rate_hz)
    series, truth = series_from_csv(p)
    return operating_points(series, limits, rate_hz, truth=truth)
