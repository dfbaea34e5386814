"""Skipping quiet ticks (the columnar replay's shortcut) leaves the warning machine exactly where
stepping tick by tick leaves it: same levels, same accumulators, bit for bit."""

import dataclasses

import numpy as np
from hypothesis import event, given, settings
from hypothesis import strategies as st

from cmcan.monitor.gating import Gate
from cmcan.monitor.warnings import Thresholds, WarningMachine

TH = Thresholds(low_pct=98.0, high_pct=102.0, hysteresis_pct=0.5, debounce_s=1.0, fault_after_s=0.5)
DT = 0.1

# ratios on every side of every threshold, and none (NaN)
RATIOS = [float("nan"), 90.0, 97.99, 98.0, 98.2, 98.5, 100.0, 101.5, 101.8, 102.0, 102.01, 110.0]
GATES = [int(g) for g in Gate]


def stepped(m: WarningMachine, gates, ratios):
    out = []
    for i, (g, r) in enumerate(zip(gates.tolist(), ratios.tolist(), strict=True)):
        m.step(i * DT, DT, g, None if r != r else r)
        out.append((int(m.level), int(m.reason), m.time_below_s))
    return out


def skipping(m: WarningMachine, gates, ratios):
    """The columnar engine's loop: quiet runs in the ok state skipped, the rest stepped."""
    n = len(gates)
    quiet = m.quiet(gates, ratios)
    loud = np.append(np.flatnonzero(~quiet), n)
    out = []
    skipped = 0
    i = 0
    while i < n:
        if quiet[i] and m.can_skip():
            j = int(loud[np.searchsorted(loud, i)])
            below = m.skip(gates[i:j], ratios[i:j], DT)
            out += [(int(m.level), int(m.reason), b) for b in below.tolist()]
            skipped += j - i
            i = j
            continue
        r = float(ratios[i])
        m.step(i * DT, DT, int(gates[i]), None if r != r else r)
        out.append((int(m.level), int(m.reason), m.time_below_s))
        i += 1
    return out, skipped


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
    want = stepped(a, gates, ratios)
    got, skipped = skipping(b, gates, ratios)
    assert got == want
    assert state(a) == state(b)
    event("skipped some ticks" if skipped else "skipped none")
    event("warned" if any(lv in (1, 2) for lv, _, _ in want) else "never warned")


def test_the_shortcut_is_taken_and_warnings_still_come():
    # a long healthy stretch, a drop below the threshold for longer than the debounce, a recovery
    n_ok, n_low = 400, 30
    ratios = np.array([100.0] * n_ok + [96.0] * n_low + [100.0] * n_ok)
    gates = np.zeros(len(ratios), dtype=np.int8)
    a, b = WarningMachine(TH), WarningMachine(TH)
    want = stepped(a, gates, ratios)
    got, skipped = skipping(b, gates, ratios)
    assert got == want and state(a) == state(b)
    assert skipped >= n_ok  # the first healthy stretch at least
    assert any(lv == 1 for lv, _, _ in got)  # the low warning came


def test_no_skip_without_a_debounce():
    m = WarningMachine(dataclasses.replace(TH, debounce_s=0.0))
    assert not m.can_skip()
