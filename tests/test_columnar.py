"""The columnar replay engine gives what the streaming core gives, byte for byte.

Logs drawn at random from a simulated run and then mangled the ways a real bus and a real logger
mangle them (frames lost, repeated, late, reordered; gaps; the clock stepping back and forward;
unknown identifiers, short frames, values out of range, error and remote frames), replayed by both
engines over small chunks: the same timeline, the same emitted frames, the same summary.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from cmcan import config as cfgmod
from cmcan.assemble import assemble
from cmcan.can.frame import Frame, FrameColumns
from cmcan.io.candump import write_candump
from cmcan.replay import (
    EmitWriter,
    FrameCollector,
    TimelineCollector,
    TimelineWriter,
    replay,
    replay_columns,
    replay_file,
)
from tests.conftest import run_cli
from tests.helpers import as_frames, sim_frames


@pytest.fixture(scope="module")
def base():
    """The excavator-like run of the paper's experiment 2 with its leak early (a low warning in the
    log), 0.12 h: about 4,300 ticks of steady points, transients and low speed."""
    leak = {"type": "leakage", "start_h": 0.03, "extra_lpm": 8.0, "ref_dp_bar": 300}
    _, frames = sim_frames("two_set_validation", duration_h=0.12, events=[leak])
    return as_frames(frames)


@pytest.fixture(scope="module")
def short_base():
    """The same machine with the leak from the start, 0.025 h (about 28,000 frames): the mangled
    logs are about the log's structure, and under :func:`quick` a replay of any slice from its first
    quarter on still reaches the low warning (some 25 s of evaluated operation after its start)."""
    leak = {"type": "leakage", "start_h": 0.002, "extra_lpm": 8.0, "ref_dp_bar": 300}
    _, frames = sim_frames("two_set_validation", duration_h=0.025, events=[leak])
    return as_frames(frames)


def quick() -> cfgmod.Config:
    """The shipped configuration with a shorter filter and debounce (100 samples, 10 s): the warning
    comes within a short log, so each mangled log costs a third of what the shipped one's would."""
    cfg = cfgmod.load()
    return replace(
        cfg,
        thresholds=replace(cfg.thresholds, debounce_s=10.0),
        filter=replace(cfg.filter, samples=100, min_samples=20),
    )


def both(frames: list[Frame], chunk: int | list[int], wrap_model=None, cfg: cfgmod.Config | None = None):
    """Timeline, frames and summary of each engine (fresh monitors, the shipped configuration unless
    ``cfg``; ``wrap_model`` replaces the model by what it makes of it). The columnar engine gets the
    frames in chunks of ``chunk`` frames, or of the given sizes one after the other."""
    cfg = cfg or cfgmod.load()
    out = {}
    for engine in ("streaming", "columnar"):
        mon = assemble(cfg).monitor
        if wrap_model is not None:
            mon.model = wrap_model(mon.model)
        tl, fr = TimelineCollector(), FrameCollector()
        if engine == "streaming":
            s = replay(mon, frames, [tl, fr])
        else:
            sizes = chunk if isinstance(chunk, list) else itertools.repeat(chunk)
            chunks, i = [], 0
            for n in sizes:
                if i >= len(frames):
                    break
                chunks.append(FrameColumns.from_frames(frames[i : i + n]))
                i += n
            s = replay_columns(mon, chunks, [tl, fr])
        out[engine] = (tl.timeline, fr.frames_out, s, mon)
    return out["streaming"], out["columnar"]


def assert_same(a, b) -> None:
    tl_a, fr_a, s_a, m_a = a
    tl_b, fr_b, s_b, m_b = b
    for name in tl_a.__dataclass_fields__:
        x, y = getattr(tl_a, name), getattr(tl_b, name)
        assert np.array_equal(x, y, equal_nan=True), name
    assert fr_a == fr_b
    assert json.dumps(s_a.__dict__, sort_keys=True, default=str) == json.dumps(
        s_b.__dict__, sort_keys=True, default=str
    )
    # and the monitor is left in the same state: a replay could go on from either
    assert m_a.save_totals().to_dict() == m_b.save_totals().to_dict()
    assert m_a.clock.next_k == m_b.clock.next_k and m_a.clock.last_frame_t == m_b.clock.last_frame_t
    for r, w in m_a.windows.windows.items():
        v = m_b.windows.windows[r]
        assert (list(w.ts), list(w.rs), w.s1, w.s2, w.last_t) == (list(v.ts), list(v.rs), v.s1, v.s2, v.last_t), r
    assert m_a.windows.low == m_b.windows.low
    assert (m_a.payloads.alive, m_a.payloads.last_warning) == (m_b.payloads.alive, m_b.payloads.last_warning)
    # the input health of every message stream, and the channels the log's frames were read on
    fields = ("prev", "prev_t", "newest_t", "newest_ok", "timed_out", "counts")
    for x, y in zip(m_a.slots, m_b.slots, strict=True):
        assert [getattr(x.stream, f) for f in fields] == [getattr(y.stream, f) for f in fields], x.spec.name
    assert m_a.router.bad_length == m_b.router.bad_length
    assert m_a.channels_seen() == m_b.channels_seen()


def mangle(frames: list[Frame], draw, rng: np.random.Generator) -> list[Frame]:
    out = list(frames)
    n = len(out)
    ops = draw(
        st.lists(
            st.sampled_from(
                [
                    "drop",
                    "dup",
                    "late",
                    "swap",
                    "gap",
                    "step_back_small",
                    "step_back_big",
                    "step_fwd",
                    "unknown",
                    "short",
                    "range",
                    "error",
                    "remote",
                    "extended",
                    "nan",
                    "burst",
                ]
            ),
            min_size=1,
            max_size=6,
        )
    )
    for op in ops:
        event(op)
        i = int(rng.integers(1, n - 2))
        f = out[i]
        if op == "drop":
            del out[i : i + int(rng.integers(1, 200))]
        elif op == "dup":
            out.insert(i, f)
        elif op == "late":  # a frame from a while ago arrives now
            j = max(0, i - int(rng.integers(1, 400)))
            out.insert(i, out[j])
        elif op == "swap":
            out[i], out[i + 1] = out[i + 1], out[i]
        elif op in ("gap", "step_back_small", "step_back_big", "step_fwd"):
            shift = {
                "gap": 5.0,
                "step_back_small": -float(rng.uniform(0.05, 30)),
                "step_back_big": -200.0,
                "step_fwd": 3600.0,
            }[op]
            out[i:] = [g._replace(timestamp_s=g.timestamp_s + shift) for g in out[i:]]
        elif op == "unknown":
            out.insert(i, f._replace(arbitration_id=0x555))
        elif op == "short":
            out.insert(i, f._replace(data=f.data[:2]))
        elif op == "range":
            out.insert(i, f._replace(data=b"\xff\xff" + f.data[2:]))
        elif op == "error":
            out.insert(i, Frame(f.timestamp_s, f.channel, 0, True, False, True, False, b""))
        elif op == "remote":
            out.insert(i, f._replace(remote=True, data=b""))
        elif op == "extended":
            out.insert(i, f._replace(extended=True))
        elif op == "nan":
            out.insert(i, f._replace(timestamp_s=float("nan")))
        elif op == "burst":  # the same frame many times within one tick
            out[i:i] = [f] * int(rng.integers(2, 30))
        n = len(out)
        if n < 10:
            break
    return out


def check_mangled(base, data, seed, chunk) -> None:
    rng = np.random.default_rng(seed)
    start = int(rng.integers(0, len(base) // 4))
    frames = mangle(base[start:], data.draw, rng)
    event(f"chunks of {chunk} frames" if chunk != "mixed" else "chunks of mixed sizes")
    if chunk == "mixed":  # as a reader's chunks of so many bytes are: from one frame (less than a tick) to thousands
        chunk = np.exp(rng.uniform(0.0, np.log(5000.0), size=len(frames))).astype(int).tolist()
    a, b = both(frames, chunk, cfg=quick())
    assert len(a[0]) > 0  # ticks were evaluated
    event("a warning" if a[2].warnings else "no warning")
    assert_same(a, b)


_MANGLED = {
    "deadline": None,
    "suppress_health_check": [HealthCheck.function_scoped_fixture],
}


@settings(max_examples=15, **_MANGLED)
@given(data=st.data(), seed=st.integers(0, 2**31), chunk=st.sampled_from(["mixed", 997, 4096, 100_000]))
def test_random_mangled_logs_replay_the_same_in_both_engines(short_base, data, seed, chunk):
    check_mangled(short_base, data, seed, chunk)


@pytest.mark.slow
@settings(max_examples=120, **_MANGLED)
@given(data=st.data(), seed=st.integers(0, 2**31), chunk=st.sampled_from(["mixed", 997, 4096, 100_000]))
def test_many_more_mangled_logs_replay_the_same_in_both_engines(short_base, data, seed, chunk):
    check_mangled(short_base, data, seed, chunk)


@pytest.fixture(scope="module")
def base_both(base):
    """Both engines over the clean ``base`` in chunks of 4096 frames, once for the tests that
    compare with it (they only read it)."""
    return both(base, 4096)


def test_a_clean_log_with_a_warning_replays_the_same(base_both):
    a, b = base_both
    assert a[2].warnings and a[2].counters["evaluated"] > 500
    assert_same(a, b)


def test_the_cli_engines_write_identical_files(tmp_path):
    # the run of ``base``: its leak gives a low warning 0.07 h in (the 1.2 h run has it at 1.07 h)
    leak = {"type": "leakage", "start_h": 0.03, "extra_lpm": 8.0, "ref_dp_bar": 300}
    _run, frames = sim_frames("two_set_validation", duration_h=0.12, events=[leak])
    log = tmp_path / "v.log"
    write_candump(log, frames.timestamp_s, frames.arbitration_id, frames.dlc, frames.data)
    outs = {}
    # the columnar engine reads and writes with the C helpers where they were built, and with numpy
    for name, engine, native in (
        ("streaming", "streaming", "1"),
        ("columnar", "columnar", "1"),
        ("numpy", "columnar", "0"),
    ):
        tl, em = tmp_path / f"{name}.csv", tmp_path / f"{name}.emit.log"
        r = run_cli(
            "replay", str(log), "--engine", engine, "--out", str(tl), "--emit", str(em), "--json",
            env={"CMCAN_NATIVE": native},
        )  # fmt: skip
        assert r.returncode == 0, r.stderr
        outs[name] = (tl.read_bytes(), em.read_bytes(), json.loads(r.stdout))
    assert outs["streaming"] == outs["columnar"] == outs["numpy"]
    assert outs["columnar"][2]["warnings"]


@pytest.mark.parametrize("fmt", ["asc", "blf"])
def test_other_formats_through_the_columnar_engine(tmp_path, base, fmt):
    import can

    from cmcan.can.frame import to_message_kwargs

    log = tmp_path / f"b.{fmt}"
    with can.Logger(str(log)) as w:
        for f in base[:20000]:
            w.on_message_received(can.Message(**to_message_kwargs(f)))
    cfg = cfgmod.load()
    res = {}
    for engine in ("streaming", "columnar"):
        fr = FrameCollector()
        s = replay_file(log, assemble(cfg).monitor, [fr], engine=engine)
        res[engine] = (fr.frames_out, s.counters)
    assert res["streaming"] == res["columnar"] and res["columnar"][1]["ticks"] > 100


def test_writers_leave_nothing_behind_when_the_replay_fails(tmp_path):
    bad = tmp_path / "bad.log"
    bad.write_text("(1767225600.000000) can0 100#0011223344556677\nnot a candump line\n")
    tl, em = tmp_path / "tl.csv", tmp_path / "em.log"
    with pytest.raises(ValueError, match="line 2"):
        replay_file(bad, assemble(cfgmod.load()).monitor, [TimelineWriter(tl), EmitWriter(em)])
    assert list(tmp_path.iterdir()) == [bad]


# -- wall-clock steps --------------------------------------------------------------------------------


def stepped(frames: list[Frame], at: float, step_s: float) -> list[Frame]:
    """The log as it comes when the wall clock steps by ``step_s`` after ``at`` of it."""
    cut = frames[0].timestamp_s + at * (frames[-1].timestamp_s - frames[0].timestamp_s)
    return [f._replace(timestamp_s=f.timestamp_s + step_s) if f.timestamp_s >= cut else f for f in frames]


@pytest.mark.parametrize("step_s", [-1.0, -30.0, -59.0, -600.0, 3600.0])
def test_a_wall_clock_step_keeps_the_tick_count_within_one(base, base_both, step_s):
    plain = base_both[0]
    a, b = both(stepped(base, 0.4, step_s), 4096)
    assert_same(a, b)
    assert abs(len(a[0]) - len(plain[0])) <= 1
    # the evaluation goes on through the step: no pause of the ratio
    assert abs(a[2].counters["evaluated"] - plain[2].counters["evaluated"]) <= 20
    assert a[2].counters["clock_steps"] == (1 if step_s < 0 else 0)
    assert a[2].counters["late"] == 0


def test_all_four_steps_in_one_log(base, base_both):
    frames = base
    for at, step in ((0.2, -1.0), (0.4, -30.0), (0.6, -59.0), (0.8, 3600.0)):
        frames = stepped(frames, at, step)
    plain = base_both[0]
    a, b = both(frames, 997)
    assert_same(a, b)
    assert abs(len(a[0]) - len(plain[0])) <= 1
    assert a[2].counters["clock_steps"] == 3 and [w["to"] for w in a[2].warnings] == [
        w["to"] for w in plain[2].warnings
    ]


# -- a model that returns nonsense ------------------------------------------------------------------


class Flaky:
    """The real model, but NaN above 350 bar, 1e30 rpm between 40 and 45 C and negative at low
    displacement: sometimes, in both engines' calls (batched and one by one) alike."""

    def __init__(self, model) -> None:
        self.model = model

    @staticmethod
    def _spoil(x: np.ndarray, p: np.ndarray) -> np.ndarray:
        p = np.where(x[:, 2] > 350.0, np.nan, p)
        p = np.where((x[:, 3] > 40.0) & (x[:, 3] < 45.0), 1e30, p)
        return np.where(x[:, 1] < 35.0, -p, p)

    def predict(self, x):
        p, w = self.model.predict(x)
        return self._spoil(np.atleast_2d(x), p), w

    def predict_one(self, *row):
        p, w = self.model.predict_one(*row)
        return float(self._spoil(np.array([row]), np.array([p]))[0]), w


def test_a_model_returning_nonsense_is_a_model_error_in_both_engines(base):
    from cmcan.monitor.gating import Gate

    a, b = both(base, 997, wrap_model=Flaky)
    assert_same(a, b)
    gates = a[0].gate
    assert (gates == Gate.MODEL_ERROR).sum() == a[2].counters["model_errors"] > 50
    assert (gates == Gate.EVALUATING).sum() > 50  # the rest is evaluated as before
