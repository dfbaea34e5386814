"""Prognostics metrics over one run's estimates against its true end of life.

The standard offline metrics of Saxena et al. ("Metrics for offline evaluation of prognostic
performance", IJPHM 2010), as NASA's progpy computes them (``progpy.metrics``; a test holds these
equal to progpy's on random profiles), plus what a workshop booking asks of an estimate:

- an estimate at operating hour ``t_i`` gives the hours left to end of life as p10 / p50 / p90; the
  truth is ``RUL*_i = eol_h - t_i``; a point estimate is its p50;
- **alpha-lambda**: at ``t_lambda = t_P + lambda (eol_h - t_P)`` (``t_P`` the first estimate), the
  first estimate at or after it within ``alpha`` of ``RUL*`` (bounds never narrower than ``floor_h``:
  the history's resolution); no estimate then is a miss;
- **relative accuracy** of an estimate: ``1 - |RUL* - RUL| / RUL*``;
- **prognostic horizon**: ``eol_h - t_i`` of the first estimate within the alpha bounds (progpy's
  ``prognostic_horizon``), and the stricter one a user relies on, from which *every* later estimate
  stays within them;
- **coverage**: the share of estimates whose p10-p90 holds ``RUL*``;
- **late**: the estimate in force ``before_h`` hours before end of life (the newest one by then)
  promises more than ``(1 + share) RUL*`` hours: the workshop would be booked too late.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Estimate:
    at_h: float  # operating hour of the estimate
    p10: float  # hours left to end of life
    p50: float
    p90: float


def within(rul: float, true_rul: float, alpha: float, floor_h: float = 0.0) -> bool:
    return abs(rul - true_rul) <= max(alpha * true_rul, floor_h)


def _before(est: Sequence[Estimate], eol_h: float) -> list[Estimate]:
    return [e for e in est if e.at_h < eol_h]


def at_lambda(est: Sequence[Estimate], eol_h: float, lam: float) -> Estimate | None:
    """The estimate alpha-lambda judges: the first at or after ``t_lambda`` (None: none by then)."""
    est = _before(est, eol_h)
    if not est:
        return None
    t_l = est[0].at_h + lam * (eol_h - est[0].at_h)
    return next((e for e in est if e.at_h >= t_l), None)


def alpha_lambda(est: Sequence[Estimate], eol_h: float, lam: float, alpha: float, floor_h: float = 0.0) -> bool:
    e = at_lambda(est, eol_h, lam)
    return e is not None and within(e.p50, eol_h - e.at_h, alpha, floor_h)


def relative_accuracy(e: Estimate, eol_h: float) -> float:
    true_rul = eol_h - e.at_h
    return 1.0 - abs(true_rul - e.p50) / true_rul


def horizon_first(est: Sequence[Estimate], eol_h: float, alpha: float, floor_h: float = 0.0) -> float:
    """Hours before end of life of the first estimate within the bounds (0: none)."""
    for e in _before(est, eol_h):
        if within(e.p50, eol_h - e.at_h, alpha, floor_h):
            return eol_h - e.at_h
    return 0.0


def horizon_stays(est: Sequence[Estimate], eol_h: float, alpha: float, floor_h: float = 0.0) -> float:
    """Hours before end of life from which every estimate is within the bounds (0: the last is not)."""
    est = _before(est, eol_h)
    i = len(est)
    while i > 0 and within(est[i - 1].p50, eol_h - est[i - 1].at_h, alpha, floor_h):
        i -= 1
    return eol_h - est[i].at_h if i < len(est) else 0.0


def coverage(est: Sequence[Estimate], eol_h: float) -> tuple[int, int]:
    """(estimates whose p10-p90 holds the truth, estimates)."""
    est = _before(est, eol_h)
    return sum(1 for e in est if e.p10 <= eol_h - e.at_h <= e.p90), len(est)


def in_force(est: Sequence[Estimate], at_h: float) -> Estimate | None:
    """The newest estimate at or before ``at_h``."""
    return next((e for e in reversed(est) if e.at_h <= at_h), None)


def lateness(est: Sequence[Estimate], eol_h: float, before_h: float, share: float = 0.2) -> str:
    """``late`` (p50 above (1 + share) RUL*), ``ok`` or ``none`` (no estimate then) ``before_h`` before
    end of life."""
    e = in_force(est, eol_h - before_h)
    if e is None:
        return "none"
    return "late" if e.p50 > (1.0 + share) * (eol_h - e.at_h) else "ok"


def main() -> None:
    """Score the estimates ``bench_prognosis.py --dump FILE`` wrote, run by run."""
    import argparse
    import json

    ap = argparse.ArgumentParser(description="Score a prognosis dump (bench_prognosis.py --dump FILE) run by run.")
    ap.add_argument("dump", help="the JSON file bench_prognosis.py --dump wrote")
    ap.add_argument("--alpha", type=float, default=0.2, help="alpha bounds (share of the true hours left)")
    args = ap.parse_args()
    with open(args.dump, encoding="utf-8") as f:
        runs = json.load(f)
    print(
        f"{'case':10} {'al@0.5':>6} {'al@0.75':>7} {'PH_first':>8} {'PH_stays':>8} {'cover':>7} {'@20h':>5} {'@10h':>5}"
    )
    for run in runs:
        eol = run["fail_h"]
        if eol is None:
            continue
        est = [Estimate(h, p10, p50, p90) for h, _state, p10, p50, p90 in run["estimates"]]
        c, n = coverage(est, eol)
        al5, al75 = (alpha_lambda(est, eol, lam, args.alpha) for lam in (0.5, 0.75))
        print(
            f"{run['case']:10} {al5!s:>6} {al75!s:>7}"
            f" {horizon_first(est, eol, args.alpha):8.1f} {horizon_stays(est, eol, args.alpha):8.1f} {c:3d}/{n:<3d}"
            f" {lateness(est, eol, 20.0):>5} {lateness(est, eol, 10.0):>5}"
        )


if __name__ == "__main__":
    main()
