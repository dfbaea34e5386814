"""Trailing-window statistics of a role's samples: the one definition, streaming and batched.

A role's samples are exact integers (the raw values a frame carries, or a difference of two of them)
with an affine map to the role's unit: value = raw * a + b. A window's mean and spread follow from
the exact integer sums S1 = sum(raw) and S2 = sum(raw^2):

    mean = (S1 / n) * a + b        std = |a| * sqrt(n S2 - S1^2) / n

The monitor keeps the sums as samples come and go (:class:`RoleWindow`); a batched reader computes
them from cumulative sums (:func:`window_sums`). Integer sums are exact, and the few floating-point
operations after them are the same in both, so both give the same bits: a replay over arrays and the
daemon frame by frame evaluate the very same operating points.

:class:`Windows` is the monitor's stage: every role's window, where each decoded value of an input
message goes (a role's window; high and low pressure into dp = high - low, formed at each
high-pressure sample with the newest low-pressure sample), and the roles the machine holds constant.
Frame by frame it adds samples (:meth:`Windows.adder`) and gives a tick's statistics
(:meth:`Windows.stats`); over a stretch of frames it gathers the samples as arrays
(:meth:`Windows.stretch`), gives every tick's statistics from prefix sums and leaves the windows as
the frames one by one would (:meth:`Stretch.commit`).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.can.codec import layout
from cmcan.roles import DP, HIGH_PRESSURE, LOW_PRESSURE

# Timestamps come from logs with microsecond resolution and from floats near 1.7e9 s (one ulp is
# 0.24 us): a sample within half a microsecond of a tick or a window edge counts as on it, so the
# same log gives the same windows whatever its format's time base.
TIME_EPS_S = 5e-7


@dataclass(frozen=True)
class Affine:
    """value = raw * a + b."""

    a: float = 1.0
    b: float = 0.0

    def mean(self, s1: int, n: int) -> float:
        return (s1 / n) * self.a + self.b

    def std(self, s1: int, s2: int, n: int) -> float:
        num = n * s2 - s1 * s1
        return abs(self.a) * math.sqrt(float(num)) / n if num > 0 else 0.0


class RoleWindow:
    """One role's samples in arrival order, with running exact sums; trimmed from the front."""

    __slots__ = ("last_t", "rs", "s1", "s2", "ts")

    def __init__(self) -> None:
        self.ts: deque[float] = deque()
        self.rs: deque[int] = deque()
        self.s1 = 0
        self.s2 = 0
        self.last_t = -math.inf

    def add(self, t: float, raw: int) -> None:
        self.ts.append(t)
        self.rs.append(raw)
        self.s1 += raw
        self.s2 += raw * raw
        if t > self.last_t:
            self.last_t = t

    def shift(self, delta_s: float) -> None:
        """The samples moved onto a time base ``delta_s`` later (a wall-clock step)."""
        self.ts = deque(t + delta_s for t in self.ts)
        self.last_t += delta_s

    def clear(self) -> None:
        self.ts.clear()
        self.rs.clear()
        self.s1 = self.s2 = 0
        self.last_t = -math.inf

    def trim(self, t_end: float, window_s: float) -> int:
        """Drop samples at or before t_end - window_s (from the front); the count left."""
        ts, rs = self.ts, self.rs
        cut = t_end - window_s + TIME_EPS_S
        while ts and ts[0] <= cut:
            ts.popleft()
            r = rs.popleft()
            self.s1 -= r
            self.s2 -= r * r
        return len(rs)

    def stats(self, t_end: float, window_s: float, f: Affine) -> tuple[float, float, int]:
        n = self.trim(t_end, window_s)
        if n == 0:
            return math.nan, math.nan, 0
        return f.mean(self.s1, n), f.std(self.s1, self.s2, n), n


def running_max(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``np.maximum.accumulate(x)``; ``x`` itself when it never falls (the usual log: in time order),
    which is checked faster than the running maximum is made."""
    if len(x) < 2 or (x[1:] >= x[:-1]).all():
        return x
    return np.maximum.accumulate(x)


def window_sums(
    ts: NDArray[np.float64], raw: NDArray[np.int64] | NDArray[np.float64], t_eval: NDArray[np.float64], window_s: float
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """For time-sorted samples: (S1, S2, n, time of the newest sample) of the window
    ``t - window_s < ts <= t`` at each evaluation time (-inf where nothing came before). Exact for
    integer raw values; for floats, centre them first."""
    hi = np.searchsorted(ts, t_eval + TIME_EPS_S, side="right")
    lo = np.searchsorted(ts, t_eval - window_s + TIME_EPS_S, side="right")
    c1 = np.concatenate([np.zeros(1, raw.dtype), np.cumsum(raw)])
    c2 = np.concatenate([np.zeros(1, raw.dtype), np.cumsum(raw * raw)])
    newest = np.where(hi > 0, ts[np.maximum(hi - 1, 0)] if len(ts) else 0.0, -np.inf)
    return c1[hi] - c1[lo], c2[hi] - c2[lo], hi - lo, newest


def mean_std(
    s1: NDArray[np.int64], s2: NDArray[np.int64], n: NDArray[np.int64], f: Affine
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:meth:`Affine.mean` and :meth:`Affine.std` over arrays (NaN where a window is empty)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (s1.astype(np.float64) / n) * f.a + f.b
        num = n * s2 - s1 * s1
        std = np.where(num > 0, abs(f.a) * np.sqrt(np.maximum(num, 0).astype(np.float64)) / n, 0.0)
    return np.where(n > 0, mean, np.nan), np.where(n > 0, std, np.nan)


def role_affine(msg: Any, signal: str, scale: float = 1.0, offset: float = 0.0) -> Affine:
    """A role's value from its DBC signal's raw value: (raw * s_dbc + o_dbc) * scale + offset."""
    lay = layout(msg, signal)
    return Affine(lay.scale * scale, lay.offset * scale + offset)


def dp_affine(high: Affine, low: Affine) -> tuple[Affine, int, int] | None:
    """dp = high - low as ``Affine`` over raw_dp = p * raw_high - q * raw_low, or None when the two
    resolutions are not in a small integer ratio."""
    pq = commensurate(high.a, low.a)
    if pq is None:
        return None
    p, q, step = pq
    return Affine(step, high.b - low.b), p, q


def dp_raw(
    t_high: NDArray[np.float64],
    raw_high: NDArray[np.int64],
    t_low: NDArray[np.float64],
    raw_low: NDArray[np.int64],
    p: int,
    q: int,
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """dp samples at the high-pressure samples with the newest low-pressure sample at or before
    each (time-sorted inputs), as the monitor forms them frame by frame."""
    idx = np.searchsorted(t_low, t_high, side="right") - 1
    keep = idx >= 0
    return t_high[keep], p * raw_high[keep] - q * raw_low[idx[keep]]


def commensurate(a_high: float, a_low: float, max_den: int = 1000) -> tuple[int, int, float] | None:
    """Integers (p, q) and a step c with a_high = p c and a_low = q c, when the two resolutions
    are in a small ratio: then high - low = c (p r_high - q r_low) + const is exact in integers."""
    if a_high == 0 or a_low == 0:
        return None
    from fractions import Fraction

    ratio = Fraction(a_high / a_low).limit_denominator(max_den)
    if abs(float(ratio) - a_high / a_low) > 1e-12 * abs(a_high / a_low):
        return None
    p, q = ratio.numerator, ratio.denominator
    return p, q, a_high / p


# -- the monitor's stage ------------------------------------------------------------------------------

# What each decoded value of an input message does.
WINDOW, HIGH, LOW, IGNORED = 0, 1, 2, 3
_I64_SAFE = 1 << 20  # raw values below this: window sums and n*S2 - S1^2 stay exact in int64


@dataclass(frozen=True)
class DpFromHighLow:
    """dp = high - low, exact in integers: raw_dp = p * raw_high - q * raw_low (see
    :func:`commensurate`), taken at each high-pressure sample with the newest low-pressure sample."""

    p: int
    q: int


@dataclass(frozen=True)
class Target:
    """Where one decoded value goes: a role's window (``WINDOW``), high or low pressure toward dp,
    or nowhere."""

    role: str | None
    kind: int


Stats = tuple[dict[str, Any], dict[str, Any], dict[str, Any], dict[str, Any]]  # mean, std, count, age


@dataclass
class Windows:
    """The windows of the gated roles (``roles``, less the ``constants``) and the newest low
    pressure (``low``, raw) when dp is formed from high and low."""

    roles: Sequence[str]
    affine: Mapping[str, Affine]
    window_s: float
    min_samples: int
    constants: Mapping[str, float] = field(default_factory=dict)
    dp_from_high_low: DpFromHighLow | None = None
    role_window_s: Mapping[str, float] = field(default_factory=dict)  # a slow message's role: its own

    def __post_init__(self) -> None:
        self.windows = {r: RoleWindow() for r in self.roles if r not in self.constants}
        self.spans = {r: self.role_window_s.get(r, self.window_s) for r in self.windows}
        self.low: int | None = None

    def targets(self, value_roles: Sequence[str]) -> tuple[Target, ...]:
        """Where the values of a message mapping ``value_roles`` (in order) go."""
        hl = self.dp_from_high_low is not None
        out = []
        for r in value_roles:
            if r == HIGH_PRESSURE and hl:
                out.append(Target(None, HIGH))
            elif r == LOW_PRESSURE and hl:
                out.append(Target(None, LOW))
            elif r in self.windows:
                out.append(Target(r, WINDOW))
            else:
                out.append(Target(None, IGNORED))
        return tuple(out)

    # -- one frame, one tick -----------------------------------------------------------------------

    def adder(self, value_roles: Sequence[str]) -> Callable[[float, Sequence[int]], None]:
        """``add(t, raws)`` for an accepted frame of a message mapping ``value_roles``."""
        targets = self.targets(value_roles)
        wins = [self.windows[x.role].add if x.kind == WINDOW else None for x in targets]  # type: ignore[index]
        if all(x.kind in (WINDOW, IGNORED) for x in targets):
            plain = [(j, add) for j, add in enumerate(wins) if add is not None]
            if len(plain) == len(targets):

                def add_all(t: float, raws: Sequence[int]) -> None:
                    for raw, add in zip(raws, wins, strict=True):
                        add(t, raw)  # type: ignore[misc]

                return add_all

            def add_some(t: float, raws: Sequence[int]) -> None:
                for j, add in plain:
                    add(t, raws[j])

            return add_some
        plan = [(x.kind, add) for x, add in zip(targets, wins, strict=True)]
        hl = self.dp_from_high_low
        p, q = (hl.p, hl.q) if hl is not None else (0, 0)
        add_dp = self.windows[DP].add if hl is not None else None

        def add_with_pressures(t: float, raws: Sequence[int]) -> None:
            high = None
            for raw, (kind, add) in zip(raws, plan, strict=True):
                if kind == WINDOW:
                    add(t, raw)  # type: ignore[misc]
                elif kind == HIGH:
                    high = raw
                elif kind == LOW:
                    self.low = raw
            if high is not None and self.low is not None:
                add_dp(t, p * high - q * self.low)  # type: ignore[misc]

        return add_with_pressures

    def stats(self, t: float) -> Stats:
        """Every gated role's window mean, spread, count and newest sample's age at a tick at ``t``; a
        role the machine holds constant is that value, fresh, with no spread."""
        mean, std, count, age = {}, {}, {}, {}
        for role, w in self.windows.items():
            mean[role], std[role], count[role] = w.stats(t, self.spans[role], self.affine[role])
            age[role] = t - w.last_t
        for role, value in self.constants.items():
            mean[role], std[role], count[role], age[role] = float(value), 0.0, self.min_samples, 0.0
        return mean, std, count, age

    def shift(self, delta_s: float) -> None:
        for w in self.windows.values():
            w.shift(delta_s)

    # -- a stretch of frames -----------------------------------------------------------------------

    def stretch(
        self,
        t: NDArray[np.float64],
        per_message: Sequence[tuple[Sequence[Target], NDArray[np.int64], Sequence[NDArray[np.int64]]]],
    ) -> Stretch:
        """The samples of a stretch of frames at times ``t``: per input message its targets, its
        accepted frames (positions in ``t``, arrival order) and their decoded values."""
        per_role: dict[str, list[tuple[NDArray[np.int64], NDArray[np.int64]]]] = {r: [] for r in self.windows}
        high: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []
        low: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []
        for targets, rows, values in per_message:
            if not len(rows):
                continue
            for x, v in zip(targets, values, strict=True):
                if x.kind == WINDOW and x.role is not None:
                    per_role[x.role].append((rows, v))
                elif x.kind == HIGH:
                    high.append((rows, v))
                elif x.kind == LOW:
                    low.append((rows, v))
        li, lv = _in_order(low)
        low_after = int(lv[-1]) if len(lv) else self.low
        if high:  # (only where dp is formed from high and low)
            per_role[DP].append(self._dp_samples(high, li, lv))
        samples = {r: StretchSamples(self.windows[r], *_in_order(parts), t) for r, parts in per_role.items()}
        return Stretch(self, samples, low_after)

    def _dp_samples(
        self, high: list[tuple[NDArray[np.int64], NDArray[np.int64]]], li: NDArray[np.int64], lv: NDArray[np.int64]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """dp at each frame with high pressure, with the newest low pressure at or before it (the one
        before the stretch where none came in it), as :meth:`adder` forms it frame by frame."""
        hl = self.dp_from_high_low
        assert hl is not None
        hi_idx, hv = _in_order(high)
        if max(magnitude(hv), magnitude(lv), abs(self.low or 0)) * max(hl.p, hl.q) >= 1 << 62:
            hv, lv = hv.astype(object), lv.astype(object)  # 64-bit signals: Python's exact integers
        j = np.searchsorted(li, hi_idx, side="right") - 1
        low_val = np.where(j >= 0, lv[np.maximum(j, 0)], 0)
        has_low = j >= 0
        if self.low is not None:
            low_val = np.where(has_low, low_val, self.low)
            has_low = np.ones_like(has_low)
        return hi_idx[has_low], hl.p * hv[has_low] - hl.q * low_val[has_low]


def magnitude(raw: NDArray[Any]) -> int:
    """The largest |value| of integer samples (exact for int64's most negative value and for the
    Python integers of 64-bit unsigned signals); 0 for none."""
    if not len(raw):
        return 0
    return max(abs(int(raw.min())), abs(int(raw.max())))


def _in_order(parts: list[tuple[NDArray[np.int64], NDArray[np.int64]]]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Samples of several messages (frame positions, values) merged in arrival order."""
    if len(parts) == 1:  # one message's frames: in arrival order already
        return parts[0]
    if not parts:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    fi = np.concatenate([r for r, _ in parts])
    rv = np.concatenate([v for _, v in parts])
    order = np.argsort(fi, kind="stable")
    return fi[order], rv[order]


class Stretch:
    """The windows' samples over a stretch of frames: every tick's statistics, then the windows as
    the frames one by one leave them (:meth:`commit`)."""

    def __init__(self, owner: Windows, samples: dict[str, StretchSamples], low_after: int | None) -> None:
        self.owner = owner
        self.samples = samples
        self.low_after = low_after

    def stats(self, trig: NDArray[np.int64], t_k: NDArray[np.float64]) -> Stats:
        """:meth:`Windows.stats` at each tick ``t_k``, whose samples are those of the frames before
        ``trig`` (the frame that completes the tick)."""
        w = self.owner
        mean, std, count, age = {}, {}, {}, {}
        for role, smp in self.samples.items():
            cut = t_k - w.spans[role] + TIME_EPS_S
            mean[role], std[role], count[role], age[role] = smp.stats(trig, cut, t_k, w.affine[role])
        n = len(t_k)
        for role, value in w.constants.items():
            mean[role], std[role] = np.full(n, float(value)), np.zeros(n)
            count[role], age[role] = np.full(n, w.min_samples, dtype=np.int64), np.zeros(n)
        return mean, std, count, age

    def commit(self) -> None:
        for smp in self.samples.values():
            smp.commit()
        self.owner.low = self.low_after


class StretchSamples:
    """One role's samples for a stretch: the window's deque at its start, then the new ones (the
    frames' positions ``frame_idx`` in the stretch, their ``raw`` values, the stretch's times ``t``)."""

    def __init__(
        self, win: RoleWindow, frame_idx: NDArray[np.int64], raw: NDArray[np.int64], t: NDArray[np.float64]
    ) -> None:
        self.win = win
        old_t = np.fromiter(win.ts, np.float64, len(win.ts))
        old_r = list(win.rs)
        self.n_old = len(old_t)
        self.ts = np.concatenate([old_t, t[frame_idx]])
        self.big = max((abs(r) for r in old_r), default=0) >= _I64_SAFE or magnitude(raw) >= _I64_SAFE
        if self.big:
            self.raw = np.array(old_r + [int(x) for x in raw.tolist()], dtype=object)
        else:
            self.raw = np.concatenate([np.asarray(old_r, dtype=np.int64), raw.astype(np.int64)])
        self.frame_idx = frame_idx
        self.rmax = running_max(self.ts)
        self.last_t0 = win.last_t
        if self.big:
            self.c1 = np.concatenate([[0], np.cumsum(self.raw)])
            self.c2 = np.concatenate([[0], np.cumsum(self.raw * self.raw)])
        else:  # the prefix sums written in place after their leading zero
            self.c1 = np.zeros(len(self.raw) + 1, dtype=np.int64)
            self.c2 = np.zeros(len(self.raw) + 1, dtype=np.int64)
            np.cumsum(self.raw, out=self.c1[1:])
            np.cumsum(self.raw * self.raw, out=self.c2[1:])
        self.front = 0  # the deque's front after the last tick of the stretch

    def stats(
        self, trig: NDArray[np.int64], cut: NDArray[np.float64], t_k: NDArray[np.float64], f: Affine
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
        # samples available at a tick: the old ones plus the new ones from frames before its trigger
        avail = self.n_old + np.searchsorted(self.frame_idx, trig, side="left")
        front = np.minimum(avail, np.searchsorted(self.rmax, cut, side="right"))
        front = np.maximum.accumulate(np.maximum(front, 0))
        self.front = int(front[-1])
        n = avail - front
        s1 = self.c1[avail] - self.c1[front]
        s2 = self.c2[avail] - self.c2[front]
        if self.big:
            mean = np.array([f.mean(a, b) if b else math.nan for a, b in zip(s1.tolist(), n.tolist(), strict=True)])
            std = np.array(
                [
                    f.std(a, b2, b) if b else math.nan
                    for a, b2, b in zip(s1.tolist(), s2.tolist(), n.tolist(), strict=True)
                ]
            )
        else:
            mean, std = mean_std(s1.astype(np.int64), s2.astype(np.int64), n, f)
        newest_new = np.where(
            avail > self.n_old, self.rmax[np.maximum(avail - 1, 0)] if len(self.rmax) else -np.inf, -np.inf
        )
        last_t = np.maximum(self.last_t0, newest_new)
        return mean, std, n.astype(np.int64), t_k - last_t

    def commit(self) -> None:
        """The window as frame by frame leaves it: samples from the last front on, their sums."""
        win = self.win
        ts = self.ts[self.front :].tolist()
        rs = [int(x) for x in self.raw[self.front :].tolist()]
        win.ts = deque(ts)
        win.rs = deque(rs)
        win.s1 = sum(rs)
        win.s2 = sum(r * r for r in rs)
        if len(self.ts) > self.n_old:
            win.last_t = max(win.last_t, float(self.rmax[-1]))
