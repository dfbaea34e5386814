"""The pure builder of outbox entries: summaries per period, transition events, drop notices, envelope."""

from __future__ import annotations

import json
import math

import hypothesis.strategies as st
import pytest
from hypothesis import given

from cmcan.uplink.records import (
    ENVELOPE_KEYS,
    LEVELS,
    Cumulative,
    Dropped,
    SummaryBuilder,
    TickSample,
    dumps,
    envelope,
    iso_utc,
    new_history,
    transition_entry,
)

T0 = 1_700_000_040.0  # a multiple of 60 s


def tick(t: float, gate: str = "evaluating", level: str = "ok", ratio: float | None = 99.0) -> TickSample:
    return TickSample(
        t_s=t,
        gate=gate,
        level=level,
        reason="none",
        ratio_raw_pct=ratio if gate == "evaluating" else None,
        ratio_filt_pct=ratio,
        extra_leak_lpm=0.5 if ratio is not None else None,
        measured=1000.0,
        predicted=1010.0,
        whitebox=1000.0,
    )


def cum(ticks: int, level_s: dict[str, float], warnings: int = 0) -> Cumulative:
    return Cumulative(dict(level_s), sum(level_s.values()), warnings, 0, {"ticks": ticks, "frames_total": 10 * ticks})


def test_a_tick_in_the_next_period_closes_the_summary_of_the_last():
    b = SummaryBuilder(60.0, cum(0, {}))
    levels = dict.fromkeys(LEVELS, 0.0)
    out = []
    for i in range(0, 1300):  # 130 s of 10 Hz ticks from T0 (a multiple of 60 s)
        t = T0 + i / 10
        levels["low" if i % 4 == 0 else "ok"] += 0.1
        out += b.add(
            tick(t, gate="transient" if i % 5 == 0 else "evaluating", ratio=98.0 + (i % 10) / 10), cum(i + 1, levels)
        )
    out += b.close()
    assert [e.kind for e in out] == ["summary"] * 3
    w = [e.body["window"] for e in out]
    assert [x["start_s"] for x in w] == [T0, T0 + 60, T0 + 120]
    assert [x["closed_by"] for x in w] == ["period", "period", "shutdown"]
    assert [e.body["counters"]["ticks"] for e in out] == [600, 600, 100]
    assert sum(e.body["counters"]["frames_total"] for e in out) == 13000
    assert out[0].t_s == pytest.approx(T0 + 59.9) and out[0].body["window"]["start"] == iso_utc(T0)
    first = out[0].body
    assert first["gate_ticks"] == {"evaluating": 480, "transient": 120}
    assert first["ratio_raw_pct"]["n"] == 480 and first["ratio_raw_pct"]["min"] == 98.1
    assert first["correction_pct"]["mean"] == pytest.approx(1.0)
    assert first["time_in_level_s"]["low"] == pytest.approx(15.0, abs=1e-3)
    assert sum(e.body["time_in_level_s"]["ok"] for e in out) == pytest.approx(levels["ok"], abs=1e-2)
    json.loads(dumps(first))


@given(
    st.lists(
        st.tuples(st.floats(0.01, 400.0), st.sampled_from(["evaluating", "transient", "no_input"])),
        min_size=1,
        max_size=80,
    ),
    st.sampled_from([10.0, 60.0, 900.0]),
)
def test_every_tick_lands_in_exactly_one_summary_in_time_order(steps, every):
    b = SummaryBuilder(every, cum(0, {}))
    t, n, out = T0, 0, []
    for dt, gate in steps:
        t += dt
        n += 1
        out += b.add(tick(t, gate=gate), cum(n, {"ok": n * 0.1}))
    out += b.close()
    assert sum(e.body["window"]["ticks_sampled"] for e in out) == n
    assert sum(e.body["counters"]["ticks"] for e in out) == n
    assert [e.t_s for e in out] == sorted(e.t_s for e in out)
    starts = [e.body["window"]["start_s"] for e in out]
    assert len(set(starts)) == len(starts)
    for e in out:
        w = e.body["window"]
        assert w["start_s"] <= w["first_tick_s"] <= w["last_tick_s"] < w["start_s"] + every
        assert math.isclose(w["start_s"] / every, round(w["start_s"] / every))


def test_a_tick_without_finite_time_is_ignored_and_nothing_without_ticks():
    b = SummaryBuilder(60.0, cum(0, {}))
    assert b.add(tick(math.nan), cum(1, {})) == []
    assert b.close() == []
    with pytest.raises(ValueError):
        SummaryBuilder(0.0, cum(0, {}))


def test_transition_events_and_new_history_survive_trimming():
    hist = [{"t_s": T0 + i, "from": "ok", "to": "low", "reason": "ratio_low", "ratio_filt_pct": 97.5} for i in range(5)]
    assert new_history(hist, None) == hist
    assert new_history(hist, hist[2]) == hist[3:]
    assert new_history(hist, hist[-1]) == []
    seen = hist[3]
    del hist[:2]  # the monitor trims its history from the front
    hist.append({"t_s": T0 + 9, "from": "low", "to": "ok", "reason": "none", "ratio_filt_pct": None})
    assert new_history(hist, seen) == hist[-2:]
    e = transition_entry(hist[-1], warning_count=3, fault_count=1, extra_leak_lpm=float("nan"))
    assert (e.kind, e.t_s) == ("event", T0 + 9)
    assert e.body == {
        "type": "level_change",
        "from": "low",
        "to": "ok",
        "reason": "none",
        "ratio_filt_pct": None,
        "extra_leak_lpm": None,
        "warning_count": 3,
        "fault_count": 1,
    }


def test_dropped_tallies_kinds_times_and_sequence_range():
    d = Dropped("size")
    for seq, kind, t in ((7, "summary", T0 + 5), (3, "summary", T0 + 1), (9, "event", T0 + 9)):
        d.add(kind, t, 100, seq)
    assert d.body() == {
        "reason": "size",
        "entries": 3,
        "bytes": 300,
        "by_kind": {"event": 1, "summary": 2},
        "first_t_s": T0 + 1,
        "last_t_s": T0 + 9,
        "first_seq": 3,
        "last_seq": 9,
    }


@given(
    st.dictionaries(
        st.text(min_size=1, max_size=8).filter(lambda k: k not in ENVELOPE_KEYS),
        st.one_of(st.none(), st.integers(), st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=5)),
        max_size=6,
    ),
    st.integers(1, 10**12),
    st.booleans(),
)
def test_envelope_wraps_any_body_into_valid_json(body, seq, late):
    payload = json.loads(envelope("wl-1", "abc123", seq, "event", T0 + 0.25, late, dumps(body)))
    assert list(payload)[: len(ENVELOPE_KEYS)] == list(ENVELOPE_KEYS)
    assert payload["id"] == f"abc123-{seq}" and payload["seq"] == seq and payload["late"] is late
    assert payload["t"] == "2023-11-14T22:14:00.250Z" and payload["schema"] == 1
    assert {k: payload[k] for k in body} == body


def test_bodies_never_shadow_the_envelope_and_nan_is_refused():
    b = SummaryBuilder(60.0, cum(0, {}))
    b.add(tick(T0), cum(1, {"ok": 0.1}))
    summary = b.close()[0].body
    event = transition_entry({"t_s": T0, "from": "ok", "to": "low", "reason": "ratio_low"}, 1, 0).body
    for body in (summary, event, Dropped("age").body()):
        assert not set(body) & set(ENVELOPE_KEYS)
    with pytest.raises(ValueError):
        dumps({"x": float("nan")})
    with pytest.raises(ValueError):
        envelope("m", "s", 1, "event", T0, False, "[1]")
