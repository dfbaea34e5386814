"""Frames a run puts on the bus: each input message at its DBC period, encoded with the DBC.

Through the shipped DBC's mapping by default, or through any machine's (:class:`BusPlan`, built from
a configuration by :func:`cmcan.assemble.bus_plan`): its messages and identifiers (11- or 29-bit),
each message's channel, its alive counter and checksum, J1939's unused bits sent as 1.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can import checksums, codec
from cmcan.can.frame import Frame, FrameColumns
from cmcan.can.j1939 import ids
from cmcan.roles import DEFAULT_INPUTS
from cmcan.sim.run import Run, motor_direction, role_conversion, send_every, send_mask

if TYPE_CHECKING:  # a hint only: cantools imports python-can, which imports asammdf (issue 37)
    from cantools.database.can import Database

# Messages of one controller cycle leave 0.2 ms apart, in identifier order, as a real CAN controller
# would queue them; this also keeps the frame order deterministic.
INTER_FRAME_S = 0.0002


@dataclass(frozen=True)
class BusPlan:
    """How a run's values go on a machine's bus."""

    mapping: dict[str, tuple[Any, ...]]  # role -> (DBC message, signal[, scale, offset]) as run.simulate takes
    channel: dict[str, str] = field(default_factory=dict)  # message -> channel name ("": the default)
    counter: dict[str, str] = field(default_factory=dict)  # message -> its alive counter signal
    checksum: dict[str, tuple[str, str]] = field(default_factory=dict)  # message -> (signal, algorithm)
    fill_unused: bool = False  # J1939: bits no signal occupies are sent as 1


@dataclass(frozen=True)
class Frames:
    """Frames in time order: timestamps (s, epoch), identifiers and data (n, 8) with lengths, whether
    each identifier is 29-bit, and each frame's channel (an index into ``channel_names``)."""

    timestamp_s: NDArray[np.float64]
    arbitration_id: NDArray[np.int64]
    dlc: NDArray[np.int64]
    data: NDArray[np.uint8]
    extended: NDArray[np.bool_] | None = None  # None: all standard
    channel_index: NDArray[np.int64] | None = None  # None: all on channel_names[0]
    channel_names: tuple[str, ...] = ("",)

    def __len__(self) -> int:
        return len(self.timestamp_s)

    def is_extended(self) -> NDArray[np.bool_]:
        return self.extended if self.extended is not None else np.zeros(len(self), dtype=bool)

    def channels(self, default: str = "can0") -> list[str]:
        """Each frame's channel name ("" named ``default``)."""
        names = [n or default for n in self.channel_names]
        if self.channel_index is None:
            return [names[0]] * len(self)
        return [names[i] for i in self.channel_index.tolist()]

    def select(self, rows: NDArray[np.int64] | NDArray[np.bool_] | slice) -> Frames:
        return Frames(
            self.timestamp_s[rows],
            self.arbitration_id[rows],
            self.dlc[rows],
            self.data[rows],
            None if self.extended is None else self.extended[rows],
            None if self.channel_index is None else self.channel_index[rows],
            self.channel_names,
        )

    def to_columns(self, default_channel: str = "can0", chunk: int = 1 << 18) -> list[FrameColumns]:
        """As the columnar replay's chunks of :class:`cmcan.can.frame.FrameColumns` (what a log's reader hands it)."""
        n = len(self)
        names = tuple(c or default_channel for c in self.channel_names)
        code = self.channel_index if self.channel_index is not None else np.zeros(n, dtype=np.int64)
        no = np.zeros(n, dtype=bool)
        cols = FrameColumns(
            timestamp_s=self.timestamp_s.astype(np.float64),
            channel=code.astype(np.int16),
            channel_names=names,
            arbitration_id=self.arbitration_id.astype(np.uint32),
            extended=self.is_extended(),
            remote=no,
            error=no,
            fd=no,
            dlc=self.dlc.astype(np.int16),
            data=self.data.astype(np.uint8),
        )
        return [cols.take(np.arange(i, min(i + chunk, n))) for i in range(0, n, chunk)]

    def to_frames(self, default_channel: str = "can0") -> list[Frame]:
        """As :class:`cmcan.can.frame.Frame` objects (what a bus or a log hands the monitor)."""
        ext = self.is_extended().tolist()
        return [
            Frame(t, ch, i, e, False, False, False, bytes(d[:n]))
            for t, ch, i, e, d, n in zip(
                self.timestamp_s.tolist(),
                self.channels(default_channel),
                self.arbitration_id.tolist(),
                ext,
                self.data,
                self.dlc.tolist(),
                strict=True,
            )
        ]


def frames_from_run(
    run: Run,
    db: Database,
    mapping: dict[str, tuple[Any, ...]] | None = None,
    jitter_ms: float | None = None,
    jitter_seed: int | None = None,
    plan: BusPlan | None = None,
) -> Frames:
    if plan is None:
        plan = BusPlan(mapping if mapping is not None else DEFAULT_INPUTS)
    mapping = plan.mapping
    jitter_ms = run.meta.get("jitter_ms", 0.0) if jitter_ms is None else jitter_ms
    rng = np.random.default_rng(run.meta.get("jitter_seed", 0) if jitter_seed is None else jitter_seed)
    t = run["time_s"]
    dt = 1.0 / run.sample_rate_hz
    bursts = _bursts(t, dt)
    values = dict(run.columns)
    values["motor_direction"] = motor_direction(run["motor_speed_rpm"])

    by_msg: dict[str, dict[str, str]] = {}
    for role, ref in mapping.items():
        if role in values:
            by_msg.setdefault(ref[0], {})[ref[1]] = role
    msgs = sorted((db.get_message_by_name(m) for m in by_msg), key=lambda m: m.frame_id)
    names = tuple(dict.fromkeys(["", *(plan.channel.get(m.name, "") for m in msgs)]))

    ts, ids_, dlcs, datas, exts, chans = [], [], [], [], [], []
    for k, msg in enumerate(msgs):
        every = send_every(msg.cycle_time, dt)
        rows = np.flatnonzero(send_mask(len(t), every, bursts))
        sig_values = {}
        for sig, role in by_msg[msg.name].items():
            scale, offset = role_conversion(mapping[role])
            v = values[role][rows]
            sig_values[sig] = v if scale == 1.0 and offset == 0.0 else (v - offset) / scale
        counter = plan.counter.get(msg.name)
        for sig in msg.signals:  # alive counters count frames of this message
            if (sig.name == counter or sig.name.endswith("counter")) and sig.name not in sig_values:
                # J1939-71: a counter's all-ones value means "not available": it counts 0..2^n - 2
                span = (1 << sig.length) - (1 if plan.fill_unused and sig.length >= 2 else 0)
                sig_values[sig.name] = np.arange(len(rows)) % span
        stamp = run.start_epoch_s + t[rows] + k * INTER_FRAME_S
        if jitter_ms > 0:
            # within 3 sigma, and less than half a period: a cyclic message never overtakes itself
            lim = min(3 * jitter_ms / 1000, 0.45 * every * dt)
            stamp = stamp + np.clip(rng.normal(0, jitter_ms / 1000.0, len(rows)), -lim, lim)
        data = np.zeros((len(rows), 8), dtype=np.uint8)
        data[:, : msg.length] = codec.encode(msg, sig_values, fill_unused=plan.fill_unused)
        fid = np.full(len(rows), msg.frame_id, dtype=np.int64)
        if msg.name in plan.checksum:
            sig, algorithm = plan.checksum[msg.name]
            data = checksums.seal(algorithm, msg.length, codec.layout(msg, sig), fid, data)
        ts.append(stamp)
        ids_.append(fid)
        dlcs.append(np.full(len(rows), msg.length))
        datas.append(data)
        exts.append(np.full(len(rows), bool(msg.is_extended_frame)))
        chans.append(np.full(len(rows), names.index(plan.channel.get(msg.name, ""))))
    stamp = np.concatenate(ts) if ts else np.empty(0)
    order = np.argsort(stamp, kind="stable")
    return Frames(
        stamp[order],
        np.concatenate(ids_)[order] if ids_ else np.empty(0, np.int64),
        np.concatenate(dlcs)[order] if dlcs else np.empty(0, np.int64),
        np.concatenate(datas)[order] if datas else np.empty((0, 8), np.uint8),
        np.concatenate(exts)[order] if exts else np.empty(0, bool),
        np.concatenate(chans)[order] if chans else np.empty(0, np.int64),
        names,
    )


def with_source_address(
    frames: Frames, db: Database, plan: BusPlan, message: str, source: int, from_s: float
) -> Frames:
    """The frames with ``message`` sent from J1939 source address ``source`` from ``from_s`` on (a
    controller that claimed another address), checksums recomputed for the new identifier."""
    msg = db.get_message_by_name(message)
    rows = (frames.arbitration_id == msg.frame_id) & (frames.timestamp_s >= from_s)
    fid = frames.arbitration_id.copy()
    fid[rows] = ids.with_source(fid[rows], source)
    data = frames.data
    if message in plan.checksum:
        sig, algorithm = plan.checksum[message]
        data = data.copy()
        data[rows] = checksums.seal(algorithm, msg.length, codec.layout(msg, sig), fid[rows], data[rows])
    return replace(frames, arbitration_id=fid, data=data)


def _bursts(t: NDArray[np.float64], dt: float) -> list[tuple[int, int]]:
    """Index ranges of gap-free stretches of the time axis (a continuous run is one)."""
    if len(t) == 0:
        return []
    cuts = np.flatnonzero(np.diff(t) > 1.5 * dt) + 1
    edges = [0, *cuts.tolist(), len(t)]
    return list(itertools.pairwise(edges))
