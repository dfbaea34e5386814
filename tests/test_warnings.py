"""The warning state machine: debounce, hysteresis, fault; property tests over random sequences."""

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.monitor.gating import Gate
from cmcan.monitor.warnings import Level, Reason, Thresholds, WarningMachine

TH = Thresholds(low_pct=98.0, high_pct=102.0, hysteresis_pct=0.5, debounce_s=1.0, fault_after_s=0.5)
DT = 0.1
N_DEBOUNCE = math.ceil(TH.debounce_s / DT - 1e-9)


def run(machine, ratios, gate=Gate.EVALUATING):
    levels = []
    for i, r in enumerate(ratios):
        machine.step(i * DT, DT, gate, r)
        levels.append(machine.level)
    return levels


def test_low_warning_only_after_the_debounce():
    m = WarningMachine(TH)
    levels = run(m, [97.0] * (N_DEBOUNCE + 2))
    assert levels[N_DEBOUNCE - 2] == Level.OK and levels[N_DEBOUNCE - 1] == Level.LOW
    assert m.reason == Reason.RATIO_LOW
    assert m.time_below_s >= TH.debounce_s


def test_a_short_dip_does_not_warn():
    m = WarningMachine(TH)
    assert set(run(m, [97.0] * (N_DEBOUNCE - 1) + [99.0] + [97.0] * (N_DEBOUNCE - 1))) == {Level.OK}


def test_recovery_needs_the_hysteresis_band():
    m = WarningMachine(TH)
    run(m, [97.0] * N_DEBOUNCE)
    assert m.level == Level.LOW
    assert run(m, [98.2] * 50)[-1] == Level.LOW  # above the threshold but inside the hysteresis
    assert run(m, [98.6] * N_DEBOUNCE)[-1] == Level.OK


def test_high_warning_for_misposition_and_direct_low_to_high():
    m = WarningMachine(TH)
    run(m, [97.0] * N_DEBOUNCE)
    assert run(m, [104.0] * N_DEBOUNCE)[-1] == Level.HIGH
    assert m.reason == Reason.RATIO_HIGH


def test_fault_after_stale_inputs_and_back():
    m = WarningMachine(TH)
    n_fault = math.ceil(TH.fault_after_s / DT - 1e-9)
    for i in range(n_fault):
        m.step(i * DT, DT, Gate.STALE_INPUT, None)
    assert m.level == Level.FAULT and m.reason == Reason.INPUT_STALE
    for i in range(n_fault):
        m.step(i * DT, DT, Gate.TRANSIENT, None)
    assert m.level == Level.OK


def test_idle_bus_is_not_a_fault():
    m = WarningMachine(TH)
    for i in range(1000):
        m.step(i * DT, DT, Gate.NO_INPUT, None)
    assert m.level == Level.OK


def test_condition_survives_a_fault():
    m = WarningMachine(TH)
    run(m, [97.0] * N_DEBOUNCE)
    for i in range(10):
        m.step(i * DT, DT, Gate.IMPLAUSIBLE_INPUT, None)
    assert m.level == Level.FAULT and m.condition == Level.LOW
    for i in range(10):
        m.step(i * DT, DT, Gate.LOW_SPEED, None)
    assert m.level == Level.LOW


step = st.one_of(
    st.tuples(st.just(Gate.EVALUATING), st.floats(90.0, 110.0)),
    st.tuples(
        st.sampled_from([Gate.TRANSIENT, Gate.LOW_SPEED, Gate.NO_INPUT, Gate.STALE_INPUT, Gate.IMPLAUSIBLE_INPUT]),
        st.none(),
    ),
)


@settings(max_examples=300, deadline=None)
@given(st.lists(step, max_size=200))
def test_properties_over_random_sequences(seq):
    m = WarningMachine(TH)
    evaluated: list[float] = []  # ratios of evaluated ticks, in order
    prev_cond = m.condition
    bad_run = 0
    for i, (g, r) in enumerate(seq):
        m.step(i * DT, DT, g, r)
        bad_run = (
            bad_run + 1 if g in (Gate.STALE_INPUT, Gate.IMPLAUSIBLE_INPUT) else (bad_run if g == Gate.NO_INPUT else 0)
        )
        if r is not None:
            evaluated.append(r)
        if m.condition != prev_cond:
            # a condition changes only on an evaluated tick, after a full debounce on the new side
            assert r is not None
            last = evaluated[-N_DEBOUNCE:]
            assert len(last) == N_DEBOUNCE
            if m.condition == Level.LOW:
                assert all(x < TH.low_pct for x in last)
            elif m.condition == Level.HIGH:
                assert all(x > TH.high_pct for x in last)
            else:
                assert all(TH.low_pct + TH.hysteresis_pct <= x <= TH.high_pct - TH.hysteresis_pct for x in last)
            prev_cond = m.condition
        if m.level == Level.FAULT:
            assert m.fault_reason in (Reason.INPUT_STALE, Reason.INPUT_IMPLAUSIBLE)
        assert m.level in (Level.FAULT, m.condition)
