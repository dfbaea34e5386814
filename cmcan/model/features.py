"""Operating points for training, scoring and evaluation: measured data in, gated means out.

Measured data is a run CSV (columns named as ``cmcan simulate`` writes them), a CAN log decoded
through the DBC and the role mapping, or an operating-point table whose rows are already means (one
per load cycle, :mod:`cmcan.io.points`). Time series become per-role series, then trailing-window
statistics at the evaluation rate, then the monitor's gate; a table's rows are gated directly (the
same rules, without staleness and steadiness, which a cycle mean does not have).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can import codec
from cmcan.can.frame import Frame, FrameColumns
from cmcan.errors import CmcanError, Kind
from cmcan.io.candump import Cut
from cmcan.io.points import Condition, Points, cell_value
from cmcan.io.runcsv import read_run_csv
from cmcan.monitor.gating import (
    Gate,
    GateLimits,
    WindowStats,
    eval_times,
    gate,
    outside_plausible,
    table_stats,
    window_stats,
)
from cmcan.monitor.windows import dp_affine, dp_raw, role_affine
from cmcan.roles import (
    DEFAULT_INPUTS,
    DP,
    HIGH_PRESSURE,
    LOW_PRESSURE,
    MODEL_INPUTS,
    MOTOR_SPEED,
    UNITS,
    SignalRef,
    gated_roles,
)

if TYPE_CHECKING:  # a hint only: cantools imports python-can, which imports asammdf (issue 37)
    from cantools.database.can import Database

Series = dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]
CSV_REQUIRED = ("time_s", *gated_roles(MOTOR_SPEED))
LOG_SUFFIXES = (".log", ".asc", ".blf", ".trc", ".mf4", ".db", ".gz")


class DataError(CmcanError, ValueError):
    """Measured data cannot be used; ``str()`` names the file and what is missing or wrong."""

    kind = Kind.DATA


@dataclass(frozen=True)
class OperatingPoints:
    t_s: NDArray[np.float64]  # evaluation times (the data's own time base); a table: 0, 1, 2, ...
    x: NDArray[np.float64]  # (n, 4) model inputs in MODEL_INPUTS order: window means
    measured: NDArray[np.float64]  # the output quantity's window mean
    gate: NDArray[np.int64]
    stats: WindowStats
    truth: dict[str, NDArray[np.float64]]  # ground-truth columns at t_s where the data has them
    t0_s: float  # time of the first sample, for hours since start
    quantity: str = MOTOR_SPEED
    # A table's 1-based data row numbers, its column names and the kept rows' cells as written.
    rows: NDArray[np.int64] | None = None
    header: tuple[str, ...] = ()
    cells: tuple[tuple[str, ...], ...] = ()
    source: str = ""

    @property
    def steady(self) -> NDArray[np.bool_]:
        """Points training may learn from: passed every gate (there is no envelope before training)."""
        return self.gate == Gate.EVALUATING

    @property
    def hours(self) -> NDArray[np.float64]:
        return (self.t_s - self.t0_s) / 3600.0

    @property
    def is_table(self) -> bool:
        return self.rows is not None

    def __len__(self) -> int:
        return len(self.t_s)

    def select(self, mask: NDArray[np.bool_]) -> OperatingPoints:
        st = self.stats
        sub = WindowStats(*({k: v[mask] for k, v in d.items()} for d in (st.mean, st.std, st.count, st.age_s)))
        idx = np.flatnonzero(mask)
        return OperatingPoints(
            self.t_s[mask],
            self.x[mask],
            self.measured[mask],
            self.gate[mask],
            sub,
            {k: v[mask] for k, v in self.truth.items()},
            self.t0_s,
            self.quantity,
            None if self.rows is None else self.rows[mask],
            self.header,
            tuple(self.cells[i] for i in idx) if self.cells else (),
            self.source,
        )

    def columns(self) -> dict[str, NDArray[np.float64]]:
        """Named columns of the points, for conditions and outputs: a table's own numeric columns,
        or time, hours, each gated role's window mean and the ground truth of a time series."""
        if self.is_table:
            out: dict[str, NDArray[np.float64]] = {}
            for j, name in enumerate(self.header):
                out[name] = _floats([row[j] for row in self.cells])
            return out
        return {
            "time_s": self.t_s,
            "operating_h": self.hours,
            **{r: self.stats.mean[r] for r in (*MODEL_INPUTS, self.quantity) if r in self.stats.mean},
            **self.truth,
        }

    def where(self, conditions: Sequence[Condition]) -> NDArray[np.bool_]:
        """Points that meet every condition (on :meth:`columns`); a condition's column must exist."""
        keep = np.ones(len(self), dtype=bool)
        if not conditions:
            return keep
        cols = self.columns()
        for c in conditions:
            if c.column not in cols:
                raise DataError(f"{self.source}: --where {c}: no column {c.column!r}; there are {', '.join(cols)}")
            keep &= c.holds(cols[c.column])
        return keep


def _floats(cells: Sequence[str]) -> NDArray[np.float64]:
    """A table column's cells as numbers by the CSV readers' rule (:func:`cmcan.io.points.cell_value`);
    a missing value or a text cell (a label such as ``healthy``) is NaN."""
    out = np.full(len(cells), np.nan)
    for i, c in enumerate(cells):
        with contextlib.suppress(ValueError):
            v = cell_value(c)
            out[i] = np.nan if v is None else v
    return out


def is_log(path: str | Path) -> bool:
    return Path(path).suffix.lower() in LOG_SUFFIXES


def series_from_csv(
    path: str | Path, quantity: str = MOTOR_SPEED, constants: Mapping[str, float] | None = None
) -> tuple[Series, dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]]:
    constants = constants or {}
    required = ("time_s", *(r for r in gated_roles(quantity) if r not in constants))
    try:
        cols = read_run_csv(path, required=required)
    except ValueError as exc:
        raise DataError(str(exc), getattr(exc, "kind", Kind.DATA)) from None
    return series_from_columns(cols, str(path), quantity, constants)


def series_from_columns(
    cols: Mapping[str, NDArray[np.float64]],
    source: str = "<run>",
    quantity: str = MOTOR_SPEED,
    constants: Mapping[str, float] | None = None,
) -> tuple[Series, dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]]:
    """Per-role series (and ground truth) from run columns, as a CSV or ``simulate()`` holds them;
    a role the machine holds constant is that value at every sample."""
    path = source
    t = cols["time_s"]
    if len(t) < 2:
        raise DataError(f"{path}: fewer than two rows of data")
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1  # the row that does not increase
        lines = getattr(cols, "lines", ())  # a run CSV's: rows left out do not shift the number
        line = lines[k] if k < len(lines) else k + 2  # else: the header is line 1, no row left out
        raise DataError(f"{path}: time_s must increase from row to row (line {line} does not)")
    constants = constants or {}
    series = {
        r: (t, np.full(len(t), float(constants[r])) if r in constants else cols[r]) for r in gated_roles(quantity)
    }
    truth = {k: (t, v) for k, v in cols.items() if k.startswith("true_") or k == "operating_h"}
    return series, truth


def as_refs(mapping: Mapping[str, Any] | None) -> dict[str, SignalRef]:
    """Role mapping as SignalRefs (from a config, or (message, signal) pairs; DBC defaults if None)."""
    mapping = mapping if mapping is not None else DEFAULT_INPUTS
    return {r: v if isinstance(v, SignalRef) else SignalRef(*v) for r, v in mapping.items()}


def _affine(db: Database, ref: SignalRef) -> Any:
    return role_affine(db.get_message_by_name(ref.message), ref.signal, ref.scale, ref.offset)


def _messages_of(
    cols: FrameColumns, match: Callable[[Frame], str | None] | None, by_id: Mapping[int, str]
) -> tuple[list[str | None], NDArray[np.int64]]:
    """Which mapped message each frame of a chunk is: the names, and each frame's index into them.
    Matching depends on a frame's channel, identifier, format and FD flag only, so it is asked once
    per distinct combination."""
    key = (
        cols.arbitration_id.astype(np.int64)
        | (cols.extended.astype(np.int64) << 29)
        | (cols.fd.astype(np.int64) << 30)
        | (cols.channel.astype(np.int64) << 31)
    )
    uniq, inv = np.unique(key, return_inverse=True)
    names: list[str | None] = []
    for k in uniq.tolist():
        fid, ext, fd, ch = k & 0x1FFFFFFF, bool(k >> 29 & 1), bool(k >> 30 & 1), k >> 31
        if match is None:
            names.append(None if ext else by_id.get(fid))
        else:
            names.append(match(Frame(0.0, cols.channel_names[ch], fid, ext, False, False, fd, b"")))
    return names, inv.ravel()


def series_from_log(
    path: str | Path,
    db: Database,
    mapping: Mapping[str, Any] | None = None,
    quantity: str = MOTOR_SPEED,
    constants: Mapping[str, float] | None = None,
    match: Callable[[Frame], str | None] | None = None,
    keep_truncated: bool = False,
    on_cut: Callable[[Cut], None] | None = None,
) -> Series:
    """Decode a CAN log into per-role series (vectorized per message), in each role's unit; dp from
    high and low pressure is formed as the monitor forms it; a constant role is its value at the
    output's samples. ``match`` says which mapped message a frame is (the monitor's rules: channels,
    29-bit and J1939 identifiers; see :func:`cmcan.assemble.frame_matcher`); by default a standard
    frame with the message's identifier. A log cut short is refused, or with ``keep_truncated`` read
    up to its last whole frame (the cut handed to ``on_cut``)."""
    from cmcan.io.columns import column_chunks

    refs = as_refs(mapping)
    by_name = {r.message: db.get_message_by_name(r.message) for r in refs.values()}
    by_id = {m.frame_id: name for name, m in by_name.items() if not m.is_extended_frame}
    stamps: dict[str, list[NDArray[np.float64]]] = {n: [] for n in by_name}
    payloads: dict[str, list[NDArray[np.uint8]]] = {n: [] for n in by_name}
    try:
        # the replay's columnar reader: chunks of arrays, the frames of each message by one mask
        for cols in column_chunks(path, keep_truncated=keep_truncated, on_cut=on_cut):
            names, which = _messages_of(cols, match, by_id)
            usable = ~(cols.remote | cols.error)
            for k, name in enumerate(names):
                if name is None:
                    continue
                sel = usable & (which == k) & (cols.dlc >= by_name[name].length)
                if sel.any():
                    stamps[name].append(cols.timestamp_s[sel])
                    payloads[name].append(_payloads(cols, sel, by_name[name].length))
    except FileNotFoundError as exc:
        raise DataError(str(exc), Kind.NO_INPUT) from None
    except (ValueError, OSError) as exc:
        raise DataError(f"{path}: cannot read CAN log: {exc}") from None
    raws: dict[str, tuple[NDArray[np.float64], NDArray[np.int64]]] = {}
    series: Series = {}
    for role, ref in refs.items():
        m = db.get_message_by_name(ref.message)
        if not stamps[m.name]:
            continue
        ts = np.concatenate(stamps[m.name])
        data = np.concatenate(payloads[m.name])
        order = np.argsort(ts, kind="stable")
        raw = codec.decode_raw(m, data[order], [ref.signal])[ref.signal]
        raws[role] = (ts[order], raw)
        f = _affine(db, ref)
        series[role] = (ts[order], codec.as_float(raw) * f.a + f.b)
    if DP not in series and HIGH_PRESSURE in raws and LOW_PRESSURE in raws:
        hl = dp_affine(_affine(db, refs[HIGH_PRESSURE]), _affine(db, refs[LOW_PRESSURE]))
        if hl is None:
            raise DataError(f"{path}: high and low pressure resolutions are not commensurate; map dp_bar", Kind.CONFIG)
        f, p, q = hl
        (t_h, r_h), (t_l, r_l) = raws[HIGH_PRESSURE], raws[LOW_PRESSURE]
        if max(_magnitude(r_h) * p, _magnitude(r_l) * q) >= 1 << 62:  # p r_h - q r_l exact beyond int64 too
            r_h, r_l = r_h.astype(object), r_l.astype(object)
        t, r = dp_raw(t_h, r_h, t_l, r_l, p, q)
        series[DP] = (t, codec.as_float(r) * f.a + f.b)
    constants = constants or {}
    missing = [r for r in gated_roles(quantity) if r not in series and r not in constants]
    if missing:
        expected = sorted({refs[r].message for r in missing if r in refs})
        raise DataError(f"{path}: no frames for {', '.join(missing)} (expected messages {', '.join(expected)})")
    t_out = series[quantity][0]
    for r, v in constants.items():
        series[r] = (t_out, np.full(len(t_out), float(v)))
    return series


def _payloads(cols: FrameColumns, sel: NDArray[np.bool_], length: int) -> NDArray[np.uint8]:
    """The selected frames' payloads, ``length`` bytes each: the columns' first 8 bytes, or for a
    longer (CAN FD) message each whole payload."""
    if length <= 8:
        return cols.data[sel]
    rows = np.flatnonzero(sel)
    out = np.zeros((len(rows), length), dtype=np.uint8)
    for i, r in enumerate(rows.tolist()):
        d = cols.payload(r)[:length]
        out[i, : len(d)] = np.frombuffer(d, dtype=np.uint8)
    return out


def _magnitude(raw: NDArray[Any]) -> int:
    """The largest magnitude of raw values (exact for int64's minimum and for Python ints)."""
    return max((abs(int(raw.min())), abs(int(raw.max()))), default=0) if len(raw) else 0


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
    source: str = "",
) -> OperatingPoints:
    quantity = limits.output_role
    t_out = series[quantity][0]
    spans = contiguous_spans(t_out, max_gap_s=max(limits.window_s, 1.0))
    t_eval = np.concatenate([eval_times(a, b, rate_hz) for a, b in spans]) if spans else np.empty(0)
    roles = gated_roles(quantity)
    stats = window_stats({r: series[r] for r in roles}, t_eval, {r: limits.window_of(r) for r in roles})
    codes = gate(stats, limits, envelope=envelope)
    x = np.column_stack([stats.mean[r] for r in MODEL_INPUTS])
    tr = {}
    for k, (tt, vv) in (truth or {}).items():
        idx = np.clip(np.searchsorted(tt, t_eval, side="right") - 1, 0, len(tt) - 1)
        tr[k] = vv[idx]
    return OperatingPoints(t_eval, x, stats.mean[quantity], codes, stats, tr, float(t_out[0]), quantity, source=source)


def table_points(
    points: Points, limits: GateLimits, envelope: dict[str, tuple[float, float]] | None = None
) -> OperatingPoints:
    """Operating points of a table whose rows are already means, gated by the same rules."""
    quantity = limits.output_role
    means = {r: points.values[r] for r in gated_roles(quantity)}
    stats = table_stats(means)
    n = len(points)
    return OperatingPoints(
        np.arange(n, dtype=np.float64),
        np.column_stack([means[r] for r in MODEL_INPUTS]) if n else np.empty((0, len(MODEL_INPUTS))),
        means[quantity],
        gate(stats, limits, envelope=envelope),
        stats,
        {},
        0.0,
        quantity,
        points.rows,
        points.header,
        points.cells,
        points.source,
    )


def load_operating_points(
    path: str | Path,
    limits: GateLimits,
    db: Database | None = None,
    mapping: Mapping[str, Any] | None = None,
    rate_hz: float = 10.0,
    constants: Mapping[str, float] | None = None,
    envelope: dict[str, tuple[float, float]] | None = None,
    match: Callable[[Frame], str | None] | None = None,
    keep_truncated: bool = False,
    on_cut: Callable[[Cut], None] | None = None,
) -> OperatingPoints:
    """Operating points of a run CSV or a CAN log (chosen by the file's extension); ``envelope``
    marks the points outside it ``EXTRAPOLATED``. ``keep_truncated``, ``on_cut``: for a log cut
    short, as :func:`series_from_log`."""
    p = Path(path)
    if not p.exists():
        raise DataError(f"{p}: file not found", Kind.NO_INPUT)
    q = limits.output_role
    if is_log(p):
        if db is None:
            from cmcan.can.dbccache import load_compiled

            db = load_compiled()
        series = series_from_log(p, db, mapping, q, constants, match, keep_truncated, on_cut)
        return operating_points(series, limits, rate_hz, envelope, source=str(p))
    series, truth = series_from_csv(p, q, constants)
    return operating_points(series, limits, rate_hz, envelope, truth, source=str(p))


@dataclass(frozen=True)
class Refusal:
    gate: Gate
    points: int
    why: str


@dataclass(frozen=True)
class GateReport:
    """How many points each gate refused and why (``cmcan train``'s account of its data)."""

    total: int
    passed: int
    refused: list[Refusal] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "points": self.total,
            "passed": self.passed,
            "refused": {r.gate.name.lower(): {"points": r.points, "why": r.why} for r in self.refused},
        }

    def lines(self) -> list[str]:
        return [f"  {r.points:>8} {r.gate.name.lower():<17} {r.why}" for r in self.refused]


def gate_report(op: OperatingPoints, limits: GateLimits, mask: NDArray[np.bool_] | None = None) -> GateReport:
    """Each refusal with the limit that caused it, over the points in ``mask`` (all by default)."""
    sel = np.ones(len(op), dtype=bool) if mask is None else mask
    codes = op.gate[sel]
    unit = UNITS[op.quantity]
    why = {
        Gate.NO_INPUT: "no input at all (machine off, bus idle)",
        Gate.STALE_INPUT: "some input older than its max_signal_age_s",
        Gate.WARMING_UP: f"fewer than {limits.min_samples} samples of some input in the window",
        Gate.IMPLAUSIBLE_INPUT: "some input missing or outside its plausible range: " + _implausible(op, limits, sel),
        Gate.LOW_SPEED: f"pump speed below {limits.min_pump_speed_rpm:.4g} rpm (gating.min_pump_speed_rpm)",
        Gate.LOW_DISPLACEMENT: f"|pump displacement| below {limits.min_pump_disp_cc:.4g} cm3/rev "
        "(gating.min_pump_disp_cc)",
        Gate.LOW_FLOW: f"{op.quantity} below {limits.min_output:.4g} {unit} (gating.min_"
        + ("motor_speed_rpm or min_flow_lpm)" if op.quantity == MOTOR_SPEED else "flow_lpm)"),
        Gate.TRANSIENT: "not steady: spread within the window above gating.max_std for " + _transient(op, limits, sel),
        Gate.EXTRAPOLATED: "outside the training envelope (evaluated)",
        Gate.REVERSE: f"reverse travel: pump displacement or {op.quantity} negative (the drive is judged forward)",
    }
    refused = []
    for g in Gate:
        n = int(np.sum(codes == g))
        if n and g != Gate.EVALUATING:
            refused.append(Refusal(g, n, why[g]))
    refused.sort(key=lambda r: -r.points)
    return GateReport(len(codes), int(np.sum(codes == Gate.EVALUATING)), refused)


def _transient(op: OperatingPoints, limits: GateLimits, sel: NDArray[np.bool_]) -> str:
    m = sel & (op.gate == Gate.TRANSIENT)
    counts = {r: int(np.sum(op.stats.std[r][m] > lim)) for r, lim in limits.max_std.items() if r in op.stats.std}
    # each role with its limit (scaled for the machine: gating.scaled), as the other refusals say theirs
    return (
        ", ".join(
            f"{r} above {limits.max_std[r]:.4g} {UNITS.get(r, '')} ({n})".replace("  (", " (")
            for r, n in sorted(counts.items(), key=lambda kv: -kv[1])
            if n
        )
        or "-"
    )


def _implausible(op: OperatingPoints, limits: GateLimits, sel: NDArray[np.bool_]) -> str:
    m = sel & (op.gate == Gate.IMPLAUSIBLE_INPUT)
    out = []
    for r, (lo, hi) in limits.plausible.items():
        if r in op.stats.mean:
            n = int(np.sum(outside_plausible(r, op.stats.mean[r][m], limits)))  # signed roles by magnitude
            if n:
                out.append(f"{r} outside [{lo:.4g}, {hi:.4g}] ({n})")
    return ", ".join(out) or "-"
