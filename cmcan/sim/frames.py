"""Frames a run puts on the bus: each input message at its DBC period, encoded with the DBC."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from cantools.database.can import Database
from numpy.typing import NDArray

from cmcan import codec
from cmcan.roles import DEFAULT_INPUTS
from cmcan.sim.run import Run, motor_direction, send_every, send_mask

# Messages of one controller cycle leave 0.2 ms apart, in identifier order, as a real CAN controller
# would queue them; this also keeps the frame order deterministic.
INTER_FRAME_S = 0.0002


@dataclass(frozen=True)
class Frames:
    """Frames in time order: timestamps (s, epoch), identifiers and data (n, 8) with lengths."""

    timestamp_s: NDArray[np.float64]
    arbitration_id: NDArray[np.int64]
    dlc: NDArray[np.int64]
    data: NDArray[np.uint8]

    def __len__(self) -> int:
        return len(self.timestamp_s)


def frames_from_run(
    run: Run,
    db: Database,
    mapping: dict[str, tuple[str, str]] | None = None,
    jitter_ms: float | None = None,
    jitter_seed: int | None = None,
) -> Frames:
    mapping = mapping if mapping is not None else DEFAULT_INPUTS
    jitter_ms = run.meta.get("jitter_ms", 0.0) if jitter_ms is None else jitter_ms
    rng = np.random.default_rng(run.meta.get("jitter_seed", 0) if jitter_seed is None else jitter_seed)
    t = run["time_s"]
    dt = 1.0 / run.sample_rate_hz
    bursts = _bursts(t, dt)
    values = dict(run.columns)
    values["motor_direction"] = motor_direction(run["motor_speed_rpm"])

    by_msg: dict[str, dict[str, str]] = {}
    for role, (msg_name, sig_name) in mapping.items():
        if role in values:
            by_msg.setdefault(msg_name, {})[sig_name] = role
    msgs = sorted((db.get_message_by_name(m) for m in by_msg), key=lambda m: m.frame_id)

    ts, ids, dlcs, datas = [], [], [], []
    for k, msg in enumerate(msgs):
        rows = np.flatnonzero(send_mask(len(t), send_every(msg.cycle_time, dt), bursts))
        sig_values = {sig: values[role][rows] for sig, role in by_msg[msg.name].items()}
        for sig in msg.signals:  # alive counters count frames of this message
            if sig.name.endswith("counter") and sig.name not in sig_values:
                sig_values[sig.name] = np.arange(len(rows)) % (1 << sig.length)
        stamp = run.start_epoch_s + t[rows] + k * INTER_FRAME_S
        if jitter_ms > 0:
            stamp = stamp + np.clip(
                rng.normal(0, jitter_ms / 1000.0, len(rows)), -3 * jitter_ms / 1000, 3 * jitter_ms / 1000
            )
        data = np.zeros((len(rows), 8), dtype=np.uint8)
        data[:, : msg.length] = codec.encode(msg, sig_values)
        ts.append(stamp)
        ids.append(np.full(len(rows), msg.frame_id))
        dlcs.append(np.full(len(rows), msg.length))
        datas.append(data)
    stamp = np.concatenate(ts) if ts else np.empty(0)
    order = np.argsort(stamp, kind="stable")
    return Frames(
        stamp[order],
        np.concatenate(ids)[order] if ids else np.empty(0, np.int64),
        np.concatenate(dlcs)[order] if dlcs else np.empty(0, np.int64),
        np.concatenate(datas)[order] if datas else np.empty((0, 8), np.uint8),
    )


def _bursts(t: NDArray[np.float64], dt: float) -> list[tuple[int, int]]:
    """Index ranges of gap-free stretches of the time axis (a continuous run is one)."""
    if len(t) == 0:
        return []
    cuts = np.flatnonzero(np.diff(t) > 1.5 * dt) + 1
    edges = [0, *cuts.tolist(), len(t)]
    return list(itertools.pairwise(edges))
