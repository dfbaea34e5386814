"""Replay: a CAN log through the monitor core, exactly as the daemon would have processed it.

The engine feeds the frames and hands what comes out to sinks in chunks: the evaluation ticks as
columns (:class:`TickColumns`) and the output frames. Sinks write files as they go (a timeline CSV,
a candump log of the emitted frames) or keep what they need (a plot's points, a fleet summary), so
a replay's memory is bounded by the chunk, not by the log. A sink writes to a temporary file and
renames it only when the replay completes: a failed replay leaves nothing behind.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cmcan.errors import CmcanError, Kind
from cmcan.frame import Frame, FrameColumns
from cmcan.io import native
from cmcan.io import textcols as tc
from cmcan.monitor.core import Monitor
from cmcan.monitor.gating import Gate
from cmcan.monitor.tick import LEVEL_NAMES, Tick
from cmcan.monitor.warnings import Level, Reason
from cmcan.roles import MOTOR_SPEED, QUANTITY_SIGNALS


def timeline_columns(quantity: str = MOTOR_SPEED) -> tuple[str, ...]:
    """The timeline CSV's columns; the output quantity's three named as in its CM frame."""
    return ("time_s", "operating_h", "gate", *QUANTITY_SIGNALS[quantity][:3], *_TAIL)


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


@dataclass(frozen=True)
class TickColumns:
    """A chunk of evaluation ticks, one array per field of :class:`cmcan.monitor.tick.Tick`."""

    t_s: NDArray[np.float64]
    gate: NDArray[np.int8]
    measured: NDArray[np.float64]  # the output quantity: motor speed (rpm) or flow (l/min)
    predicted: NDArray[np.float64]
    whitebox: NDArray[np.float64]
    ratio_raw_pct: NDArray[np.float64]
    ratio_filt_pct: NDArray[np.float64]
    extra_leak_lpm: NDArray[np.float64]
    filt_valid: NDArray[np.bool_]
    level: NDArray[np.int8]
    reason: NDArray[np.int8]
    time_below_s: NDArray[np.float64]
    # t_s + this: each tick on the run's continuous time base (the wall clock's steps undone); zeros
    # when not given
    run_shift_s: NDArray[np.float64] = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.run_shift_s is None:
            object.__setattr__(self, "run_shift_s", np.zeros(len(self.t_s)))

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def t_run_s(self) -> NDArray[np.float64]:
        """The ticks' times on the run's continuous time base, which operating hours count on."""
        return self.t_s + self.run_shift_s

    @classmethod
    def from_ticks(cls, ticks: Sequence[Tick]) -> TickColumns:
        def col(name: str, dtype: Any) -> NDArray[Any]:
            return np.fromiter((getattr(k, name) for k in ticks), dtype=dtype, count=len(ticks))

        return cls(
            t_s=col("t_s", np.float64),
            gate=col("gate", np.int8),
            measured=col("measured", np.float64),
            predicted=col("predicted", np.float64),
            whitebox=col("whitebox", np.float64),
            ratio_raw_pct=col("ratio_raw_pct", np.float64),
            ratio_filt_pct=col("ratio_filt_pct", np.float64),
            extra_leak_lpm=col("extra_leak_lpm", np.float64),
            filt_valid=col("filt_valid", np.bool_),
            level=col("level", np.int8),
            reason=col("reason", np.int8),
            time_below_s=col("time_below_s", np.float64),
            run_shift_s=col("run_shift_s", np.float64),
        )

    @classmethod
    def concat(cls, chunks: Sequence[TickColumns]) -> TickColumns:
        names = cls.__dataclass_fields__
        if not chunks:
            return cls.from_ticks([])

        return cls(**{n: np.concatenate([getattr(c, n) for c in chunks]) for n in names})


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


class TimelineWriter(_FileSink):
    """The timeline CSV (:func:`timeline_columns`), one row per tick."""

    wants_ticks = True

    def __init__(self, path: str | Path, quantity: str = MOTOR_SPEED) -> None:
        super().__init__(path)
        self.f.write(",".join(timeline_columns(quantity)) + "\r\n")
        self.decimals = 2 if quantity == MOTOR_SPEED else 4  # 0.01 rpm; flows of small machines need more

    def ticks(self, c: TickColumns) -> None:
        # The columns formatted with arrays, byte for byte what f"{x:.3f}" and friends write.
        if not len(c):
            return
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
        return native.format_rows(len(c), cols, b"\r\n")


class EmitWriter(_FileSink):
    """The emitted frames as a ``candump -l`` log (written with arrays, as ``candump_line`` writes),
    each on its own channel unless ``channel`` is given."""

    wants_frames = True

    def __init__(self, path: str | Path, channel: str | None = None) -> None:
        super().__init__(path)
        self.channel = channel  # None: each frame on its own channel (can0 when it has none)

    def frames(self, frames: FrameColumns) -> None:
        from cmcan.io.candump import candump_lines

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


def replay(monitor: Monitor, frames_in: Iterable[Frame], sinks: Sequence[Sink] = ()) -> ReplaySummary:
    """Feed every frame to the monitor in log order (the streaming engine, frame by frame, exactly as
    the daemon does); ticks and emitted frames go to the sinks in chunks."""
    monitor.keep_timeline = any(s.wants_ticks for s in sinks)
    want_frames = any(s.wants_frames for s in sinks)
    feed = monitor.feed
    first = last = None
    out: list[Frame] = []
    n_out = 0
    timeline = monitor.timeline

    def drain() -> None:
        nonlocal n_out
        if timeline:
            chunk = TickColumns.from_ticks(timeline)
            timeline.clear()
            for s in sinks:
                s.ticks(chunk)
        if out:
            n_out += len(out)
            cols = FrameColumns.from_frames(out)
            for s in sinks:
                if s.wants_frames:
                    s.frames(cols)
            out.clear()

    try:
        for f in frames_in:
            t = f.timestamp_s
            if first is None:
                first = t
                for s in sinks:
                    s.start(t)
            last = t
            res = feed(f)
            if res and want_frames:
                out.extend(res)
            if len(timeline) >= CHUNK_TICKS or len(out) >= 3 * CHUNK_TICKS:
                drain()
        if first is None:
            raise NoFrames("no frames in the log")
        tail = monitor.flush()
        if want_frames:
            out.extend(tail)
        drain()
    except BaseException:
        for s in sinks:
            s.abort()
        raise
    for s in sinks:
        s.close()
    return summarize(monitor, first, last, n_out)


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
) -> ReplaySummary:
    """Replay a log file with the chosen engine. Both give the same ticks, frames and summary; the
    columnar engine reads and evaluates the log in large chunks of arrays, the streaming engine
    frame by frame as the daemon does."""
    from cmcan.io.candump import iter_frames

    if engine not in ENGINES:
        raise ValueError(f"engine {engine!r} is not one of {', '.join(ENGINES)}")
    try:
        if engine == "streaming":
            return replay(monitor, iter_frames(path), sinks)
        # progress(bytes of the file read, frames): after each chunk (-1 bytes: unknown)
        from cmcan.columnar import replay_columns
        from cmcan.io.columns import column_chunks

        # the files are written from a thread of their own while the engine goes on
        threaded: Sequence[Sink] = [SinkThread(sinks)] if sinks else ()
        return replay_columns(monitor, column_chunks(path, progress=progress), threaded)
    except NoFrames:
        raise NoFrames(f"{path}: no frames in the log") from None
