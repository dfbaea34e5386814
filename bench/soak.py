"""Soak: the daemon on a full 1 Mbit/s bus for hours of bus time, as fast as it takes the frames.

The drive's own frames (the simulated excavator-like run, about 310 frames/s) with a flood of
unrelated identifiers filling the bus to about 9,000 frames/s (a 1 Mbit/s bus of 8-byte frames),
served to the daemon's own receive loop (:class:`cmcan.daemon.loop.Daemon`: recv, core, send, state
saves) by an in-memory bus: python-can's virtual bus and the kernel's vcan cost more per frame than
the daemon itself, so hours of bus time would take days. No receive filter: every flood frame reaches
the core and is counted there (on a real bus the kernel filter drops them before). The daemon's clock
is the bus's time, so its periodic state saves come at the pace they would on the machine.

Checked, per sample of bus time after the warm-up: resident memory flat (growth below 1 MB per hour of
bus time), CPU per frame flat, every frame counted once in the core's counters, ticks at the
evaluation rate, state saves no more than one per ``state.save_every_s`` plus one per warning change.

    python bench/soak.py --hours 24              # the documented benchmark (about 1 h on one core)
    python bench/soak.py --minutes 15 --json     # tests/test_soak.py (slow tier): about 8 M frames

Prints the figures (and with --json one JSON document); exit 1 when a check fails.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field

import can
import numpy as np

BUS_FPS = 9000.0  # a 1 Mbit/s bus of 8-byte standard frames (about 111 bits each with stuffing)
SAMPLE_EVERY_S = 60.0  # bus time between samples
PAGE = os.sysconf("SC_PAGE_SIZE")


def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE


@dataclass
class Sample:
    bus_s: float  # bus time since the start
    frames: int  # frames served so far
    inputs: int  # of which the drive's own
    rss_mb: float
    cpu_s: float  # process CPU time so far
    saves: int


@dataclass
class Result:
    bus_s: float
    frames: int
    inputs: int
    wall_s: float
    samples: list[Sample] = field(default_factory=list)
    counters: dict[str, int] = field(default_factory=dict)
    stats: dict[str, int] = field(default_factory=dict)
    saves: int = 0
    transitions: int = 0
    checks: dict[str, bool] = field(default_factory=dict)
    figures: dict[str, float] = field(default_factory=dict)


class FloodBus(can.BusABC):
    """The drive's frames in blocks of the simulated run, repeated on a continuous time axis, with
    the flood between them; each frame a reused ``can.Message`` with its time set (the daemon copies
    what it keeps). Served as fast as the daemon asks; ``on_sample`` every SAMPLE_EVERY_S of bus time."""

    def __init__(self, block, flood_fps: float, duration_s: float, on_sample, seed: int = 11) -> None:
        super().__init__(channel="soak")
        self.block_t = block.timestamp_s - block.timestamp_s[0]
        self.block_span = float(self.block_t[-1]) + 0.01
        # each with a float of its own from the start: setting the time later swaps one float for
        # another, so the bus's own memory is flat from the first frame on
        self.block_msgs = [
            can.Message(timestamp=float(t) + 0.5, arbitration_id=int(i), data=bytes(d), is_extended_id=False)
            for t, i, d in zip(self.block_t.tolist(), block.arbitration_id.tolist(), block.data, strict=True)
        ]
        self.t0 = float(block.timestamp_s[0])
        self.flood_fps = flood_fps
        self.duration_s = duration_s
        self.on_sample = on_sample
        rng = np.random.default_rng(seed)
        busy = set(block.arbitration_id.tolist()) | set(range(0x3A0, 0x3B0))
        ids = [i for i in range(0x800) if i not in busy]
        self.flood_msgs = [
            can.Message(timestamp=k + 0.5, arbitration_id=int(rng.choice(ids)), data=rng.bytes(8), is_extended_id=False)
            for k in range(4096)
        ]
        self.sent = 0
        self.served = 0
        self.inputs = 0
        self.now = self.t0  # bus time: the newest frame's
        self.done = threading.Event()
        self._it = self._frames()
        self._next_sample = SAMPLE_EVERY_S

    def _frames(self):
        """One second of bus time at a time (memory stays flat): the block's input frames of that
        second and the flood's, merged by time."""
        rng = np.random.default_rng(5)
        n_block = len(self.block_msgs)
        span = self.block_span
        n_flood = self.flood_fps  # per second, the fraction carried over
        carry = 0.0
        for sec in range(int(np.ceil(self.duration_s))):
            rep, off = divmod(float(sec), span)
            lo = int(np.searchsorted(self.block_t, off, side="left"))
            hi = int(np.searchsorted(self.block_t, off + 1.0, side="left"))
            t_in = self.t0 + rep * span + self.block_t[lo:hi]
            if off + 1.0 > span:  # the second runs past the block's end: the next repetition's start
                k = int(np.searchsorted(self.block_t, off + 1.0 - span, side="left"))
                t_in = np.concatenate([t_in, self.t0 + (rep + 1) * span + self.block_t[:k]])
                idx = np.concatenate([np.arange(lo, hi), np.arange(k)])
            else:
                idx = np.arange(lo, hi)
            carry += n_flood
            nf = int(carry)
            carry -= nf
            t_flood = self.t0 + sec + np.sort(rng.uniform(0.0, 1.0, nf))
            times = np.concatenate([t_in, t_flood])
            which = np.concatenate([idx, n_block + rng.integers(0, len(self.flood_msgs), nf)])
            order = np.argsort(times, kind="stable")
            for t, k in zip(times[order].tolist(), which[order].tolist(), strict=True):
                if t - self.t0 >= self.duration_s:
                    return
                if k < n_block:
                    m = self.block_msgs[k]
                    self.inputs += 1
                else:
                    m = self.flood_msgs[k - n_block]
                m.timestamp = t
                yield m

    def _recv_internal(self, timeout: float | None):
        m = next(self._it, None)
        if m is None:
            self.done.set()
            return None, False
        self.served += 1
        self.now = m.timestamp
        if self.now - self.t0 >= self._next_sample:
            self._next_sample += SAMPLE_EVERY_S
            self.on_sample(self)
        return m, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent += 1


def soak(bus_s: float, flood_fps: float | None = None, warmup_s: float | None = None) -> Result:
    from cmcan import config as cfgmod
    from cmcan.assemble import assemble, dbc_for
    from cmcan.daemon.loop import Daemon, DaemonOptions
    from cmcan.service.statefile import StateStore
    from cmcan.sim import scenario as scn
    from cmcan.sim.frames import frames_from_run
    from cmcan.sim.run import simulate

    cfg = cfgmod.load()
    db = dbc_for(cfg)
    # ten minutes of the excavator-like duty (steady points, transients, low speed), repeated
    block = frames_from_run(simulate(scn.load(scn.shipped("two_set_train")).with_overrides(duration_h=1 / 6), db), db)
    in_fps = len(block.timestamp_s) / (block.timestamp_s[-1] - block.timestamp_s[0])
    flood = BUS_FPS - in_fps if flood_fps is None else flood_fps

    class CountingStore(StateStore):
        saves = 0

        def save(self, totals):
            CountingStore.saves += 1
            super().save(totals)

    samples: list[Sample] = []

    def on_sample(bus: FloodBus) -> None:
        samples.append(
            Sample(
                bus.now - bus.t0, bus.served, bus.inputs, rss_bytes() / 2**20, time.process_time(), CountingStore.saves
            )
        )

    with tempfile.TemporaryDirectory() as state_dir:
        cfg = cfgmod.with_overrides(cfg, state_dir=state_dir)
        mon = assemble(cfg).monitor
        bus = FloodBus(block, flood, bus_s, on_sample)
        clock = lambda: bus.now  # noqa: E731 - the daemon's timers on bus time
        daemon = Daemon(
            cfg,
            mon,
            CountingStore(state_dir),
            lambda: bus,
            options=DaemonOptions(recv_timeout_s=0.0, idle_after_s=3600.0),
            clock=clock,
            boot_clock=clock,
        )
        w0 = time.perf_counter()
        th = threading.Thread(target=daemon.run, daemon=True)
        th.start()
        bus.done.wait()
        daemon.stop()
        th.join(60)
        wall = time.perf_counter() - w0
        on_sample(bus)
    res = Result(bus.now - bus.t0, bus.served, bus.inputs, wall, samples, dict(mon.counters), dict(daemon.stats))
    res.saves = CountingStore.saves
    res.transitions = len(mon.totals.history)
    evaluate(res, cfg.rate_hz, cfg.state.save_every_s, warmup_s)
    return res


def evaluate(res: Result, rate_hz: float, save_every_s: float, warmup_s: float | None) -> None:
    c = res.counters
    parts = ("accepted", "unknown_id", "bad_length", "out_of_range", "error_frame", "remote_frame", "late")
    warm = warmup_s if warmup_s is not None else min(600.0, 0.2 * res.bus_s)
    after = [s for s in res.samples if s.bus_s >= warm]
    hours = np.array([s.bus_s / 3600.0 for s in after])
    rss = np.array([s.rss_mb for s in after])
    slope = float(np.polyfit(hours, rss, 1)[0]) if len(after) >= 3 else float("nan")
    growth = float(rss[-1] - rss[0]) / max(hours[-1] - hours[0], 1e-9) if len(after) >= 2 else float("nan")
    cpu = np.diff([s.cpu_s for s in after]) / np.maximum(np.diff([s.frames for s in after]), 1) * 1e6
    third = max(1, len(cpu) // 3)
    cpu_ratio = float(np.mean(cpu[-third:]) / np.mean(cpu[:third])) if len(cpu) >= 3 else float("nan")
    allowed_saves = int(res.bus_s // save_every_s) + res.transitions + 2
    res.figures = {
        "bus_hours": res.bus_s / 3600.0,
        "frames_million": res.frames / 1e6,
        "bus_frames_per_s": res.frames / max(res.bus_s, 1e-9),
        "speedup_vs_bus": res.bus_s / max(res.wall_s, 1e-9),
        "rss_start_mb": after[0].rss_mb if after else float("nan"),
        "rss_end_mb": after[-1].rss_mb if after else float("nan"),
        "rss_slope_mb_per_bus_h": slope,
        "rss_growth_mb_per_bus_h": growth,
        "cpu_us_per_frame_first": float(np.mean(cpu[:third])) if len(cpu) else float("nan"),
        "cpu_us_per_frame_last": float(np.mean(cpu[-third:])) if len(cpu) else float("nan"),
        "cpu_per_frame_last_over_first": cpu_ratio,
        "saves": res.saves,
        "saves_allowed": allowed_saves,
    }
    res.checks = {
        "every frame counted once": c["frames_total"] == res.frames and sum(c[k] for k in parts) == res.frames,
        "inputs accepted, flood counted as unknown": c["accepted"] == res.inputs
        and c["unknown_id"] == res.frames - res.inputs,
        "ticks at the evaluation rate": abs(c["ticks"] - res.bus_s * rate_hz) <= 2 + res.bus_s * rate_hz * 1e-4,
        "evaluated the drive": c["evaluated"] > 0.2 * c["ticks"],
        "no internal error": res.stats.get("internal_errors", 1) == 0,
        "RSS flat (< 1 MB per bus hour)": bool(slope < 1.0 and growth < 1.0),
        "CPU per frame flat (last third within 1.5x of the first)": bool(cpu_ratio < 1.5),
        "state saves bounded": 0 < res.saves <= allowed_saves,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--hours", type=float, help="hours of bus time (default 24)")
    g.add_argument("--minutes", type=float, help="minutes of bus time")
    ap.add_argument("--flood-fps", type=float, help="unrelated frames per second of bus time (default: fill 9,000/s)")
    ap.add_argument("--json", action="store_true", help="print the result as JSON")
    args = ap.parse_args()
    bus_s = args.minutes * 60 if args.minutes else (args.hours or 24.0) * 3600
    res = soak(bus_s, args.flood_fps)
    if args.json:
        json.dump(asdict(res), sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        f = res.figures
        print(
            f"bus time {f['bus_hours']:.2f} h, {f['frames_million']:.1f} M frames ({f['bus_frames_per_s']:.0f}/s of "
            f"bus time, {res.inputs / 1e6:.2f} M of them the drive's), {res.wall_s:.0f} s wall "
            f"({f['speedup_vs_bus']:.1f}x bus time)"
        )
        print(
            f"RSS {f['rss_start_mb']:.1f} -> {f['rss_end_mb']:.1f} MB after warm-up: slope "
            f"{f['rss_slope_mb_per_bus_h']:+.3f} MB per bus hour (end-to-end {f['rss_growth_mb_per_bus_h']:+.3f})"
        )
        print(
            f"CPU per frame {f['cpu_us_per_frame_first']:.2f} us (first third) -> {f['cpu_us_per_frame_last']:.2f} us "
            f"(last third), ratio {f['cpu_per_frame_last_over_first']:.3f}"
        )
        print(
            f"state saves {res.saves} (allowed {f['saves_allowed']}: one per save_every_s of bus time plus one per "
            f"warning change, {res.transitions} changes); ticks {res.counters['ticks']}, "
            f"evaluated {res.counters['evaluated']}"
        )
        for name, ok in res.checks.items():
            print(f"  {'ok  ' if ok else 'FAIL'} {name}")
    return 0 if all(res.checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
