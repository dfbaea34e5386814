"""The daemon: the imperative shell around the monitor core on a live bus.

It owns its receive loop (python-can's Notifier thread would stop for good on the first receive
error), asks the kernel to filter the input identifiers, feeds every frame to the core and sends what
the core returns. Bus errors (network down, a full transmit queue, bus-off) are logged with rate
limits and recovered from by reopening the bus with a growing back-off; no frame and no bus error
stops it. Under systemd it reports READY, WATCHDOG and STATUS; SIGTERM and SIGINT stop it cleanly.
A reload (SIGHUP, :meth:`Daemon.request_reload`) swaps in a new configuration and model validated by
the caller, between two frames, with the monitor's state carried over.
"""

from __future__ import annotations

import errno
import logging
import math
import signal
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import can

from cmcan.config import BusConfig, Config
from cmcan.errors import CmcanError
from cmcan.frame import Frame, from_message, to_message_kwargs
from cmcan.monitor.core import Monitor
from cmcan.ratelog import RateLimitedLog
from cmcan.sdnotify import Notifier
from cmcan.statefile import StateStore

if TYPE_CHECKING:  # issue 15 (uplink): only for the type hint; the feed imports this module
    from cmcan.uplink.feed import UplinkFeed

log = logging.getLogger("cmcan.daemon")

SO_RCVBUFFORCE = 33
SOL_CAN_RAW = 101
CAN_RAW_ERR_FILTER = 2
# Error classes worth hearing about: controller problems, bus-off, restarts after bus-off.
CAN_ERR_MASK = 0x04 | 0x40 | 0x100


WALL_STEP_S = 1.0  # a jump of frame time against boot time beyond this is a wall-clock step


def _boot_time() -> float:
    return time.clock_gettime(time.CLOCK_BOOTTIME)


@dataclass(frozen=True)
class Reloaded:
    """What a reload brings: the new configuration, its monitor (built and checked) and bus opener."""

    cfg: Config
    monitor: Monitor
    open_bus: Callable[[], can.BusABC]


@dataclass
class DaemonOptions:
    recv_timeout_s: float = 0.1
    idle_after_s: float = 1.0  # no frame for this long: advance the core's time on the wall clock
    backoff_min_s: float = 0.5
    backoff_max_s: float = 10.0
    status_every_s: float = 2.0
    send_timeout_s: float = 0.005


def bus_kwargs(b: BusConfig, input_ids: list[int]) -> dict[str, Any]:
    kw: dict[str, Any] = {
        "interface": b.interface,
        "channel": b.channel,
        "bitrate": b.bitrate,
        "can_filters": [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in sorted(input_ids)],
        "receive_own_messages": False,
    }
    return kw


def tune_socketcan(bus: can.BusABC, rcvbuf: int) -> None:
    """A larger receive buffer (no loss when the bus is busy) and error frames for bus-off."""
    sock = getattr(bus, "socket", None)
    if not isinstance(sock, socket.socket):
        return
    if rcvbuf:
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, rcvbuf)
        except OSError:  # needs CAP_NET_ADMIN (the unit grants none); the plain option is capped by net.core.rmem_max
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            except OSError as exc:
                log.warning("cannot enlarge the receive buffer: %s", exc)
        got = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) // 2  # the kernel reports twice the size
        if got < rcvbuf:
            log.warning(
                "receive buffer %d bytes, %d asked for (bus.receive_buffer_bytes): raise net.core.rmem_max, "
                "e.g. with systemd/60-cmcan.conf in /etc/sysctl.d/",
                got,
                rcvbuf,
            )
    try:
        sock.setsockopt(SOL_CAN_RAW, CAN_RAW_ERR_FILTER, struct.pack("=I", CAN_ERR_MASK))
    except OSError as exc:
        log.debug("cannot subscribe to error frames: %s", exc)


class Daemon:
    def __init__(
        self,
        cfg: Config,
        monitor: Monitor,
        store: StateStore | None,
        open_bus: Callable[[], can.BusABC],
        notifier: Notifier | None = None,
        options: DaemonOptions | None = None,
        clock: Callable[[], float] = time.monotonic,
        uplink: UplinkFeed | None = None,
        boot_clock: Callable[[], float] | None = None,
    ) -> None:
        self.cfg = cfg
        self.monitor = monitor
        self.store = store
        self.open_bus = open_bus
        self.notifier = notifier or Notifier(env={})
        self.opt = options or DaemonOptions()
        self.clock = clock
        self.stop_event = threading.Event()
        self.bus: can.BusABC | None = None
        self.stats = {"bus_opens": 0, "bus_errors": 0, "tx_frames": 0, "tx_dropped": 0, "internal_errors": 0}
        self.ratelog = RateLimitedLog(clock=clock)
        self.save_every_s = cfg.state.save_every_s
        self.uplink = uplink  # queues events and summaries for the outbox; never blocks
        # Frame time against a clock that neither steps nor stops in suspend: a jump of their
        # difference is the wall clock stepping (the kernel stamps frames with the wall clock).
        self.boot_clock = boot_clock or _boot_time
        self._wall_minus_boot: float | None = None
        self.reloader: Callable[[], Reloaded] | None = None  # builds a validated configuration (SIGHUP)
        self._reload_requested = threading.Event()
        self.stop_signal: int | None = None  # the signal that stopped the daemon, if one did

    # -- the loop --------------------------------------------------------------------------------------

    def run(self) -> None:
        opt = self.opt
        backoff = opt.backoff_min_s
        last_rx_wall: float | None = None
        last_frame_t = math.nan
        next_wd = next_status = self.clock()
        last_save = self.clock()
        saved_ticks = -1
        self.notifier.ready(self._status_text())
        log.info("cmcan running on %s %s", self.cfg.bus.interface, self.cfg.bus.channel)
        while not self.stop_event.is_set():
            if self._reload_requested.is_set():
                self._reload_requested.clear()
                self._reload()
            now = self.clock()
            if self.notifier.watchdog_interval_s is not None and now >= next_wd:
                self.notifier.watchdog()
                next_wd = now + self.notifier.watchdog_interval_s
            if now >= next_status:
                self.notifier.status(self._status_text())
                next_status = now + opt.status_every_s
            # Save on every warning change at once, else periodically while the core evaluates;
            # an idle gateway does not wear its flash rewriting unchanged totals.
            ticks = self.monitor.counters["ticks"]
            if self.store is not None and (
                self.monitor.transitions_since_save or (now - last_save >= self.save_every_s and ticks != saved_ticks)
            ):
                self._save()
                last_save, saved_ticks = now, ticks

            if self.bus is None:
                if not self._open():
                    self.stop_event.wait(backoff)
                    backoff = min(backoff * 2, opt.backoff_max_s)
                    continue
                backoff = opt.backoff_min_s
            try:
                msg = self.bus.recv(timeout=opt.recv_timeout_s)
            except (can.CanError, OSError, ValueError) as exc:
                self._bus_failed("receive", exc)
                self.stop_event.wait(backoff)
                backoff = min(backoff * 2, opt.backoff_max_s)
                continue

            now = self.clock()
            try:
                if msg is not None:
                    if msg.is_error_frame:
                        self.ratelog(
                            logging.WARNING,
                            "errframe",
                            "error frame on the bus: id 0x%X data %s",
                            msg.arbitration_id,
                            bytes(msg.data).hex(),
                        )
                    self._watch_wall_clock(msg.timestamp)
                    steps = self.monitor.counters["clock_steps"]
                    out = self.monitor.feed(from_message(msg))
                    if self.monitor.counters["clock_steps"] != steps:  # the core found a step back
                        log.warning(
                            "the wall clock stepped back by %.3f s; monitoring goes on on the new time base",
                            last_frame_t - msg.timestamp,
                        )
                    last_rx_wall = now
                    last_frame_t = msg.timestamp
                elif last_rx_wall is not None and now - last_rx_wall >= opt.idle_after_s:
                    out = self.monitor.advance(last_frame_t + (now - last_rx_wall))
                else:
                    out = []
            except Exception:  # the core must never take the daemon down: log, count, go on
                self.stats["internal_errors"] += 1
                self.ratelog(logging.ERROR, "internal", "internal error processing a frame", exc_info=True)
                out = []
            if self.uplink is not None:  # issue 15: after each step of the core (cheap unless a tick completed)
                self.uplink.observe(self.monitor, self.stats)
            if out:
                self._send(out)
        self._shutdown()

    def _watch_wall_clock(self, frame_t: float) -> None:
        """A step of the wall clock forward moves the monitor onto the new time base (a step back the
        core finds by itself); otherwise it would look like the machine had been off that long."""
        diff = frame_t - self.boot_clock()
        prev = self._wall_minus_boot
        self._wall_minus_boot = diff
        if prev is None or not math.isfinite(diff):
            return
        if diff - prev > WALL_STEP_S:
            log.warning(
                "the wall clock stepped forward by %.3f s; monitoring goes on on the new time base", diff - prev
            )
            self.monitor.shift_time(diff - prev)

    def stop(self, signum: int | None = None) -> None:
        """Stop after the current step (safe from a signal handler); the state is saved on the way out."""
        if signum is not None and self.stop_signal is None:
            self.stop_signal = signum
        self.stop_event.set()

    # -- reload ----------------------------------------------------------------------------------------

    def request_reload(self) -> None:
        """Reload between two frames (safe from a signal handler: it only sets a flag)."""
        self._reload_requested.set()

    def _reload(self) -> None:
        """Swap in the configuration and model the reloader builds and checks; if it cannot (a bad
        file, a model that does not fit), say why and go on with the running ones."""
        if self.reloader is None:
            log.warning("reload requested, but this daemon has nothing to reload from")
            return
        self.notifier.reloading()
        try:
            new = self.reloader()
        except Exception as exc:  # a CmcanError names the file and field; anything else is a bug, logged
            log.error("reload failed, running on with the previous configuration: %s", exc, exc_info=not _named(exc))
            self.notifier.ready(self._status_text())
            return
        old_cfg, old_mon = self.cfg, self.monitor
        afresh = new.monitor.take_over(old_mon)
        self.cfg, self.monitor, self.open_bus = new.cfg, new.monitor, new.open_bus
        self.save_every_s = new.cfg.state.save_every_s
        kept = []
        if new.cfg.state.directory != old_cfg.state.directory:
            kept.append(f"state.directory stays {old_cfg.state.directory} until a restart")
        if new.cfg.uplink != old_cfg.uplink:
            kept.append("the uplink settings take effect at a restart")
        if new.cfg.bus != old_cfg.bus or set(new.monitor.inputs) != set(old_mon.inputs):
            self._close()  # reopened by the loop with the new settings and kernel filters
            afresh.append("the bus connection (new bus settings or input identifiers)")
        log.info(
            "reloaded %s: totals, warning state, filter and counters kept; started afresh: %s%s",
            new.cfg.source,
            "; ".join(afresh) or "nothing",
            "".join(f"; {k}" for k in kept),
        )
        self.notifier.ready(self._status_text())

    # -- bus handling ----------------------------------------------------------------------------------

    def _open(self) -> bool:
        try:
            self.bus = self.open_bus()
        except (can.CanError, OSError, ValueError) as exc:
            self.stats["bus_errors"] += 1
            self.ratelog(logging.WARNING, "open", "cannot open the bus (%s); retrying", exc)
            self.notifier.status(f"bus unavailable: {exc}")
            return False
        self.stats["bus_opens"] += 1
        if self.stats["bus_opens"] > 1:
            log.info("bus reopened")
        self.notifier.status(self._status_text())
        return True

    def _close(self) -> None:
        if self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception as exc:  # a failing shutdown of a dead bus is expected
                log.debug("bus shutdown: %s", exc)
            self.bus = None

    def _bus_failed(self, what: str, exc: BaseException) -> None:
        self.stats["bus_errors"] += 1
        code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
        hint = " (network down)" if code == errno.ENETDOWN else ""
        self.ratelog(logging.WARNING, f"fail-{what}", "bus %s failed%s: %s; reopening", what, hint, exc)
        self.notifier.status(f"bus {what} failed: {exc}")
        self._close()

    def _send(self, frames: list[Frame]) -> None:
        for f in frames:
            if self.bus is None:
                self.stats["tx_dropped"] += 1
                continue
            msg = can.Message(**to_message_kwargs(f))
            try:
                self.bus.send(msg, timeout=self.opt.send_timeout_s)
                self.stats["tx_frames"] += 1
            except (can.CanError, OSError) as exc:
                self.stats["tx_dropped"] += 1
                code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
                if code in (errno.ENETDOWN, errno.ENODEV, errno.EBADF):
                    self._bus_failed("send", exc)
                else:  # ENOBUFS, a full queue, bus-off while restarting: drop this frame, keep going
                    self.ratelog(logging.WARNING, "tx", "cannot send 0x%X: %s; frame dropped", f.arbitration_id, exc)

    # -- state and status ------------------------------------------------------------------------------

    def _save(self) -> None:
        assert self.store is not None
        try:
            self.store.save(self.monitor.save_totals())
        except OSError as exc:
            self.ratelog(logging.ERROR, "save", "cannot save state to %s: %s", self.store.path, exc)

    def _status_text(self) -> str:
        s = self.monitor.snapshot()
        c = s["counters"]
        ratio = f"{s['ratio_filt_pct']:.2f} %" if s["ratio_filt_pct"] is not None else "n/a"
        bus = "bus up" if self.bus is not None else "bus down"
        return (
            f"{s['level']} ({s['reason']}), ratio {ratio}, {s['warning_count']} warnings, {bus}; "
            f"frames {c['frames_total']} (inputs {c['accepted']}, bad length {c['bad_length']}, "
            f"out of range {c['out_of_range']}, unknown {c['unknown_id']}, late {c['late']}), "
            f"sent {self.stats['tx_frames']}, dropped {self.stats['tx_dropped']}"
        )

    def _shutdown(self) -> None:
        if self.stop_signal is not None:
            log.info("stopping on %s: saving state", _signal_name(self.stop_signal))
        self.notifier.stopping()
        if self.store is not None:
            self._save()
        if self.uplink is not None:  # issue 15: the period's last summary, then the queue written out
            self.uplink.close(self.monitor, self.stats)
        self._close()
        c = self.monitor.counters
        log.info(
            "stopped: %d frames (%d inputs, %d unknown id, %d bad length, %d out of range), %d sent, %d dropped",
            c["frames_total"],
            c["accepted"],
            c["unknown_id"],
            c["bad_length"],
            c["out_of_range"],
            self.stats["tx_frames"],
            self.stats["tx_dropped"],
        )


def _named(exc: BaseException) -> bool:
    return isinstance(exc, CmcanError)


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"
