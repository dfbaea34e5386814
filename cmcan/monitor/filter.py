"""The moving average of the last N evaluated CM ratios and leakage estimates."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable


class RatioFilter:
    __slots__ = ("leaks", "min_samples", "ratios", "samples")

    def __init__(
        self, samples: int, min_samples: int, ratios: Iterable[float] = (), leaks: Iterable[float] = ()
    ) -> None:
        self.samples = samples
        self.min_samples = min_samples
        self.ratios: deque[float] = deque(ratios, maxlen=samples)  # a saved filter, oldest first
        self.leaks: deque[float] = deque(leaks, maxlen=samples)

    def add(self, ratio_pct: float, leak_lpm: float) -> None:
        self.ratios.append(ratio_pct)
        self.leaks.append(leak_lpm)

    def __len__(self) -> int:
        return len(self.ratios)

    @property
    def valid(self) -> bool:
        return len(self.ratios) >= self.min_samples

    @property
    def ratio_pct(self) -> float:
        n = len(self.ratios)
        return math.fsum(self.ratios) / n if n else 0.0

    @property
    def leak_lpm(self) -> float:
        n = len(self.leaks)
        return math.fsum(self.leaks) / n if n else 0.0

    def saved(self) -> tuple[list[float], list[float]]:
        """The ring's contents, oldest first (for the state file)."""
        return list(self.ratios), list(self.leaks)
