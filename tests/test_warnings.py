"""The warning state machine: debounce, hysteresis, fault; property tests over random sequences."""

import math

from hypothesis import event, given, settings
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


# Ratios from each region the machine tells apart (below the low threshold, inside its hysteresis,
# inside the band, inside the high hysteresis, above the high threshold), clear of the region's edges
# by more than the jitter, and from anywhere.
ratio = st.one_of(
    st.floats(90.0, 97.9),
    st.floats(98.1, 98.4),
    st.floats(98.6, 101.4),
    st.floats(101.6, 101.9),
    st.floats(102.1, 110.0),
    st.floats(90.0, 110.0),
)
# A run of ticks with one gate (and, when evaluated, ratios around one value), its length on either
# side of the debounce: a sequence raises and clears warnings and faults, not only flickers.
run_ = st.tuples(
    st.sampled_from(
        [
            *(Gate.EVALUATING,) * 6,
            Gate.EXTRAPOLATED,
            *(Gate.TRANSIENT, Gate.LOW_SPEED, Gate.NO_INPUT),
            *(Gate.STALE_INPUT, Gate.IMPLAUSIBLE_INPUT, Gate.MODEL_ERROR),
        ]
    ),
    ratio,
    st.sampled_from([1, 2, N_DEBOUNCE // 2, N_DEBOUNCE - 1, N_DEBOUNCE, N_DEBOUNCE + 1, 2 * N_DEBOUNCE]),
    st.floats(0.0, 0.05),
)
sequences = st.lists(run_, min_size=4, max_size=30).map(
    lambda runs: [
        (g, (r + (-1) ** i * jitter) if g in (Gate.EVALUATING, Gate.EXTRAPOLATED) else None)
        for g, r, n, jitter in runs
        for i in range(n)
    ]
)
FAULT_REASONS = {Gate.STALE_INPUT: Reason.INPUT_STALE, Gate.IMPLAUSIBLE_INPUT: Reason.INPUT_IMPLAUSIBLE}
FAULT_REASONS[Gate.MODEL_ERROR] = Reason.MODEL_ERROR


def check_properties(seq) -> list[str]:
    """The machine's rules over one sequence; returns what happened (for counting)."""
    m = WarningMachine(TH)
    seen = []
    evaluated: list[tuple[float, bool]] = []  # (ratio, inside the envelope) of evaluated ticks, in order
    prev_cond, prev_fault = m.condition, m.fault_reason
    bad_run = 0
    for i, (g, r) in enumerate(seq):
        m.step(i * DT, DT, g, r)
        bad = g in FAULT_REASONS
        bad_run = bad_run + 1 if bad else (bad_run if g == Gate.NO_INPUT else 0)
        if r is not None:
            evaluated.append((r, g == Gate.EVALUATING))
        if m.condition != prev_cond:
            # a condition changes only on an evaluated tick, after a full debounce on the new side
            assert r is not None
            last = [x for x, _ in evaluated[-N_DEBOUNCE:]]
            assert len(last) == N_DEBOUNCE
            if m.condition == Level.LOW:
                assert all(x < TH.low_pct for x in last)
            elif m.condition == Level.HIGH:
                assert all(x > TH.high_pct for x in last)
            else:  # back to ok: on a trusted point, after a debounce of points inside the band
                assert g == Gate.EVALUATING
                band = [(x, inside) for x, inside in evaluated if TH.low_pct + TH.hysteresis_pct <= x]
                assert band and all(
                    TH.low_pct + TH.hysteresis_pct <= x <= TH.high_pct - TH.hysteresis_pct for x in last
                )
            seen.append(f"to_{m.condition.name.lower()}")
            prev_cond = m.condition
        if m.fault_reason != prev_fault:
            if m.fault_reason != Reason.NONE:  # raised after fault_after_s of bad input, by the gate's cause
                assert bad and bad_run * DT >= TH.fault_after_s - 1e-6
                assert m.fault_reason == FAULT_REASONS[g]
                seen.append("fault")
            else:  # cleared after as much good input
                assert not bad and g != Gate.NO_INPUT
                seen.append("fault_cleared")
            prev_fault = m.fault_reason
        if m.level == Level.FAULT:
            assert m.fault_reason in FAULT_REASONS.values()
        assert m.level in (Level.FAULT, m.condition)
    return seen


def test_properties_over_random_sequences():
    """The rules hold over structured random sequences, and the sequences reach what the rules are
    about: warnings raised and cleared, faults raised and cleared (counted, not hoped for)."""
    from collections import Counter

    seen: Counter[str] = Counter()

    @settings(max_examples=300, deadline=None, derandomize=True, database=None)
    @given(sequences)
    def prop(seq):
        what = check_properties(seq)
        for w in set(what):
            event(w)
        seen.update(what)

    prop()
    # (about 100 low, 110 high, 30 back to ok, 320 faults, 260 cleared with hypothesis 6.x)
    assert seen["to_low"] > 30 and seen["to_high"] > 30 and seen["to_ok"] > 10, seen
    assert seen["fault"] > 30 and seen["fault_cleared"] > 30, seen


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
