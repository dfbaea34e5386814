"""The turnstile of ``tests/machine_share.py``: shared holders run together; a real-time holder waits
for them, and those that start while it runs run beside it at idle priority."""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from pathlib import Path

import pytest

from tests.machine_share import idle_priority, machine_share

pytestmark = pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux's")


def _hold(where: str, realtime: bool, started, release, log) -> None:
    with machine_share(realtime, Path(where)):
        log.put((time.monotonic(), "in", realtime, os.sched_getscheduler(0)))
        started.set()
        release.wait(30)
        log.put((time.monotonic(), "out", realtime, os.sched_getscheduler(0)))


def _drain(q, n: int) -> list[tuple[str, bool, int]]:
    """The ``n`` events in the order they happened: a queue fed by several processes may deliver them
    in another (each process's feeder thread flushes on its own)."""
    got = sorted(q.get(timeout=20) for _ in range(n))
    return [e[1:] for e in got]


def test_a_realtime_holder_waits_for_the_running_tests_and_the_next_ones_step_back(tmp_path):
    ctx = mp.get_context("fork")
    log = ctx.Queue()
    ev = [(ctx.Event(), ctx.Event()) for _ in range(3)]
    procs = [
        ctx.Process(target=_hold, args=(str(tmp_path), rt, s, r, log))
        for rt, (s, r) in zip((False, False, True), ev, strict=True)
    ]
    procs[0].start()
    procs[1].start()
    assert ev[0][0].wait(20) and ev[1][0].wait(20)  # both shared holders inside at once
    procs[2].start()
    time.sleep(0.5)
    assert not ev[2][0].is_set()  # the real-time one waits for them
    # a new shared holder waits behind the real-time one (the turnstile), then runs beside it
    beside_s, beside_r = ctx.Event(), ctx.Event()
    beside = ctx.Process(target=_hold, args=(str(tmp_path), False, beside_s, beside_r, log))
    beside.start()
    time.sleep(0.3)
    assert not beside_s.is_set()
    ev[0][1].set()
    ev[1][1].set()
    assert ev[2][0].wait(20) and beside_s.wait(20)
    ev[2][1].set()
    procs[2].join(20)
    after_s, after_r = ctx.Event(), ctx.Event()  # starts once the real-time one is gone
    after = ctx.Process(target=_hold, args=(str(tmp_path), False, after_s, after_r, log))
    after.start()
    assert after_s.wait(20)
    beside_r.set()
    after_r.set()
    for p in [*procs, beside, after]:
        p.join(20)
        assert p.exitcode == 0
    events = _drain(log, 10)
    rt_in = events.index(("in", True, os.SCHED_OTHER))
    assert {e[:2] for e in events[:rt_in]} == {("in", False), ("out", False)}  # both shared left first
    beside_in = events.index(("in", False, os.SCHED_IDLE))  # beside the real-time one, stepped back
    assert rt_in < beside_in < events.index(("out", True, os.SCHED_OTHER))
    assert events.count(("in", False, os.SCHED_IDLE)) == 1  # only that one: the one after runs normally


def _sys_nice() -> bool:
    """CAP_SYS_NICE (bit 23) in this process's effective capabilities."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("CapEff:"):
            return bool(int(line.split()[1], 16) >> 23 & 1)
    return False


def _policies(log) -> None:
    with idle_priority():
        inside = os.sched_getscheduler(0)
    log.put((inside, os.sched_getscheduler(0)))


def test_idle_priority_lasts_the_block_and_ends_where_the_kernel_lets_it():
    ctx = mp.get_context("fork")
    log = ctx.Queue()
    p = ctx.Process(target=_policies, args=(log,))
    p.start()
    inside, after = log.get(timeout=20)
    p.join(20)
    assert inside == os.SCHED_IDLE
    assert after == (os.SCHED_OTHER if _sys_nice() else os.SCHED_IDLE)
