"""Read ahead in a process of its own: a log's chunks made by a child process while this one replays.

The candump path reads ahead in a thread because its parser releases the GIL. asammdf does not: its
import (pandas, canmatrix: some 0.75 s) and the conversion of its records hold the GIL, so a thread
only takes turns with the replay. A child process does that work on the other core: it is started
(:func:`warm`) before the replay assembles its monitor, imports what the reading needs while this
process imports and builds its own, then reads the file (:func:`read_in_process`) while this one
replays, one chunk ahead (memory stays bounded by the chunk size). After a reading it waits for the
next (several logs of one life, a training's logs: asammdf imported once) until :func:`cancel` or
this process's exit.

Items arrive in order, pickled; an exception in the child is raised here where the item would have
come, the same exception (a :class:`cmcan.errors.CmcanError` keeps its kind). The child ignores SIGINT
(this process decides), quits when this one is gone, and is stopped when the reading is closed early.
Where no child may be started (in a Dask worker, which is a daemonic process; a process limit) the
same iterator is read here, in a thread: slower, never different.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import signal
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from cmcan.io.readahead import read_ahead

T = TypeVar("T")
log = logging.getLogger(__name__)

_DONE = "done"
_ITEM = "item"
_FAILED = "failed"


def _serve(prepare: Callable[[], None] | None, jobs: Any, out: Any) -> None:
    """The child: prepare (the imports), then job after job, each one's items sent to ``out``. Sent
    from this thread (no feeder thread: a chunk's megabytes would cross in 64 KiB turns for the GIL
    with the reading); each send waits until the parent has taken the item before, so the child is
    one item ahead. Ends when the parent closes its end of ``jobs`` (or is gone)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if prepare is not None:
        prepare()
    try:
        while True:
            make, args = jobs.recv()
            try:
                for item in make(*args):
                    out.send((_ITEM, item))
            except (BrokenPipeError, ConnectionResetError):
                raise
            except BaseException as exc:  # handed over: the parent raises it
                out.send((_FAILED, _picklable(exc)))
                continue
            out.send((_DONE, None))
    except (EOFError, BrokenPipeError, ConnectionResetError):
        return  # the parent stopped reading or is gone


def _picklable(exc: BaseException) -> BaseException:
    """``exc``, or a RuntimeError saying it where it cannot cross to the parent."""
    import pickle

    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")


class _Child:
    """One reader process, started at once, given one job at a time."""

    def __init__(self, prepare: Callable[[], None] | None) -> None:
        ctx = mp.get_context("spawn")  # a fresh interpreter: no copy of this one's threads
        job_r, self.jobs = ctx.Pipe(duplex=False)
        self.out, out_w = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_serve, args=(prepare, job_r, out_w), name="cmcan-reader", daemon=True)
        try:
            self.proc.start()
        finally:
            job_r.close()  # the child's ends: its exit is then an end of file here
            out_w.close()

    def items(self, make: Callable[..., Iterator[T]], args: tuple[Any, ...]) -> Iterator[T]:
        """The job's items; the child waits for the next job after its last one (or its error), and is
        stopped when the reading ends early (it would be one item into the rest)."""
        global _spare
        whole = False
        try:
            self.jobs.send((make, args))
            while True:
                try:
                    kind, value = self.out.recv()
                except EOFError:
                    self.proc.join()
                    raise RuntimeError(f"the reader process ended without a word (exit {self.proc.exitcode})") from None
                if kind == _ITEM:
                    yield value
                    continue
                whole = True
                if kind == _FAILED:
                    raise value
                return
        finally:
            if whole and _spare is None:
                _spare = self  # kept for the next reading: its imports are done
            else:
                self.stop()

    def stop(self) -> None:
        self.jobs.close()  # a child still waiting for its job ends
        self.out.close()
        if self.proc.is_alive() and self.proc.exitcode is None:
            self.proc.terminate()
        self.proc.join()


def _start(prepare: Callable[[], None] | None) -> _Child | None:
    """A reader process, or None where none may be started: in a daemonic process (a Dask worker's:
    multiprocessing refuses it children), or when the system refuses one (a process limit, memory)."""
    if mp.current_process().daemon:
        log.debug("no reader process in a daemonic process: the log is read in a thread")
        return None
    try:
        return _Child(prepare)
    except OSError as exc:
        log.debug("no reader process (%s): the log is read in a thread", exc)
        return None


_spare: _Child | None = None


def warm(prepare: Callable[[], None] | None = None) -> None:
    """Start a reader process now (it runs ``prepare``, a module-level function, e.g. the imports the
    reading needs), for the next :func:`read_in_process` to take. Nothing if one is waiting."""
    global _spare
    if _spare is None:
        _spare = _start(prepare)


def cancel() -> None:
    """Stop the waiting reader process (one :func:`warm` started, or one a reading left for the next)."""
    global _spare
    if _spare is not None:
        _spare.stop()
        _spare = None


def read_in_process(make: Callable[..., Iterator[T]], *args: Any) -> Iterator[T]:
    """``make(*args)``'s items, made in a reader process (the one :func:`warm` started, or a new one);
    ``make`` and the items must pickle. In a thread where no process can be started."""
    global _spare
    child, _spare = _spare, None
    if child is None:
        child = _start(None)
    if child is None:
        yield from read_ahead(make(*args))
        return
    yield from child.items(make, args)
