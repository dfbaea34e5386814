"""The warning machine over a stretch of ticks (:meth:`WarningMachine.run_columns`, which skips runs of
quiet ticks) leaves it exactly where stepping tick by tick leaves it: same levels, transitions,
warning and fault counts, accumulators, bit for bit."""

import dataclasses

import numpy as np
from hypothesis import event, given, settings
from hypothesis import strategies as st

from cmcan.monitor.gating import Gate
from cmcan.monitor.warnings import Thresholds, WarningMachine, fault_raised, warning_raised

TH = Thresholds(low_pct=98.0, high_pct=102.0, hysteresis_pct=0.5, debounce_s=1.0, fault_after_s=0.5)
DT = 0.1

# ratios on every side of every threshold, and none (NaN)
RATIOS = [float("nan"), 90.0, 97.99, 98.0, 98.2, 98.5, 100.0, 101.5, 101.8, 102.0, 102.01, 110.0]
GATES = [int(g) for g in Gate]


def stepped(m: WarningMachine, gates, ratios):
    out, transitions = [], []
    for i, (g, r) in enumerate(zip(gates.tolist(), ratios.tolist(), strict=True)):
        cb, fb = m.condition, m.fault_reason
        transitions += m.step(i * DT, DT, g, None if r != r else r)
        raised = warning_raised(cb, m.condition)
        out.append((int(m.level), int(m.reason), m.time_below_s, raised, fault_raised(fb, m.fault_reason)))
    return out, transitions


def skipping(m: WarningMachine, gates, ratios):
    """The machine's own run over columns (which skips quiet runs in the ok state), with the ticks
    it skipped counted."""
    skipped = 0
    skip = m.skip

    def counting(g, r, dt):
        nonlocal skipped
        skipped += len(g)
        return skip(g, r, dt)

    m.skip = counting  # type: ignore[method-assign]
    transitions = []
    w = m.run_columns(np.arange(len(gates)) * DT, gates, ratios, DT, (0, 0), transitions.append)
    del m.skip
    wc = np.concatenate([[0], w.warning_count])
    out = [
        (int(lv), int(rs), b, bool(wc[i + 1] - wc[i]), False)
        for i, (lv, rs, b) in enumerate(zip(w.level.tolist(), w.reason.tolist(), w.time_below_s.tolist(), strict=True))
    ]
    faults = np.flatnonzero((w.fault != 0) & (np.concatenate([[0], w.fault[:-1]]) == 0))
    for i in faults.tolist():  # a fault rose at this tick
        out[i] = (*out[i][:4], True)
    assert (w.warnings, w.faults) == (int(wc[-1]), len(faults))
    return out, skipped, transitions


def state(m: WarningMachine):
    return dataclasses.astuple(m)


ticks = st.lists(
    st.tuples(st.sampled_from(GATES + [int(Gate.EVALUATING)] * 6), st.sampled_from(RATIOS)), min_size=1, max_size=150
)


@settings(max_examples=400, deadline=None)
@given(ticks, ticks)
def test_skipping_quiet_ticks_equals_stepping(first, second):
    gates = np.array([g for g, _ in first + second], dtype=np.int8)
    ratios = np.array([r for _, r in first + second])
    a, b = WarningMachine(TH), WarningMachine(TH)
    # the two machines agree on every tick and in every field (bitwise: the floats compare equal)
    want, trs_a = stepped(a, gates, ratios)
    got, skipped, trs_b = skipping(b, gates, ratios)
    assert got == want and trs_a == trs_b
    assert state(a) == state(b)
    event("skipped some ticks" if skipped else "skipped none")
    event("warned" if any(lv in (1, 2) for lv, *_ in want) else "never warned")


def test_the_shortcut_is_taken_and_warnings_still_come():
    # a long healthy stretch, a drop below the threshold for longer than the debounce, a recovery
    n_ok, n_low = 400, 30
    ratios = np.array([100.0] * n_ok + [96.0] * n_low + [100.0] * n_ok)
    gates = np.zeros(len(ratios), dtype=np.int8)
    a, b = WarningMachine(TH), WarningMachine(TH)
    want, _ = stepped(a, gates, ratios)
    got, skipped, _ = skipping(b, gates, ratios)
    assert got == want and state(a) == state(b)
    assert skipped >= n_ok  # the first healthy stretch at least
    assert any(lv == 1 for lv, *_ in got)  # the low warning came


def test_no_skip_without_a_debounce():
    m = WarningMachine(dataclasses.replace(TH, debounce_s=0.0))
    assert not m.can_skip()
