"""Replay: a CAN log through the monitor core, exactly as the daemon would have processed it.

One driver for both engines: the streaming engine feeds the log frame by frame (``Monitor.feed``,
as the daemon does), the columnar engine in chunks of arrays (``Monitor.feed_columns``); the
monitor's ticks (as a :class:`~cmcan.monitor.tick.TickListener`) and output frames go to sinks in
chunks: the evaluation ticks as columns (:class:`~cmcan.monitor.tick.TickColumns`) and the output
frames. Sinks write files as they go (a timeline CSV, a candump log of the emitted frames) or keep
what they need (a plot's points, a fleet summary), so a replay's memory is bounded by the chunk, not
by the log. A sink writes to a temporary file and renames it only when the replay completes: a
failed replay leaves nothing behind.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np

from cmcan.can.frame import Frame, FrameColumns
from cmcan.errors import CmcanError, Kind
from cmcan.io import native
from cmcan.io import textcols as tc
from cmcan.io.candump import Cut, candump_lines, iter_frames
from cmcan.io.columns import column_chunks
from cmcan.monitor.core import Monitor
from cmcan.monitor.gating import EVALUATED, Gate
from cmcan.monitor.prognosis import DIRECTION_CODES as PROGNOSIS_DIRECTION_CODES
from cmcan.monitor.prognosis import FIELDS as PROGNOSIS_FIELDS
from cmcan.monitor.prognosis import STATE_CODES as PROGNOSIS_STATE_CODES
from cmcan.monitor.tick import LEVEL_NAMES, PROGNOSIS_HOURS, Tick, TickColumns
from cmcan.monitor.warnings import Level, Reason
from cmcan.roles import MOTOR_SPEED, QUANTITY_SIGNALS


def timeline_columns(quantity: str = MOTOR_SPEED, prognosis: bool = False) -> tuple[str, ...]:
    """The timeline CSV's columns; the output quantity's three named as in its CM frame; the
    prognosis's fields (as a tick names them) at the end where it is configured."""
    tail = PROGNOSIS_FIELDS if prognosis else ()
    return ("time_s", "operating_h", "gate", *QUANTITY_SIGNALS[quantity][:3], *_TAIL, *tail)


_TAIL = (
    "cm_ratio_raw_pct",
    "cm_ratio_filt_pct",
    "cm_filt_valid",
    "extra_leak_lpm",
    "warning_level",
    "warning_reason",
    "time_below_threshold_s",
)
TIMELINE_COLUMNS = timeline_columns(MOTOR_SPEED)
CHUNK_TICKS = 8192


class NoFrames(CmcanError, ValueError):
    """A log without a single frame: nothing to replay (the sinks leave nothing behind)."""

    kind = Kind.DATA


class Sink(Protocol):
    wants_ticks: bool
    wants_frames: bool

    def start(self, t0: float) -> None: ...
    def ticks(self, chunk: TickColumns) -> None: ...
    def frames(self, frames: FrameColumns) -> None: ...
    def close(self) -> None: ...
    def abort(self) -> None: ...


class _FileSink:
    """Writes to ``path.tmp`` and renames it over ``path`` on close; abort removes the temporary."""

    wants_ticks = False
    wants_frames = False

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(self.path.name + ".tmp")
        self.f = open(self.tmp, "w", encoding="ascii", newline="\n")  # noqa: SIM115 - closed in close/abort
        self.t0 = 0.0

    def start(self, t0: float) -> None:
        self.t0 = t0

    def ticks(self, chunk: TickColumns) -> None:
        pass

    def frames(self, frames: FrameColumns) -> None:
        pass

    def close(self) -> None:
        self.f.close()
        os.replace(self.tmp, self.path)

    def abort(self) -> None:
        self.f.close()
        self.tmp.unlink(missing_ok=True)


_GATE_NAMES = {int(g): g.name.lower() for g in Gate}
_LEVEL_NAMES = {int(lv): LEVEL_NAMES[lv] for lv in Level}
_REASON_NAMES = {int(r): r.name.lower() for r in Reason}
# The prognosis's codes written by name (the state, the direction), as numbers where one has none; its
# hours with 0.01 h (36 s), inf where the estimate never gets there, empty without one
_PROGNOSIS_NAMES = {
    "prognosis_state": {0: "off", **{code: name for name, code in PROGNOSIS_STATE_CODES.items()}},
    "prognosis_direction": {code: name or "none" for name, code in PROGNOSIS_DIRECTION_CODES.items()},
}
PROGNOSIS_DECIMALS = 2


class TimelineWriter(_FileSink):
    """The timeline CSV (:func:`timeline_columns`), one row per tick."""

    wants_ticks = True

    def __init__(self, path: str | Path, quantity: str = MOTOR_SPEED, prognosis: bool = False) -> None:
        super().__init__(path)
        self.f.write(",".join(timeline_columns(quantity, prognosis)) + "\r\n")
        self.decimals = 2 if quantity == MOTOR_SPEED else 4  # 0.01 rpm; flows of small machines need more
        self.prognosis = PROGNOSIS_FIELDS if prognosis else ()

    def ticks(self, c: TickColumns) -> None:
        # The columns formatted with arrays, byte for byte what f"{x:.3f}" and friends write; what a
        # tick does not have (a prediction and raw ratio where it was not evaluated, the filtered ratio
        # and leakage where the filter is not yet valid) an empty cell
        if not len(c):
            return
        c = _absent_as_nan(c)
        if native.LIB is not None and (text := self._native_rows(c)) is not None:
            self.f.write(text.decode("ascii"))
            return
        d = self.decimals
        comma = b","
        line = tc.rows(
            [
                tc.fixed(c.t_s, 3),
                comma,
                tc.fixed((c.t_run_s - self.t0) / 3600.0, 6),  # operating hours: clock steps undone
                comma,
                tc.Column.of_names(c.gate, _GATE_NAMES),
                comma,
                tc.fixed(c.measured, d),
                comma,
                tc.fixed(c.predicted, d),
                comma,
                tc.fixed(c.whitebox, d),
                comma,
                tc.fixed(c.ratio_raw_pct, 3),
                comma,
                tc.fixed(c.ratio_filt_pct, 3),
                comma,
                tc.integers(c.filt_valid.astype(np.int64)),
                comma,
                tc.fixed(c.extra_leak_lpm, 3),
                comma,
                tc.Column.of_names(c.level, _LEVEL_NAMES),
                comma,
                tc.Column.of_names(c.reason, _REASON_NAMES),
                comma,
                tc.fixed(c.time_below_s, 1),
                *_prognosis_cells(c, self.prognosis),
            ],
            end=b"\r\n",
        )
        self.f.write(line.decode("ascii"))

    def _native_rows(self, c: TickColumns) -> bytes | None:
        """The same rows by the C formatter (which holds no GIL), or None to use the arrays."""
        F, N = native.FIXED, native.NAME
        cols = [
            native.TextColumn(F, c.t_s, decimals=3),
            native.TextColumn(F, (c.t_run_s - self.t0) / 3600.0, b",", 6),
        ]
        for what, codes, names in (("gate", c.gate, _GATE_NAMES), ("level", c.level, _LEVEL_NAMES)):
            named = tc.name_indexes(codes, names)
            if named is None:
                return None
            if what == "gate":
                cols.append(native.TextColumn(N, named[0], b",", names=named[1]))
                d = self.decimals
                cols += [native.TextColumn(F, x, b",", d) for x in (c.measured, c.predicted, c.whitebox)]
                cols += [native.TextColumn(F, x, b",", 3) for x in (c.ratio_raw_pct, c.ratio_filt_pct)]
                cols.append(native.TextColumn(native.INT, c.filt_valid.astype(np.int64), b","))
                cols.append(native.TextColumn(F, c.extra_leak_lpm, b",", 3))
            else:
                cols.append(native.TextColumn(N, named[0], b",", names=named[1]))
        named = tc.name_indexes(c.reason, _REASON_NAMES)
        if named is None:
            return None
        cols.append(native.TextColumn(N, named[0], b",", names=named[1]))
        cols.append(native.TextColumn(F, c.time_below_s, b",", 1))
        progn = _prognosis_native(c, self.prognosis)
        if progn is None:
            return None
        return native.format_rows(len(c), [*cols, *progn], b"\r\n")


def _prognosis_cells(c: TickColumns, fields: Sequence[str]) -> list[tc.Column | bytes]:
    """The prognosis's cells of a stretch of ticks (each after a comma), with arrays."""
    out: list[tc.Column | bytes] = []
    for name in fields:
        v = getattr(c, name)
        if name in PROGNOSIS_HOURS:
            cell = tc.fixed(v, PROGNOSIS_DECIMALS)
        elif name in _PROGNOSIS_NAMES:
            cell = tc.Column.of_names(v, _PROGNOSIS_NAMES[name])
        else:
            cell = tc.integers(v.astype(np.int64))
        out += [b",", cell]
    return out


def _prognosis_native(c: TickColumns, fields: Sequence[str]) -> list[native.TextColumn] | None:
    """The same cells for the C formatter; None where a code has no name (the arrays then write it)."""
    out = []
    for name in fields:
        v = getattr(c, name)
        if name in PROGNOSIS_HOURS:
            out.append(native.TextColumn(native.FIXED, v, b",", PROGNOSIS_DECIMALS))
        elif name in _PROGNOSIS_NAMES:
            named = tc.name_indexes(v, _PROGNOSIS_NAMES[name])
            if named is None:
                return None
            out.append(native.TextColumn(native.NAME, named[0], b",", names=named[1]))
        else:
            out.append(native.TextColumn(native.INT, v.astype(np.int64), b","))
    return out


_EVALUATED = np.array(sorted(int(g) for g in EVALUATED), dtype=np.int8)


def _absent_as_nan(c: TickColumns) -> TickColumns:
    evaluated = np.isin(c.gate, _EVALUATED)
    valid = c.filt_valid
    return replace(
        c,
        predicted=np.where(evaluated, c.predicted, np.nan),
        whitebox=np.where(evaluated, c.whitebox, np.nan),
        ratio_raw_pct=np.where(evaluated, c.ratio_raw_pct, np.nan),
        ratio_filt_pct=np.where(valid, c.ratio_filt_pct, np.nan),
        extra_leak_lpm=np.where(valid, c.extra_leak_lpm, np.nan),
    )


class EmitWriter(_FileSink):
    """The emitted frames as a ``candump -l`` log (written with arrays, as ``candump_line`` writes),
    each on its own channel unless ``channel`` is given."""

    wants_frames = True

    def __init__(self, path: str | Path, channel: str | None = None) -> None:
        super().__init__(path)
        self.channel = channel  # None: each frame on its own channel (can0 when it has none)

    def frames(self, frames: FrameColumns) -> None:
        self.f.write(candump_lines(frames, self.channel))


class SinkThread:
    """Sinks driven from a thread of their own: formatting text and writing files (numpy and I/O,
    which release the GIL) overlap the engine on a second core. Calls are queued in order (at most
    ``depth`` chunks wait); a sink's error is raised in the engine at its next call or at close."""

    def __init__(self, sinks: Sequence[Sink], depth: int = 4) -> None:
        import queue
        import threading

        self.sinks = list(sinks)
        self.wants_ticks = any(s.wants_ticks for s in self.sinks)
        self.wants_frames = any(s.wants_frames for s in self.sinks)
        self._q: queue.Queue[tuple[str, Any] | None] = queue.Queue(maxsize=max(1, depth))
        self._error: BaseException | None = None
        self._worker = threading.Thread(target=self._run, name="cmcan-sinks", daemon=True)
        self._worker.start()

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            if self._error is not None:
                continue  # after a failure: drain without writing
            what, arg = item
            try:
                for s in self.sinks:
                    if what == "start":
                        s.start(arg)
                    elif what == "ticks" and s.wants_ticks:
                        s.ticks(arg)
                    elif what == "frames" and s.wants_frames:
                        s.frames(arg)
            except BaseException as exc:  # raised in the engine's thread
                self._error = exc

    def _put(self, what: str, arg: Any) -> None:
        if self._error is not None:
            raise self._error
        self._q.put((what, arg))

    def _stop(self) -> None:
        if self._worker.is_alive():
            self._q.put(None)
            self._worker.join()

    def start(self, t0: float) -> None:
        self._put("start", t0)

    def ticks(self, chunk: TickColumns) -> None:
        self._put("ticks", chunk)

    def frames(self, frames: FrameColumns) -> None:
        self._put("frames", frames)

    def close(self) -> None:
        self._stop()
        if self._error is not None:
            for s in self.sinks:
                s.abort()
            raise self._error
        for s in self.sinks:
            s.close()

    def abort(self) -> None:
        self._stop()
        for s in self.sinks:
            s.abort()


@dataclass
class TimelineCollector:
    """Keeps every tick (for a plot or a test): memory grows with the log."""

    wants_ticks = True
    wants_frames = False

    chunks: list[TickColumns] = field(default_factory=list)
    t0: float = 0.0

    def start(self, t0: float) -> None:
        self.t0 = t0

    def ticks(self, chunk: TickColumns) -> None:
        self.chunks.append(chunk)

    def frames(self, frames: FrameColumns) -> None:
        pass

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass

    @property
    def timeline(self) -> TickColumns:
        return TickColumns.concat(self.chunks)


@dataclass
class FrameCollector:
    """Keeps every emitted frame."""

    wants_ticks = False
    wants_frames = True

    frames_out: list[Frame] = field(default_factory=list)

    def start(self, t0: float) -> None:
        pass

    def ticks(self, chunk: TickColumns) -> None:
        pass

    def frames(self, frames: FrameColumns) -> None:
        self.frames_out.extend(frames.frames())

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


@dataclass
class ReplaySummary:
    first_t: float | None
    last_t: float | None
    counters: dict[str, int]
    warnings: list[dict[str, Any]]  # level changes, with operating hours since the first frame
    snapshot: dict[str, Any]
    totals: dict[str, Any]
    frames_emitted: int
    run_shift_s: float = 0.0  # the wall clock's steps undone at the last frame (Monitor.run_shift_s)

    @property
    def duration_h(self) -> float:
        """First to last frame in operating hours (the wall clock's steps undone)."""
        if self.first_t is None or self.last_t is None:
            return 0.0
        return (self.last_t + self.run_shift_s - self.first_t) / 3600.0


Item = TypeVar("Item")


def replay(monitor: Monitor, frames_in: Iterable[Frame], sinks: Sequence[Sink] = ()) -> ReplaySummary:
    """The streaming engine: every frame fed to the monitor in log order, one by one, exactly as the
    daemon does."""
    return _drive(monitor, frames_in, monitor.feed, lambda f: (f.timestamp_s, f.timestamp_s), sinks)


def replay_columns(monitor: Monitor, chunks: Iterable[FrameColumns], sinks: Sequence[Sink] = ()) -> ReplaySummary:
    """The columnar engine: chunks of frames fed as arrays; the same ticks, frames and totals as
    :func:`replay` over the same frames one by one."""
    wanted = any(s.wants_frames for s in sinks)

    def feed(cols: FrameColumns) -> FrameColumns | None:
        return monitor.feed_columns(cols, frames=wanted)

    def span(cols: FrameColumns) -> tuple[float, float]:
        return float(cols.timestamp_s[0]), float(cols.timestamp_s[-1])

    return _drive(monitor, (c for c in chunks if len(c)), feed, span, sinks)


def _drive(
    monitor: Monitor,
    items: Iterable[Item],
    feed: Callable[[Item], list[Frame] | FrameColumns | None],
    span: Callable[[Item], tuple[float, float]],
    sinks: Sequence[Sink],
) -> ReplaySummary:
    """Feed every item, the ticks and output frames to the sinks; ``span(item)``: the times of an
    item's first and last frame."""
    out = _Fanout(sinks)
    first = last = None
    monitor.listeners.append(out)
    try:
        item = None
        for item in items:
            if first is None:
                first = span(item)[0]
                for s in sinks:
                    s.start(first)
            out.frames(feed(item))
        if first is None:
            raise NoFrames("no frames in the log")
        last = span(item)[1]  # type: ignore[arg-type]
        out.frames(monitor.flush())
        out.flush()
    except BaseException:
        for s in sinks:
            s.abort()
        raise
    finally:
        monitor.listeners.remove(out)
    for s in sinks:
        s.close()
    return summarize(monitor, first, last, out.n_out)


class _Fanout:
    """What leaves the core in a replay, handed to the sinks that want it: the ticks (it is one of the
    monitor's :class:`~cmcan.monitor.tick.TickListener`: single ticks from the per-frame path gathered
    into columns of up to ``size``, columns from the array path passed on after the single ticks
    before them) and the output frames (lists gathered into columns, columns passed on)."""

    def __init__(self, sinks: Sequence[Sink], size: int = CHUNK_TICKS) -> None:
        self.tick_sinks = [s for s in sinks if s.wants_ticks]
        self.frame_sinks = [s for s in sinks if s.wants_frames]
        self.size = size
        self.pending_ticks: list[Tick] = []
        self.pending_frames: list[Frame] = []
        self.n_out = 0  # output frames handed on

    def tick(self, tick: Tick) -> None:
        if self.tick_sinks:
            self.pending_ticks.append(tick)
            if len(self.pending_ticks) >= self.size:
                self._flush_ticks()

    def ticks(self, chunk: TickColumns) -> None:
        self._flush_ticks()
        for s in self.tick_sinks:
            s.ticks(chunk)

    def frames(self, frames: list[Frame] | FrameColumns | None) -> None:
        if not frames or not self.frame_sinks:
            return
        if isinstance(frames, FrameColumns):
            self._flush_frames()
            self._send(frames)
            return
        self.pending_frames.extend(frames)
        if len(self.pending_frames) >= 3 * self.size:
            self._flush_frames()

    def flush(self) -> None:
        self._flush_ticks()
        self._flush_frames()

    def _flush_ticks(self) -> None:
        if self.pending_ticks:
            chunk = TickColumns.from_ticks(self.pending_ticks)
            self.pending_ticks = []
            for s in self.tick_sinks:
                s.ticks(chunk)

    def _flush_frames(self) -> None:
        if self.pending_frames:
            cols = FrameColumns.from_frames(self.pending_frames)
            self.pending_frames = []
            self._send(cols)

    def _send(self, cols: FrameColumns) -> None:
        self.n_out += len(cols)
        for s in self.frame_sinks:
            s.frames(cols)


def operating(h: dict[str, Any], t0: float) -> dict[str, Any]:
    """A level change with its operating hours since ``t0`` (the first frame), counted on the run's
    continuous time base (a step of the wall clock is no operating time), without that base's time."""
    entry = {k: v for k, v in h.items() if k != "t_run_s"}
    return {**entry, "operating_h": (h.get("t_run_s", h["t_s"]) - t0) / 3600.0}


def summarize(monitor: Monitor, first: float | None, last: float | None, n_out: int) -> ReplaySummary:
    t0 = first if first is not None else 0.0
    return ReplaySummary(
        first_t=first,
        last_t=last,
        counters=dict(monitor.counters),
        warnings=[operating(h, t0) for h in monitor.totals.history],
        snapshot=monitor.snapshot(),
        totals={k: v for k, v in monitor.save_totals().to_dict().items() if not k.startswith("filter_")},
        frames_emitted=n_out,
        run_shift_s=monitor.run_shift_s,
    )


ENGINES = ("columnar", "streaming")


def replay_file(
    path: str | Path,
    monitor: Monitor,
    sinks: Sequence[Sink] = (),
    engine: str = "columnar",
    progress: Callable[[int, int], None] | None = None,
    keep_truncated: bool = False,
    on_cut: Callable[[Cut], None] | None = None,
) -> ReplaySummary:
    """Replay a log file with the chosen engine. Both give the same ticks, frames and summary; the
    columnar engine reads and evaluates the log in large chunks of arrays (its files written from a
    thread of their own while the engine goes on), the streaming engine frame by frame as the
    daemon does. ``progress(bytes of the file read, frames)``: after each chunk (-1 bytes: unknown).
    A log cut short is refused, or with ``keep_truncated`` read up to its last whole frame and the cut
    handed to ``on_cut`` (:mod:`cmcan.io.candump`)."""
    if engine not in ENGINES:
        raise ValueError(f"engine {engine!r} is not one of {', '.join(ENGINES)}")
    cut = {"keep_truncated": keep_truncated, "on_cut": on_cut}
    try:
        if engine == "streaming":
            return replay(monitor, iter_frames(path, **cut), sinks)
        threaded: Sequence[Sink] = [SinkThread(sinks)] if sinks else ()
        return replay_columns(monitor, column_chunks(path, progress=progress, **cut), threaded)
    except NoFrames:
        raise NoFrames(f"{path}: no frames in the log") from None
