"""Read ahead: an iterator's next items made by a background thread while the consumer works.

Reading and parsing a log chunk is numpy work that releases the GIL, so on a machine with a second
core the next chunk is parsed while the replay engine does the current one. At most ``depth`` items
wait in the queue, so memory stays bounded by the chunk size; items arrive in order, and an
exception in the producer is raised in the consumer at the point the item would have come.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from typing import TypeVar

T = TypeVar("T")

_DONE = object()


class _Failed:
    __slots__ = ("exc",)

    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


def read_ahead(items: Iterator[T], depth: int = 1) -> Iterator[T]:
    """Yield ``items`` in order, producing up to ``depth`` of them ahead in a thread. Closing the
    returned generator early stops the producer (it finishes the item in hand, then quits)."""
    q: queue.Queue[object] = queue.Queue(maxsize=max(1, depth))
    stop = threading.Event()

    def put(x: object) -> bool:
        while not stop.is_set():
            try:
                q.put(x, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for x in items:
                if not put(x):
                    return
        except BaseException as exc:  # handed over to the consumer, which raises it
            put(_Failed(exc))
            return
        finally:
            close = getattr(items, "close", None)
            if close is not None:
                close()  # e.g. a generator's open file
        put(_DONE)

    worker = threading.Thread(target=produce, name="cmcan-read-ahead", daemon=True)
    worker.start()
    try:
        while True:
            x = q.get()
            if x is _DONE:
                return
            if isinstance(x, _Failed):
                raise x.exc
            yield x  # type: ignore[misc]
    finally:
        stop.set()
        worker.join()
