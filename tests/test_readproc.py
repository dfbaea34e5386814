"""Read-ahead in a reader process: items in order and intact, the child's error raised here with its
kind, an early stop or a cancel leaves no process, a child that dies is said, a warmed child is used
and kept for the next reading."""

from __future__ import annotations

import multiprocessing as mp
import os

import numpy as np
import pytest

from cmcan.errors import CmcanError, Kind
from cmcan.io import readproc

_prepared = "no"


def _prepare() -> None:  # runs in the child before its job
    global _prepared
    _prepared = f"yes in {os.getpid()}"


def _chunks(n: int, size: int):
    rng = np.random.default_rng(n)
    for i in range(n):
        yield i, rng.integers(0, 255, size=(size, 8), dtype=np.uint8)


def _fails_after(k: int):
    yield from range(k)
    raise CmcanError("r.mf4: frame 3: a payload of 65 bytes", Kind.DATA)


def _dies_after(k: int):
    yield from range(k)
    os._exit(3)


def _endless():
    i = 0
    while True:
        yield i
        i += 1


def _who():
    yield _prepared
    yield os.getpid()


def _no_children() -> bool:
    readproc.cancel()  # the child a whole reading keeps for the next
    return not mp.active_children()


def test_items_come_in_order_and_intact_from_another_process():
    got = list(readproc.read_in_process(_chunks, 6, 300_000))  # 2.4 MB each: larger than a pipe's buffer
    want = list(_chunks(6, 300_000))
    assert [i for i, _ in got] == list(range(6))
    for (_, a), (_, b) in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    assert _no_children()


def test_the_childs_error_is_raised_here_with_its_kind_after_the_items_before_it():
    got = []
    with pytest.raises(CmcanError, match="frame 3: a payload of 65 bytes") as exc:
        for x in readproc.read_in_process(_fails_after, 2):
            got.append(x)
    assert got == [0, 1]
    assert exc.value.kind is Kind.DATA
    assert _no_children()


def test_a_child_that_dies_is_said_not_waited_for():
    with pytest.raises(RuntimeError, match=r"ended without a word \(exit 3\)"):
        list(readproc.read_in_process(_dies_after, 2))
    assert _no_children()


def test_stopping_early_stops_the_child():
    it = readproc.read_in_process(_endless)
    assert [next(it) for _ in range(5)] == [0, 1, 2, 3, 4]
    it.close()
    assert _no_children()


def test_a_warmed_child_is_prepared_and_taken_by_the_next_reading():
    readproc.warm(_prepare)
    prepared, pid = list(readproc.read_in_process(_who))
    assert pid != os.getpid()
    assert prepared == f"yes in {pid}"
    assert _no_children()


def test_a_warmed_child_nothing_took_is_cancelled():
    readproc.warm(_prepare)
    assert mp.active_children()
    readproc.cancel()
    assert not mp.active_children()
    readproc.cancel()  # twice: nothing to do


def test_one_child_serves_reading_after_reading_and_after_an_error():
    readproc.warm(_prepare)
    _, first = list(readproc.read_in_process(_who))
    with pytest.raises(CmcanError):
        list(readproc.read_in_process(_fails_after, 1))
    assert [i for i, _ in readproc.read_in_process(_chunks, 2, 10)] == [0, 1]
    prepared, again = list(readproc.read_in_process(_who))
    assert again == first
    assert prepared == f"yes in {first}"  # prepared once, at its start
    assert _no_children()


def _read_in_a_daemonic_process(out) -> None:
    from cmcan.io import readproc as rp

    out.put((list(rp.read_in_process(_who)), os.getpid()))


def test_a_daemonic_process_such_as_a_dask_worker_reads_in_a_thread():
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    p = ctx.Process(target=_read_in_a_daemonic_process, args=(out,), daemon=True)
    p.start()
    (prepared, pid), own = out.get(timeout=60)
    p.join()
    assert p.exitcode == 0
    assert pid == own  # the same process made the items (in its read-ahead thread)
    assert prepared == "no"
