"""Both replay engines on the machine buses of issue 11: the J1939 machine (29-bit identifiers matched
on PGN, TSC1 counters and checksums, a sender changing its address, DM1 over BAM), the same machine
without DM1 (the columnar engine's array path for the checks), two channels, CAN FD frames, and
counters broken the ways a real bus breaks them. The same timeline, frames, summary and state."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from cmcan import config as cfgmod
from cmcan.assemble import assemble, bus_plan, dbc_for
from cmcan.can.checksums import byte_sums
from cmcan.can.frame import Frame, FrameColumns
from cmcan.can.j1939 import ids
from cmcan.io.candump import iter_frames, write_frames
from cmcan.io.candump_columns import iter_candump_columns
from cmcan.monitor.core import Monitor
from cmcan.monitor.diagnostics import Dm1Producer
from cmcan.monitor.health import Stream
from cmcan.replay import FrameCollector, TimelineCollector, replay, replay_columns
from cmcan.sim import scenario as scn
from cmcan.sim.frames import frames_from_run, with_source_address
from cmcan.sim.run import simulate
from tests.test_columnar import assert_same
from tests.test_monitor_j1939 import freeze_counter, j1939_cfg, machine_frames


def both(cfg: cfgmod.Config, frames: list[Frame], chunk: int):
    out = {}
    for engine in ("streaming", "columnar"):
        mon = assemble(cfg).monitor
        tl, fr = TimelineCollector(), FrameCollector()
        if engine == "streaming":
            s = replay(mon, frames, [tl, fr])
        else:
            chunks = [FrameColumns.from_frames(frames[i : i + chunk]) for i in range(0, len(frames), chunk)]
            s = replay_columns(mon, chunks, [tl, fr])
        out[engine] = (tl.timeline, fr.frames_out, s, mon)
    return out["streaming"], out["columnar"]


def no_dm1(cfg: cfgmod.Config) -> cfgmod.Config:
    return replace(cfg, j1939=replace(cfg.j1939, dm1=replace(cfg.j1939.dm1, enabled=False)))


@pytest.fixture(scope="module")
def j1939():
    """40 s of the J1939 machine with a leak, HST_MOTOR's counter frozen from 25 s on (DM1 over BAM),
    the sender moving from address 0x03 to 0x04 at 30 s."""
    cfg = j1939_cfg()
    frames, plan = machine_frames(cfg, 40.0)
    t0 = float(frames.timestamp_s[0])
    frames = freeze_counter(frames, cfg, plan, "HST_MOTOR", t0 + 25.0)
    db = dbc_for(cfg)
    for name in ("HST_PUMP", "HST_MOTOR", "HST_LOOP_PRESSURE"):
        frames = with_source_address(frames, db, plan, name, 0x04, t0 + 30.0)
    return cfg, frames.to_frames()


@pytest.mark.parametrize("dm1", [True, False])
@pytest.mark.parametrize("chunk", [333, 100_000])
def test_the_j1939_machine_replays_the_same(j1939, dm1, chunk):
    cfg, frames = j1939
    cfg = cfg if dm1 else no_dm1(cfg)
    a, b = both(cfg, frames, chunk)
    assert_same(a, b)
    counters = a[2].counters
    assert counters["counter_frozen"] > 0 and counters["accepted"] > 0
    if dm1:
        assert any(f.arbitration_id & 0x00FF0000 == 0x00EC0000 for f in a[1])  # a BAM announcement


def test_the_j1939_machine_with_dm1_takes_the_array_path(j1939, monkeypatch):
    """DM1 (single frames and BAM) is stepped alongside the ticks of a stretch: only irregular frames
    (the first, a sender's new address, the frozen counter's edges) go through the core one by one."""
    cfg, frames = j1939
    fed = []
    feed = Monitor.feed
    monkeypatch.setattr(Monitor, "feed", lambda self, f: fed.append(f) or feed(self, f))
    mon = assemble(cfg).monitor
    fr = FrameCollector()
    replay_columns(mon, [FrameColumns.from_frames(frames)], [fr])
    assert any(f.arbitration_id & 0x00FF0000 == 0x00EC0000 for f in fr.frames_out)  # BAM went out
    assert len(fed) < 0.01 * len(frames), f"{len(fed)} of {len(frames)} frames through the streaming core"


def _frames_of_every_kind(rng: np.random.Generator, n: int) -> list[Frame]:
    out = []
    for i in range(n):
        k = int(rng.integers(4))
        data = bytes(rng.integers(0, 256, int(rng.integers(9, 65)) if k == 3 else int(rng.integers(0, 9)), np.uint8))
        out.append(
            Frame(
                float(i) / 10,
                ("can0", "can1", "vcan2")[k % 3],
                int(rng.integers(1 << 29)),
                k > 0,
                False,
                False,
                k == 3,
                data,
            )
        )
    return out


def test_frame_columns_concat_and_take_keep_every_field():
    """Concatenated pieces with their own channel names, and rows taken in any order (CAN FD
    payloads beyond 8 bytes included), are the frames they were made of."""
    rng = np.random.default_rng(3)
    frames = _frames_of_every_kind(rng, 300)
    cuts = [0, 17, 18, 150, 300]
    parts = [FrameColumns.from_frames(frames[a:b]) for a, b in itertools.pairwise(cuts)]
    whole = FrameColumns.concat(parts)
    assert any(p.channel_names != whole.channel_names for p in parts)  # codes had to be mapped
    assert whole.long_data  # FD payloads beyond 8 bytes
    assert whole.frames() == frames
    order = rng.permutation(len(frames))
    assert whole.take(order).frames() == [frames[i] for i in order]
    assert whole.take(order[:0]).frames() == []


def test_byte_sums_match_numpys_reduction():
    rng = np.random.default_rng(7)
    data = rng.integers(0, 256, (5000, 8), dtype=np.uint8)
    data[:10] = 0xFF  # the largest sums: no carry may leave a lane
    assert np.array_equal(byte_sums(data.view("<u8")[:, 0]), data.sum(axis=1))
    ids = rng.integers(0, 1 << 29, 5000).astype(np.uint32)
    assert np.array_equal(byte_sums(ids), ids.view(np.uint8).reshape(-1, 4).sum(axis=1))


@pytest.mark.parametrize("chunk", [333, 100_000])
def test_a_quiet_dm1_is_resent_without_stepping_and_replays_the_same(chunk, monkeypatch):
    """A healthy drive: every second a single DM1 frame, the all-zero DTC, then the stale-input DTC
    while the motor's message is silent for 8 s, then the all-zero DTC again. The columnar engine
    resends the cached frame for runs of due ticks with nothing changed instead of stepping the
    producer at each (as the producer's own fast path would send it), with the same output."""
    cfg = j1939_cfg()
    frames = machine_frames(cfg, 60.0, leak_lpm=0.0)[0].to_frames()
    pgn = ids.pgn(dbc_for(cfg).get_message_by_name("HST_MOTOR").frame_id)
    t0 = frames[0].timestamp_s
    frames = [f for f in frames if not (ids.pgn(f.arbitration_id) == pgn and t0 + 20 <= f.timestamp_s < t0 + 28)]
    a, b = both(cfg, frames, chunk)
    assert_same(a, b)
    singles = [f for f in b[1] if f.arbitration_id & 0x00FFFF00 == 0x00FECA00]
    assert len(singles) >= 55
    payloads = [f.data for f in singles]
    changes = sum(x != y for x, y in itertools.pairwise(payloads))
    assert changes >= 2 and payloads[0] == payloads[-1], payloads  # on, then off again
    steps = []
    step = Dm1Producer.step
    monkeypatch.setattr(Dm1Producer, "step", lambda self, *a: steps.append(a[0]) or step(self, *a))
    chunks = [FrameColumns.from_frames(frames[i : i + chunk]) for i in range(0, len(frames), chunk)]
    replay_columns(assemble(cfg).monitor, chunks)
    assert len(steps) < len(singles) / 3, (len(steps), len(singles))


def corrupt(frames: list[Frame], rng: np.random.Generator, share: float) -> list[Frame]:
    """Bytes flipped in some frames (a bad checksum, a counter out of step, a value out of range)."""
    out = []
    for f in frames:
        if rng.random() < share and f.data:
            d = bytearray(f.data)
            d[int(rng.integers(len(d)))] ^= int(rng.integers(1, 256))
            f = f._replace(data=bytes(d))
        out.append(f)
    return out


@pytest.fixture(scope="module")
def shipped():
    """72 s of the shipped 11-bit machine, simulated once for every example."""
    from tests.helpers import as_frames, sim_frames

    _, sim = sim_frames("two_set_validation", duration_h=0.02)
    return as_frames(sim)


_SETTINGS = {"deadline": None, "suppress_health_check": [HealthCheck.function_scoped_fixture, HealthCheck.too_slow]}


@settings(max_examples=12, **_SETTINGS)
@given(
    seed=st.integers(0, 2**31),
    share=st.sampled_from([0.001, 0.01, 0.1]),
    chunk=st.sampled_from([97, 4096]),
    dm1=st.booleans(),
)
def test_corrupted_j1939_frames_replay_the_same(j1939, seed, share, chunk, dm1):
    cfg, frames = j1939
    cfg = cfg if dm1 else no_dm1(cfg)
    a, b = both(cfg, corrupt(frames, np.random.default_rng(seed), share), chunk)
    assert_same(a, b)
    c = a[2].counters
    for k in ("checksum", "counter_jump", "counter_frozen", "out_of_range"):
        if c[k]:
            event(f"reached {k}")


@settings(max_examples=12, **_SETTINGS)
@given(seed=st.integers(0, 2**31), share=st.sampled_from([0.002, 0.02, 0.2]), chunk=st.sampled_from([97, 4096]))
def test_corrupted_and_dropped_frames_on_the_shipped_machine_replay_the_same(shipped, seed, share, chunk):
    """The shipped 11-bit machine checks its alive counters: lost frames (jumps), repeated frames
    (frozen), flipped bytes, and a message silent long enough to time out."""
    rng = np.random.default_rng(seed)
    frames = shipped  # a new list is made of it below, it stays as it is
    keep = rng.random(len(frames)) > share  # lost frames
    frames = [f for f, k in zip(frames, keep, strict=True) if k]
    dup = [f for f in frames if rng.random() < share]  # repeated ones, right after themselves
    frames = sorted(frames + dup, key=lambda f: f.timestamp_s)
    # one message silent for two seconds in the middle: it times out while the others go on
    t_mid = frames[len(frames) // 2].timestamp_s
    frames = [f for f in frames if not (f.arbitration_id == 0x101 and t_mid <= f.timestamp_s < t_mid + 2.0)]
    a, b = both(cfgmod.load(), corrupt(frames, rng, share), chunk)
    assert_same(a, b)
    counts = a[3].snapshot()["inputs"]
    assert sum(v["timeout"] for v in counts.values()) > 0
    assert a[2].counters["timeout"] == sum(v["timeout"] for v in counts.values())  # the monitor's total
    for k in ("counter_jump", "counter_frozen", "out_of_range"):
        if a[2].counters[k]:
            event(f"reached {k}")


def crc8_machine(tmp_path) -> cfgmod.Config:
    """The shipped 11-bit machine with a CRC-8/SAE-J1850 byte in each input message (byte 7, beside the
    alive counter; Motorola in one message)."""
    base = cfgmod.load()
    text = base.dbc_path.read_text()
    for counter, sig in (
        ("pump_status_counter", ' SG_ pump_crc : 48|8@1+ (1,0) [0|255] "" CMCAN'),
        ("pressure_status_counter", ' SG_ pressure_crc : 48|8@1+ (1,0) [0|255] "" CMCAN'),
        ("motor_status_counter", ' SG_ motor_crc : 39|8@0+ (1,0) [0|255] "" CMCAN'),
        ("oil_status_counter", ' SG_ oil_crc : 48|8@1+ (1,0) [0|255] "" CMCAN'),
    ):
        line = next(x for x in text.splitlines() if x.startswith(f" SG_ {counter} "))
        text = text.replace(line, f"{line}\n{sig}")
    dbc = tmp_path / "crc8.dbc"
    dbc.write_text(text)
    names = ("PUMP_STATUS", "LOOP_PRESSURE", "MOTOR_STATUS", "OIL_STATUS")
    return replace(base, dbc_path=dbc, messages={n: cfgmod.MessageConfig(checksum="crc8_sae_j1850") for n in names})


def test_a_machine_with_crc8_checksums_replays_the_same_through_the_array_path(tmp_path, monkeypatch):
    """CRC-8 checks in the columnar engine are array operations (``checksums.crc8_ok``), not the
    stream's per-frame check: the same verdicts on corrupted frames, and no frame checked one by one."""
    cfg = crc8_machine(tmp_path)
    db = dbc_for(cfg)
    plan = bus_plan(cfg, db)
    assert set(plan.checksum) == {"PUMP_STATUS", "LOOP_PRESSURE", "MOTOR_STATUS", "OIL_STATUS"}
    s = scn.load(scn.shipped("two_set_validation")).with_overrides(duration_h=0.01)
    frames = frames_from_run(simulate(s, db, plan.mapping), db, plan=plan).to_frames()
    frames = corrupt(frames, np.random.default_rng(5), 0.02)
    a, b = both(cfg, frames, 5000)
    assert_same(a, b)
    c = a[2].counters
    assert c["checksum"] > 0.01 * len(frames) and c["accepted"] > 0.9 * len(frames), c
    checked = []
    check = Stream.check
    monkeypatch.setattr(Stream, "check", lambda self, *a: checked.append(a) or check(self, *a))
    chunks = [FrameColumns.from_frames(frames[i : i + 5000]) for i in range(0, len(frames), 5000)]
    replay_columns(assemble(cfg).monitor, chunks)
    assert len(checked) < 0.01 * len(frames)  # the irregular frames the core takes one by one


def padded_fd(frames: list[Frame], seed: int, pad: bytes) -> list[Frame]:
    """Every frame as CAN FD; some 5 % padded beyond 8 bytes (a gateway that pads to a DLC step)."""
    rng = np.random.default_rng(seed)
    return [f._replace(fd=True, data=f.data + pad if rng.random() < 0.05 else f.data) for f in frames]


@pytest.mark.parametrize("pad", [bytes(4), b"\x01\x02\x03\x04"])
def test_fd_frames_longer_than_8_bytes_replay_the_same(tmp_path, pad):
    """CAN FD frames longer than their 8-byte message: values, CRC-8 and counters are read from their
    first bytes by both engines (a longer frame's first 8 bytes are in FrameColumns.data too), from
    frames in memory and from a candump log through the array reader."""
    cfg = crc8_machine(tmp_path)
    cfg = replace(cfg, frames=replace(cfg.frames, fd=True))
    db = dbc_for(cfg)
    plan = bus_plan(cfg, db)
    s = scn.load(scn.shipped("two_set_validation")).with_overrides(duration_h=0.005)
    frames = padded_fd(frames_from_run(simulate(s, db, plan.mapping), db, plan=plan).to_frames(), 0, pad)
    assert sum(len(f.data) > 8 for f in frames) > 100
    a, b = both(cfg, frames, 100_000)
    assert_same(a, b)
    assert a[2].counters["checksum"] == 0 and a[2].counters["accepted"] > 0.9 * len(frames)
    log = tmp_path / "fd.log"
    write_frames(log, frames)
    out = []
    for engine in ("streaming", "columnar"):
        mon = assemble(cfg).monitor
        tl, fr = TimelineCollector(), FrameCollector()
        if engine == "streaming":
            s_log = replay(mon, list(iter_frames(log)), [tl, fr])
        else:
            s_log = replay_columns(mon, iter_candump_columns(log), [tl, fr])
        out.append((tl.timeline, fr.frames_out, s_log, mon))
    assert_same(*out)


@pytest.mark.parametrize("pad", [b"\xaa" * 4, b"\xff" * 8, b"\xcc" * 56])
def test_j1939_checksums_of_fd_frames_padded_beyond_8_bytes(j1939, pad):
    """The TSC1 checksum covers the 8-byte message: a CAN FD frame padded to 12, 16 or 64 bytes (0xAA
    as FD controllers pad, or anything else) is checked on its first 8 bytes by both engines. It was
    summed over the padding: rejected, or past the checksum table (an IndexError, exit 70)."""
    cfg, frames = j1939
    cfg = replace(cfg, frames=replace(cfg.frames, fd=True))
    fd = padded_fd(frames, 1, pad)
    assert sum(len(f.data) > 8 for f in fd) > 50
    a, b = both(cfg, fd, 1000)
    assert_same(a, b)
    plain = both(cfg, [f._replace(fd=True) for f in frames], 1000)[0]
    assert a[2].counters == plain[2].counters  # padding changes nothing: the same frames accepted, rejected
    # and a byte changed under the padding fails as it does without the padding
    bad = [f._replace(data=bytes([f.data[0] ^ 0x10]) + f.data[1:]) if len(f.data) > 8 else f for f in fd]
    a, b = both(cfg, bad, 1000)
    assert_same(a, b)
    unpadded = [f._replace(data=f.data[:8]) for f in bad]
    assert a[2].counters == both(cfg, unpadded, 1000)[0][2].counters
    assert a[2].counters["checksum"] > 0


def test_two_channels_replay_the_same():
    base = cfgmod.load()
    cfg = replace(
        base,
        channels=replace(base.channels, extra=(cfgmod.ChannelConfig("can1"),)),
        messages={n: cfgmod.MessageConfig(channel="can1") for n in ("MOTOR_STATUS", "OIL_STATUS")},
    )
    db = dbc_for(cfg)
    plan = bus_plan(cfg, db)
    s = scn.load(scn.shipped("two_set_validation")).with_overrides(duration_h=0.02)
    frames = frames_from_run(simulate(s, db, plan.mapping), db, plan=plan).to_frames()
    assert {f.channel for f in frames} == {"can0", "can1"}
    # a third channel nobody configured, and CAN FD frames on the classic bus: counted the same
    extra = [f._replace(channel="can7") for f in frames[:200]] + [f._replace(fd=True) for f in frames[200:400]]
    frames = sorted(frames + extra, key=lambda f: f.timestamp_s)
    for chunk in (211, 50_000):
        a, b = both(cfg, frames, chunk)
        assert_same(a, b)
    c = a[2].counters
    assert c["unknown_channel"] == 200 and c["bad_fd"] == 200
