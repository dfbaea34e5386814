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


def test_extrapolated_points_raise_a_warning_like_any_evaluated_point():
    a, b = WarningMachine(TH), WarningMachine(TH)
    assert run(a, [97.0] * N_DEBOUNCE, Gate.EXTRAPOLATED) == run(b, [97.0] * N_DEBOUNCE, Gate.EVALUATING)
    assert a.level == Level.LOW and a.reason == Reason.RATIO_LOW


def test_extrapolated_points_cannot_clear_a_warning():
    m = WarningMachine(TH)
    run(m, [97.0] * N_DEBOUNCE, Gate.EXTRAPOLATED)
    assert run(m, [100.0] * (10 * N_DEBOUNCE), Gate.EXTRAPOLATED)[-1] == Level.LOW
    # points inside the envelope clear it after the usual debounce
    levels = run(m, [100.0] * N_DEBOUNCE, Gate.EVALUATING)
    assert levels[-2] == Level.LOW and levels[-1] == Level.OK


def test_an_extrapolated_point_outside_the_band_resets_the_clearing_count():
    m = WarningMachine(TH)
    run(m, [97.0] * N_DEBOUNCE)
    run(m, [100.0] * (N_DEBOUNCE - 1))  # one tick short of clearing
    run(m, [97.5], Gate.EXTRAPOLATED)  # evidence against clearing, even from outside the envelope
    assert run(m, [100.0] * (N_DEBOUNCE - 1))[-1] == Level.LOW
    assert run(m, [100.0])[-1] == Level.OK


def check_envelope_rules(steps: list[tuple[float, bool]]) -> tuple[int, int]:
    """Every return to ok happens on a point inside the envelope, and the first warning comes at the
    same tick as if every point had been inside. Returns how often a warning cleared, and how often
    the all-inside reference cleared where the mixed machine did not (an extrapolated point held it)."""
    m, ref = WarningMachine(TH), WarningMachine(TH)
    first_m = first_ref = None
    cleared = held = 0
    for i, (r, outside) in enumerate(steps):
        g = Gate.EXTRAPOLATED if outside else Gate.EVALUATING
        before, ref_before = m.level, ref.level
        m.step(i * DT, DT, g, r)
        ref.step(i * DT, DT, Gate.EVALUATING, r)
        if before != Level.OK and m.level == Level.OK:
            assert g == Gate.EVALUATING
            cleared += 1
        if ref_before != Level.OK and ref.level == Level.OK and m.level != Level.OK and before != Level.OK:
            held += 1
        if first_m is None and m.level != Level.OK:
            first_m = i
        if first_ref is None and ref.level != Level.OK:
            first_ref = i
    assert first_m == first_ref
    return cleared, held


RATIOS = [97.0, 98.2, 100.0, 101.8, 103.0]


@settings(max_examples=200, deadline=None)
@given(steps=st.lists(st.tuples(st.sampled_from(RATIOS), st.booleans()), min_size=1, max_size=120))
def test_only_trusted_points_clear_and_raising_does_not_depend_on_the_envelope(steps):
    check_envelope_rules(steps)


def test_the_envelope_rules_reach_clearing_and_holding():
    """The property's interesting cases happen: runs of ratios long enough to raise and to clear,
    in- and out-of-envelope stretches mixed."""
    import numpy as np

    rng = np.random.default_rng(12)
    cleared = held = 0
    for _ in range(300):
        steps = []
        while len(steps) < 200:
            run_len = int(rng.integers(1, 2 * N_DEBOUNCE))
            steps += [(float(rng.choice(RATIOS)), bool(rng.random() < 0.5))] * run_len
        c, h = check_envelope_rules(steps)
        cleared, held = cleared + c, held + h
    assert cleared > 20 and held > 20
