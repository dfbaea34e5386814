"""The machine shared between xdist workers, with the real-time tests first in line for the CPU.

The vcan tier asserts watchdog periods, frame gaps and a stop within 2 s, in a VM emulated on the
host's cores; run next to another worker's CPU-bound test at the same priority, those fail for want
of CPU, not for a fault. Yet the emulator keeps about one of the two cores busy, and leaving the other
idle for the tier's ten minutes made it a third of the suite's time. So:

- every test holds the ``run`` lock shared while it runs;
- a real-time test (the vcan tier) first takes it exclusively, which waits for the tests running now
  to end (they started at normal priority), marks the machine as taken by holding the ``realtime``
  lock, and steps down to shared;
- a test that starts while ``realtime`` is held runs at idle priority (``SCHED_IDLE``, inherited by
  the processes it starts): it gets only the CPU time the real-time test leaves over, and back to
  normal priority when it ends (where the kernel lets a process do that: it needs ``CAP_SYS_NICE``;
  without, the worker stays at idle priority for the rest of its session, which only slows it).

A turnstile lock in front keeps the real-time waiter from starving behind a stream of shared ones.
flock locks end with their process, so a killed run leaves nothing held.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext, suppress
from pathlib import Path
from typing import BinaryIO


def lock_dir() -> Path:
    d = Path(tempfile.gettempdir()) / f"cmcan-tests-{os.getuid()}"
    d.mkdir(mode=0o700, exist_ok=True)
    return d


def _held(lock: BinaryIO) -> bool:
    """True when another process holds ``lock`` exclusively."""
    try:
        fcntl.flock(lock, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    fcntl.flock(lock, fcntl.LOCK_UN)
    return False


@contextmanager
def idle_priority() -> Iterator[None]:
    """This thread (and what it starts) at ``SCHED_IDLE`` for the block; back as it was after, where
    the kernel allows it."""
    try:
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):  # not Linux, or not allowed: run as is
        yield
        return
    try:
        yield
    finally:
        with suppress(OSError):  # no CAP_SYS_NICE: stays idle, see the module's docstring
            os.sched_setscheduler(0, policy, param)


@contextmanager
def machine_share(realtime: bool, where: Path | None = None) -> Iterator[None]:
    """Hold the machine shared, as a real-time test (``realtime``: the others step back) or beside
    one (at idle priority while a real-time test runs)."""
    d = where or lock_dir()
    with open(d / "turnstile", "a+b") as gate, open(d / "run", "a+b") as run, open(d / "realtime", "a+b") as rt:
        fcntl.flock(gate, fcntl.LOCK_EX)
        try:
            if realtime:
                fcntl.flock(run, fcntl.LOCK_EX)  # the tests running now end first
                fcntl.flock(rt, fcntl.LOCK_EX)  # those that start from now on step back
                fcntl.flock(run, fcntl.LOCK_SH)
                behind = False
            else:
                fcntl.flock(run, fcntl.LOCK_SH)
                behind = _held(rt)
        finally:
            fcntl.flock(gate, fcntl.LOCK_UN)
        with idle_priority() if behind else nullcontext():
            yield  # closing the files releases the locks
