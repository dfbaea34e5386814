"""Logging a recurring problem without flooding the journal: the first occurrence at once, then one
line per interval with the count of what was suppressed."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any


class RateLimitedLog:
    """Logs the first occurrence of a problem, then at most one summary line per interval."""

    def __init__(
        self,
        interval_s: float = 30.0,
        clock: Callable[[], float] = time.monotonic,
        logger: logging.Logger | None = None,
    ) -> None:
        self.interval = interval_s
        self.clock = clock
        self.logger = logger or logging.getLogger("cmcan.daemon")
        self.last: dict[str, float] = {}
        self.suppressed: dict[str, int] = {}

    def __call__(self, level: int, key: str, msg: str, *args: Any, exc_info: bool = False) -> None:
        now = self.clock()
        if key in self.last and now - self.last[key] < self.interval:
            self.suppressed[key] = self.suppressed.get(key, 0) + 1
            return
        n = self.suppressed.pop(key, 0)
        self.last[key] = now
        self.logger.log(level, msg + (f" (and {n} more since the last report)" if n else ""), *args, exc_info=exc_info)
