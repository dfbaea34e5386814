"""The turnstile of ``tests/machine_share.py``: shared holders run together, an exclusive holder
waits for them and keeps new ones out until it is done."""

from __future__ import annotations

import multiprocessing as mp
import time
from pathlib import Path

from tests.machine_share import machine_share


def _hold(where: str, exclusive: bool, started, release, log) -> None:
    with machine_share(exclusive, Path(where)):
        log.put((time.monotonic(), "in", exclusive))
        started.set()
        release.wait(30)
        log.put((time.monotonic(), "out", exclusive))


def _drain(q, n: int) -> list[tuple[str, bool]]:
    """The ``n`` events in the order they happened: a queue fed by several processes may deliver them
    in another (each process's feeder thread flushes on its own)."""
    got = sorted(q.get(timeout=20) for _ in range(n))
    return [(what, exclusive) for _, what, exclusive in got]


def test_shared_holders_run_together_and_an_exclusive_one_waits_for_them(tmp_path):
    ctx = mp.get_context("fork")
    log = ctx.Queue()
    ev = [(ctx.Event(), ctx.Event()) for _ in range(3)]
    procs = [
        ctx.Process(target=_hold, args=(str(tmp_path), excl, s, r, log))
        for excl, (s, r) in zip((False, False, True), ev, strict=True)
    ]
    procs[0].start()
    procs[1].start()
    assert ev[0][0].wait(20) and ev[1][0].wait(20)  # both shared holders inside at once
    procs[2].start()
    time.sleep(0.5)
    assert not ev[2][0].is_set()  # the exclusive one waits for them
    # a new shared holder now waits behind the exclusive one (the turnstile)
    late_s, late_r = ctx.Event(), ctx.Event()
    late = ctx.Process(target=_hold, args=(str(tmp_path), False, late_s, late_r, log))
    late.start()
    time.sleep(0.3)
    ev[0][1].set()
    ev[1][1].set()
    assert ev[2][0].wait(20)
    time.sleep(0.3)
    assert not late_s.is_set()  # kept out while the exclusive one runs
    ev[2][1].set()
    assert late_s.wait(20)
    late_r.set()
    for p in [*procs, late]:
        p.join(20)
        assert p.exitcode == 0
    events = _drain(log, 8)
    excl_in = events.index(("in", True))
    assert events[excl_in - 2 : excl_in].count(("out", False)) == 2  # both shared left first
    assert events[excl_in + 1] == ("out", True)  # nobody came in while it ran
