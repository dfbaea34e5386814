"""Read-ahead: items in order, a producer's error raised at its place, an early stop ends the thread."""

import threading

import pytest

from cmcan.io.readahead import read_ahead


def test_items_come_in_order():
    assert list(read_ahead(iter(range(1000)), depth=2)) == list(range(1000))


def test_an_error_in_the_producer_is_raised_after_the_items_before_it():
    def gen():
        yield 1
        yield 2
        raise ValueError("bad chunk")

    got = []
    with pytest.raises(ValueError, match="bad chunk"):
        for x in read_ahead(gen()):
            got.append(x)
    assert got == [1, 2]


def test_stopping_early_closes_the_source_and_ends_the_thread():
    closed = threading.Event()

    def gen():
        try:
            yield from range(10**9)
        finally:
            closed.set()

    it = read_ahead(gen())
    assert next(it) == 0
    it.close()
    assert closed.is_set()
    assert not any(t.name == "cmcan-read-ahead" for t in threading.enumerate())
