"""The send schedule (issue 38, "Real time"): the daemon wakes for the next due output and sends it at
its frame time whether the bus is silent, flooded or full of requests; answers queued with a bound and
a global rate, the node's own DM1 ahead of them. A fake clock and a fake bus drive ``Daemon.run``;
the core's limits are tested on their own (hypothesis where apt)."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.can.j1939 import dm1, ids, transport
from cmcan.can.j1939 import requests as rq
from cmcan.daemon.loop import Daemon, DaemonOptions
from cmcan.monitor.diagnostics import Dm1Params, Dm1Producer
from cmcan.monitor.totals import Totals
from cmcan.monitor.warnings import Level, Reason
from tests.helpers import monitor
from tests.test_monitor_j1939 import j1939_cfg, machine_frames

OFFSET = 1.7e9  # frame (wall) time minus the loop's clock
SA, TOOL = 0x8C, 0xF9
RATIO_PGN = 65312
RIVAL_NAME = 1  # lower than any NAME cmcan has: it wins every contention


class FakeTime:
    def __init__(self) -> None:
        self.t = 1000.0

    def clock(self) -> float:
        return self.t

    def wall(self) -> float:
        return self.t + OFFSET


class TimedBus(can.BusABC):
    """A bus on the fake clock: serves each frame when the clock reaches its time (stamped with the
    wall clock as a kernel bus does), a wait moves the clock on; what the daemon sends is recorded
    with the clock's time. The daemon is stopped once the clock passes ``end``."""

    def __init__(self, ft: FakeTime, frames: list[tuple[float, int, bytes]], end: float) -> None:
        super().__init__(channel="timed")
        self.ft, self.frames, self.end = ft, sorted(frames, key=lambda x: x[0]), end
        self.sent: list[tuple[float, can.Message]] = []
        self.stop: Callable[[], None] = lambda: None
        self.waits: list[float] = []

    def recv(self, timeout: float | None = None) -> can.Message | None:
        ft = self.ft
        if self.frames and self.frames[0][0] <= ft.t:
            at, fid, data = self.frames.pop(0)
            return can.Message(timestamp=at + OFFSET, arbitration_id=fid, data=data, is_extended_id=True)
        self.waits.append(timeout or 0.0)
        nxt = self.frames[0][0] if self.frames else np.inf
        ft.t = min(ft.t + (timeout or 0.0), max(ft.t, nxt))
        if ft.t >= self.end:
            self.stop()
        return None

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append((self.ft.t, msg))

    def _recv_internal(self, timeout):  # pragma: no cover - recv is overridden
        return None, False


def run_daemon(frames: list[tuple[float, int, bytes]], seconds: float, totals: Totals | None = None):
    """The example J1939 machine's daemon on a silent bus (no input frame) for ``seconds`` of the fake
    clock, the node frames ``frames`` (clock time, identifier, data) arriving."""
    ft = FakeTime()
    cfg = j1939_cfg()
    mon = monitor(cfg=cfg, totals=totals)
    bus = TimedBus(ft, [(ft.t + at, fid, data) for at, fid, data in frames], ft.t + seconds)
    opt = DaemonOptions(status_every_s=3600.0)
    d = Daemon(cfg, mon, None, lambda: bus, None, opt, clock=ft.clock, boot_clock=ft.clock, wall_clock=ft.wall)
    bus.stop = d.stop
    d.run()
    return d, bus, ft


def request(sa: int, pgn: int, dest: int = ids.GLOBAL_ADDRESS) -> tuple[int, bytes]:
    return ids.make_id(6, rq.PGN_REQUEST, sa, dest), rq.request_data(pgn)


def _sent(bus: TimedBus, pgn: int, source: int = SA) -> list[tuple[float, can.Message]]:
    return [(t, m) for t, m in bus.sent if ids.pgn(m.arbitration_id) == pgn and m.arbitration_id & 0xFF == source]


def test_a_silent_bus_full_of_requests_keeps_cm_ratio_on_its_period_and_each_frame_on_its_time():
    """Requests every 50 ms and no input frame: the ticks come from the wall clock on time (before, a
    request was taken for an input and held every tick back); every frame leaves at its frame time."""
    kinds = [dm1.PGN_DM1, rq.PGN_DM2, 65262, rq.PGN_ADDRESS_CLAIMED]
    frames = [(0.5 + 0.05 * i, *request(TOOL, kinds[i % 4])) for i in range(int(29.5 / 0.05))]
    d, bus, _ = run_daemon(frames, 30.0)
    ratio = [t for t, _ in _sent(bus, RATIO_PGN)]
    assert len(ratio) >= 270
    assert np.max(np.abs(np.diff(ratio) - 0.1)) < 1e-3, np.diff(ratio)
    late = [t - (m.timestamp - OFFSET) for t, m in bus.sent if m.timestamp]
    assert late and max(late) < 1e-3 and min(late) >= -1e-6  # (float resolution of wall times)
    assert d.stats["internal_errors"] == 0


def test_cannot_claim_answers_a_request_after_its_delay_on_a_quiet_bus():
    """A lower NAME takes cmcan's address; each later Request for Address Claimed is answered with
    Cannot Claim after the NAME's delay (J1939-81: 0 to 153 ms) on a bus where nothing else comes."""
    rival = (ids.make_id(6, rq.PGN_ADDRESS_CLAIMED, SA), RIVAL_NAME.to_bytes(8, "little"))
    asks = [5.0, 7.3, 9.9]
    d, bus, _ = run_daemon([(3.0, *rival), *[(at, *request(TOOL, rq.PGN_ADDRESS_CLAIMED)) for at in asks]], 12.0)
    name = d.monitor.node.claim.name_value.to_bytes(8, "little")
    cannot = [t - 1000.0 for t, m in _sent(bus, rq.PGN_ADDRESS_CLAIMED, ids.NULL_ADDRESS) if bytes(m.data) == name]
    assert len(cannot) == 4  # at the contention, then one per request
    delay = (d.monitor.node.claim.name_value % 256) * 0.0006
    assert np.allclose(np.array(cannot[1:]) - asks, delay, atol=1e-3) and delay <= 0.153


def test_a_flood_of_dm2_requests_from_rotating_addresses_keeps_dm1_and_is_answered_at_the_global_rate():
    """1000 DM2 requests a second from 96 source addresses for 10 s: DM1 (one frame) every second on
    time, the answers (BAM) one session at a time at no more than the global rate, the rest dropped or
    refused and counted in the status."""
    totals = Totals(dtc_occurrences={"520193:2": 1, "520193:12": 2, "520192:17": 1})
    frames = [(2.0 + i / 1000, *request(0x20 + i % 96, rq.PGN_DM2)) for i in range(10_000)]
    d, bus, _ = run_daemon(frames, 15.0, totals)
    dm1s = [t for t, _ in _sent(bus, dm1.PGN_DM1)]
    assert len(dm1s) >= 13 and np.max(np.abs(np.diff(dm1s) - 1.0)) < 1e-3, np.diff(dm1s)
    bams = [
        t
        for t, m in _sent(bus, transport.PGN_TP_CM)
        if m.data[0] == transport.CM_BAM and bytes(m.data[5:8]) == rq.request_data(rq.PGN_DM2)
    ]
    limits = rq.AnswerLimits()
    assert 5 <= len(bams) <= limits.burst + 10 * limits.rate_per_s
    assert min(np.diff(bams)) >= 0.2 - 1e-6  # one BAM at a time: three packets 100 ms apart
    assert bams[-1] - 1000.0 < 13.0  # nothing scheduled long past the flood
    node = d.monitor.snapshot()["j1939_node"]
    assert node["requests_refused_rate"] > 0
    status = d._status_text()
    assert "answers refused" in status and "dropped" in status, status


# -- the core's limits ---------------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(
    gaps=st.lists(st.floats(0.0, 0.2), min_size=1, max_size=300),
    rate=st.floats(0.5, 50.0),
    burst=st.integers(1, 20),
)
def test_the_global_rate_holds_whatever_the_requesters(gaps, rate, burst):
    """In any stretch of frame time w no more than burst + rate x w answers, whatever the source
    addresses; a full bucket answers the first burst at once."""
    lim = rq.RequestLimit(0.3, answers=rq.AnswerLimits(rate_per_s=rate, burst=burst))
    t = np.cumsum(gaps)
    ok = np.array([lim.allow(float(x), i % 250, rq.PGN_DM2) for i, x in enumerate(t)])
    at = t[ok]
    for i in range(len(at)):
        n = np.searchsorted(at, at[i:] + 1e-9, side="right") - i  # answers in [at[i], at[j]]
        assert np.all(n <= burst + rate * (at[i:] - at[i]) + 1e-6)
    assert ok[: min(burst, len(t))].all()
    assert lim.refused_global == int((~ok).sum())


@settings(max_examples=100, deadline=None)
@given(
    events=st.lists(st.tuples(st.integers(1, 12), st.booleans()), min_size=1, max_size=60),
    waiting_max=st.integers(0, 5),
)
def test_answers_wait_with_a_bound_and_never_hold_back_dm1(events, waiting_max):
    """Ticks of 100 ms with a DM1 of one frame each second and requests for DM2 (three DTCs: a BAM) in
    between: DM1 at every due tick, BAMs one at a time, at most ``waiting_max`` waiting, every answer
    sent, waiting or dropped."""
    p = Dm1Params(520192, 520193, 96.0, 104.0, 0.5, 10, SA, answers_waiting_max=waiting_max)
    dm = Dm1Producer(p, Totals(dtc_occurrences={"520193:2": 1, "520193:12": 2, "520192:17": 1}))
    k, frames, asked = 100, [], 0
    for n_ticks, ask in events:
        for _ in range(n_ticks):
            t = k / 10
            frames += dm.step(k, t, Level.OK, Reason.INPUT_STALE, None)
            k += 1
        if ask:
            frames += dm.answer(rq.PGN_DM2, k / 10 - 0.05)
            asked += 1
        assert len(dm.waiting) <= waiting_max
    dm1_t = [f.timestamp_s for f in frames if ids.pgn(f.arbitration_id) == dm1.PGN_DM1]
    assert dm1_t == [x / 10 for x in range(100, k) if x % 10 == 0]
    cms = [f for f in frames if ids.pdu_format(f.arbitration_id) == transport.PGN_TP_CM >> 8]
    starts = [f.timestamp_s for f in cms]
    assert all(b - a >= 0.2 - 1e-9 for a, b in itertools.pairwise(starts))  # one BAM at a time
    assert len(cms) + len(dm.waiting) + dm.dropped == asked


@pytest.fixture(scope="module")
def leak40():
    cfg = j1939_cfg()
    f, _ = machine_frames(cfg, 40.0)
    return cfg, f.to_frames()


@pytest.mark.parametrize("chunk", [97])
def test_a_flood_replays_the_same_in_both_engines_and_ends_with_the_log(leak40, chunk):
    """A replayed leak log with a flood of DM2 requests to all from rotating source addresses (20 a
    second from 0.5 s to 30 s; DM2 of three DTCs: BAM): both engines send the same frames, the answers
    waiting are bounded and none is scheduled past the log's end (before: minutes past it), and DM1
    (one frame, or a BAM with two DTCs) keeps its second."""
    from tests.test_columnar import assert_same
    from tests.test_j1939_node import both, merged, req

    cfg, frames = leak40
    t0, t_end = frames[0].timestamp_s, frames[-1].timestamp_s
    extra = [req(t0 + 0.5 + i / 20, 0x20 + i % 96, 255, rq.PGN_DM2) for i in range(590)]
    totals = Totals(dtc_occurrences={"520193:2": 1, "520193:12": 2, "520193:3": 1})
    a, b = both(cfg, merged(frames, extra), chunk, totals)
    assert_same(a, b)
    out, mon = a[1], a[3]
    mine = [f for f in out if f.extended and f.arbitration_id & 0xFF == SA]
    assert max(f.timestamp_s for f in mine) <= t_end + 1.0
    dm1_sent = [
        f.timestamp_s
        for f in mine
        if ids.pgn(f.arbitration_id) == dm1.PGN_DM1
        or (ids.pgn(f.arbitration_id) == transport.PGN_TP_CM and bytes(f.data[5:8]) == rq.request_data(dm1.PGN_DM1))
    ]
    flood = [t for t in dm1_sent if t0 + 2.0 <= t <= t0 + 30.0]
    assert len(flood) >= 27 and max(np.diff(flood)) <= 1.0 + 1e-6, np.diff(flood)
    dm = mon.dm1_producer
    assert len(dm.waiting) <= dm.p.answers_waiting_max
    assert mon.node.limit.refused_global + dm.dropped > 0


def test_the_answers_section_reaches_the_node_and_dm1():
    """j1939.answers (declared once, in AnswerLimits) reaches the request limit and the DM1 producer."""
    from cmcan import config as cfgmod
    from cmcan.schema import load_yaml
    from tests.test_monitor_j1939 import J1939_YAML

    raw = load_yaml(J1939_YAML)
    raw["j1939"]["answers"] = {"rate_per_s": 2.5, "burst": 3, "waiting_max": 1}
    cfg = cfgmod.from_dict(raw, str(J1939_YAML), J1939_YAML.parent)
    mon = monitor(cfg=cfg)
    assert mon.node.limit.answers == rq.AnswerLimits(2.5, 3, 1) and mon.dm1_producer.p.answers_waiting_max == 1
