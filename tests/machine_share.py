"""The machine shared between xdist workers, except by tests that time real-time behaviour.

The vcan tier asserts watchdog periods, frame gaps and a stop within 2 s, in a VM emulated on the
host's cores; run next to another worker's CPU-bound test, those fail for want of CPU, not for a
fault. Every test holds a shared lock while it runs; a vcan test holds it exclusively, so it waits
for the running tests to end and no other starts before it is done. A turnstile lock in front keeps
the exclusive waiter from starving behind a stream of shared ones. flock locks end with their
process, so a killed run leaves nothing held.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def lock_dir() -> Path:
    d = Path(tempfile.gettempdir()) / f"cmcan-tests-{os.getuid()}"
    d.mkdir(mode=0o700, exist_ok=True)
    return d


@contextmanager
def machine_share(exclusive: bool, where: Path | None = None) -> Iterator[None]:
    """Hold the machine shared (``exclusive`` False) or alone for the ``with`` block."""
    d = where or lock_dir()
    with open(d / "turnstile", "a+b") as gate, open(d / "run", "a+b") as run:
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(run, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        finally:
            fcntl.flock(gate, fcntl.LOCK_UN)
        yield  # closing the file releases the lock
