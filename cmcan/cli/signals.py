"""What ``cmcan run`` does on each signal.

- SIGHUP reloads the configuration and model (``systemctl reload cmcan``): validated first, the
  running ones kept if the new ones do not fit, the monitor's state carried over.
- SIGTERM and SIGINT stop the daemon: state saved, exit 0.
- Every other signal whose default action would end the process at once (SIGQUIT, SIGUSR1, SIGUSR2,
  SIGALRM, SIGVTALRM, SIGPROF, SIGXCPU, SIGPWR, SIGSTKFLT, SIGIO, the real-time signals) is logged
  and stops the daemon the same way, state saved, but with the exit status 128 + N a shell gives a
  process killed by signal N: systemd's ``Restart=on-failure`` then restarts it, as it would have
  after the kill. Signals raised by a fault in the process itself (SIGSEGV, SIGBUS, SIGFPE, SIGILL,
  SIGABRT, SIGSYS, SIGTRAP) are not handled: nothing is left to save from there.

A handler only sets a flag for the daemon's loop, which acts between two frames.
"""

from __future__ import annotations

import logging
import signal
from types import FrameType
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # a hint only: cmcan run's parser imports this module
    from cmcan.daemon.loop import Daemon

log = logging.getLogger("cmcan")

RELOAD = signal.SIGHUP
STOP = (signal.SIGTERM, signal.SIGINT)
_FATAL_NAMES = ("SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM", "SIGVTALRM", "SIGPROF", "SIGXCPU", "SIGPWR", "SIGSTKFLT")
_FATAL_NAMES += ("SIGIO",)
FATAL: tuple[int, ...] = tuple(getattr(signal, n) for n in _FATAL_NAMES if hasattr(signal, n)) + tuple(
    range(signal.SIGRTMIN, signal.SIGRTMAX + 1)
)


def install(daemon: Daemon) -> None:
    """Route the signals above to ``daemon``."""

    def on_reload(signum: int, _frame: FrameType | None) -> None:
        log.info("received SIGHUP: reloading the configuration and model")
        daemon.request_reload()

    def on_stop(signum: int, _frame: FrameType | None) -> None:
        log.info("received %s, stopping", _name(signum))
        daemon.stop(signum)

    def on_fatal(signum: int, _frame: FrameType | None) -> None:
        log.warning("received %s: saving state and exiting (status %d)", _name(signum), 128 + signum)
        daemon.stop(signum)

    signal.signal(RELOAD, on_reload)
    for s in STOP:
        signal.signal(s, on_stop)
    for s in FATAL:
        signal.signal(s, on_fatal)


def exit_status(daemon: Daemon) -> int:
    """0 after a requested stop; 128 + N after any other signal N."""
    s = daemon.stop_signal
    return 0 if s is None or s in STOP else 128 + s


def _name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"SIGRTMIN+{signum - signal.SIGRTMIN}"
