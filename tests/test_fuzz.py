"""A million fuzzed frames through the daemon on an in-process python-can bus: no crash, no warning, every frame
accounted for in the counters."""

import os
import threading
import time

import can
import numpy as np
import pytest

from cmcan import config as cfgmod
from cmcan.daemon.loop import Daemon, DaemonOptions, bus_kwargs
from cmcan.daemon.preflight import prepare
from cmcan.demo import PlayerBus

pytestmark = pytest.mark.slow

N = 1_000_000
INPUT_IDS = np.array([0x100, 0x101, 0x102, 0x103])


def fuzz_frames(n, seed=7):
    rng = np.random.default_rng(seed)
    kind = rng.choice(6, size=n, p=[0.25, 0.2, 0.3, 0.15, 0.05, 0.05])
    ids = INPUT_IDS[rng.integers(0, 4, n)]
    unknown = rng.integers(0, 0x800, n)
    unknown = np.where(np.isin(unknown, INPUT_IDS), 0x7FF, unknown)
    ids = np.where(kind == 0, unknown, ids)
    payload = rng.integers(0, 256, (n, 8), dtype=np.uint8)
    lengths = np.where(kind == 1, rng.integers(0, 8, n), 8)
    payload[kind == 3, 0:2] = 0xFF  # beyond each input signal's DBC maximum in the first 16 bits
    t = 1767225600.0 + np.arange(n) * 0.0005
    for i in range(n):
        k = int(kind[i])
        yield can.Message(
            timestamp=float(t[i]),
            arbitration_id=int(ids[i]),
            data=bytes(payload[i, : lengths[i]]),
            is_extended_id=False,
            is_remote_frame=k == 4,
            is_error_frame=k == 5,
            dlc=int(lengths[i]),
        )


def test_a_million_fuzzed_frames(tmp_path):
    channel = f"fuzz-{os.getpid()}"
    cfg = cfgmod.with_overrides(cfgmod.load(), interface="virtual", channel=channel, state_dir=str(tmp_path))
    prep = prepare(cfg)
    mon = prep.parts.monitor
    # No kernel filter on an in-process bus: every fuzzed frame reaches the core and must be counted.
    # The bus hands the frames over as the daemon reads them (python-can's virtual bus would spend
    # three quarters of the time copying them through its queue)
    kw = {**bus_kwargs(cfg, cfg.channel_list[0], mon.inputs), "can_filters": None}
    bus = PlayerBus(messages=fuzz_frames(N), **kw)
    daemon = Daemon(cfg, mon, prep.store, lambda: bus, options=DaemonOptions())
    th = threading.Thread(target=daemon.run, daemon=True)
    warn_id = 0x3A2
    try:
        th.start()
        while not bus.played.wait(0.5) and th.is_alive():
            pass
        deadline = time.monotonic() + 120
        while mon.counters["frames_total"] < N and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        daemon.stop()
        th.join(10)
    levels = {m.data[0] for m in bus.sent if m.arbitration_id == warn_id}
    assert not th.is_alive()
    c = mon.counters
    print(c, daemon.stats)
    assert c["frames_total"] == N
    parts = (
        "accepted",
        "unknown_id",
        "bad_length",
        "out_of_range",
        "error_frame",
        "remote_frame",
        "late",
        "checksum",
        "counter_frozen",
        "counter_jump",
    )
    assert sum(c[k] for k in parts) == N
    assert c["unknown_id"] > 0 and c["bad_length"] > 0 and c["out_of_range"] > 0 and c["accepted"] > 0
    assert mon.totals.warning_count == 0
    assert levels and levels <= {0, 3}  # ok, or fault for garbage inputs: never a low or high wear warning
    assert daemon.stats["internal_errors"] == 0
