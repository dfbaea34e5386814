"""The daemon: the imperative shell around the monitor core on live buses.

It owns its receive loop (python-can's Notifier thread would stop for good on the first receive
error), opens one python-can bus per configured channel, asks the kernel to filter the input
identifiers (11-bit exactly, J1939 on PGN and source address), feeds every frame to the core stamped
with the channel it came from, and sends what the core returns on the channel each frame names, at
the frame's time (a J1939 transport session's packets are spaced in frame time; the daemon sends each
when the bus's time reaches it). Bus errors (network down, a full transmit queue, bus-off) are logged
with rate limits and recovered from by reopening that bus with a growing back-off while the others go
on; no frame and no bus error stops it, and a channel that cannot be opened (not there yet, unplugged)
is such a link down. Under systemd it reports READY, WATCHDOG and STATUS; the watchdog is pinged at
its interval whatever the links do (every wait of the loop ends by the next ping: a daemon retrying its
links is working, a hung loop is what the watchdog is for). SIGTERM and SIGINT stop it cleanly.

Its send schedule waits for no input: each wait of the loop ends by the next output the core has
queued (a transport packet, a delayed Cannot Claim, an answer's BAM) and, while the inputs are silent,
by the next evaluation tick, so periodic frames and answers leave at their frame time whether the
bus is silent, flooded or full of requests. Frame time at a moment of the loop is the wall clock
where the bus stamps frames with it, else (and across a step of the wall clock) the last frame's time
plus the loop's clock since it arrived; the core only ever takes such times. A request or claim for the J1939 node is no
input: it moves frame time on, but not the idle clock that says the inputs are silent. A
reload (SIGHUP, :meth:`Daemon.request_reload`) swaps in a new configuration and model validated by the
caller, between two frames, with the monitor's state carried over. A stop or reload request wakes the
loop from any wait (through a socket pair a signal handler can write to: no lock taken there).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import queue
import select
import signal
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import can

from cmcan.can.frame import Frame, from_message, to_message_kwargs
from cmcan.can.j1939 import ids, transport
from cmcan.config import ChannelConfig, Config
from cmcan.errors import CmcanError
from cmcan.monitor.baseline import MODE_NAMES, Mode
from cmcan.monitor.clock import STEP_BACK_S
from cmcan.monitor.core import Monitor
from cmcan.monitor.inputs import NODE_PFS, InputMessage
from cmcan.service.ratelog import RateLimitedLog
from cmcan.service.sdnotify import Notifier
from cmcan.service.statefile import StateStore, done_baseline_request, read_baseline_request, write_node_status

if TYPE_CHECKING:  # only for the type hint: the uplink's feed is an application beside this one
    from cmcan.uplink.feed import UplinkFeed

log = logging.getLogger("cmcan.daemon")
# A claim sent later than its frame time by less than this was sent by a loop behind its bus: its
# 250 ms count from when it left. More is no lag but a time base the loop cannot compare (a replayed log).
CLAIM_LATE_MAX_S = 1.0

SO_RCVBUFFORCE = 33
SOL_CAN_RAW = 101
CAN_RAW_ERR_FILTER = 2
# Error classes worth hearing about: controller problems, bus-off, restarts after bus-off.
CAN_ERR_MASK = 0x04 | 0x40 | 0x100


WALL_STEP_S = 1.0  # a jump of frame time against boot time beyond this is a wall-clock step
TICK_LAG_S = 1e-5  # a tick on the wall clock is evaluated this long after its time (the core's epsilon)
HOUSEKEEPING_GAP_S = 0.03  # the status line and a save run when no output is due within this
HOUSEKEEPING_WAIT_S = 1.0  # and wait for such a gap at most this long


def _boot_time() -> float:
    return time.clock_gettime(time.CLOCK_BOOTTIME)


@dataclass(frozen=True)
class Reloaded:
    """What a reload brings: the new configuration, its monitor (built and checked) and an opener per
    configured channel (one opener: the configuration's bus.channel), as ``Daemon`` takes them."""

    cfg: Config
    monitor: Monitor
    opens: Callable[[], can.BusABC] | Mapping[str, Callable[[], can.BusABC]]


@dataclass
class _LoopState:
    """What the loop's steps remember between turns (monotonic times; frame times of the bus)."""

    next_wd: float
    next_status: float
    last_save: float
    started: float = 0.0
    saved_ticks: int = -1
    last_rx_wall: float | None = None  # when the last frame arrived (any frame: frame time's anchor)
    last_frame_t: float = math.nan  # and its timestamp
    last_input_wall: float | None = None  # when the last frame that is no node frame arrived
    idle_failed: float = -math.inf  # when the idle step last failed (no wake-up for it for a receive timeout)
    baseline_state: str | None = None  # the on-board baseline's state last said
    save_since: float | None = None  # a save due since then, waiting for a gap in the outputs


@dataclass
class DaemonOptions:
    recv_timeout_s: float = 0.1
    idle_after_s: float = 1.0  # no input frame for this long: advance the core's time on the wall clock
    backoff_min_s: float = 0.5
    backoff_max_s: float = 10.0
    status_every_s: float = 2.0
    send_timeout_s: float = 0.005
    # Frames stamped with the wall clock (a kernel bus): a jump of their time against the boot clock is
    # a step of the wall clock. False where a bus carries a log's own times (the demo's time-lapse).
    stamps_on_wall_clock: bool = True


# frames read from one bus in one go (the loop's other steps run once per batch), before the others
# get their turn
DRAIN = 256
MAX_BATCH = 4096  # several buses: frames read before some go on
J1939_PGN_MASK = 0x03FFFF00  # EDP, DP, PF, PS: the priority and the source address left out
# A filter no real frame matches: a channel that only carries cmcan's outputs receives nothing.
NOTHING = {"can_id": 0, "can_mask": 0x1FFFFFFF, "extended": True}
# cmcan's J1939 node hears every frame the router hands it (NODE_PFS: Request, Address Claimed and TP.CM,
# the CTS and EndOfMsgAck of its connections), whatever the destination and sender: the priority bits
# left out, EDP, DP and PF compared. They are no inputs (they do not hold the idle ticks back).
NODE_FILTERS = [{"can_id": pf << 16, "can_mask": 0x03FF0000, "extended": True} for pf in sorted(NODE_PFS)]
CAN_ERR_BUSOFF, CAN_ERR_RESTARTED = 0x40, 0x100  # error classes (linux/can/error.h)


def can_filters(inputs: Sequence[InputMessage], channel: str) -> list[dict[str, Any]]:
    """Kernel filters for the input messages on ``channel``: 11-bit identifiers exactly; 29-bit ones
    exactly, or for J1939 on the PGN (the priority ignored) and the listed source addresses (or any),
    with the DBC's destination for a PDU1 PGN."""
    out: list[dict[str, Any]] = []
    for m in inputs:
        if m.channel != channel:
            continue
        if not m.extended:
            out.append({"can_id": m.frame_id, "can_mask": 0x7FF, "extended": False})
        elif m.pgn is None:
            out.append({"can_id": m.frame_id, "can_mask": ids.MAX_ID, "extended": True})
        else:
            any_dest = ids.is_pdu1(m.pgn) and m.destinations is None
            dests = sorted(m.destinations) if ids.is_pdu1(m.pgn) and m.destinations is not None else [0]
            pgn_mask = J1939_PGN_MASK & ~0xFF00 if any_dest else J1939_PGN_MASK  # any destination: PS not compared
            for da in dests:
                base = (m.pgn | da) << 8
                if m.sources is None:
                    out.append({"can_id": base, "can_mask": pgn_mask, "extended": True})
                else:
                    out += [
                        {"can_id": base | sa, "can_mask": pgn_mask | 0xFF, "extended": True} for sa in sorted(m.sources)
                    ]
    return out or [NOTHING]


def bus_kwargs(cfg: Config, channel: ChannelConfig, inputs: Sequence[InputMessage]) -> dict[str, Any]:
    """python-can's ``Bus`` arguments for one configured channel (``fd=True`` on a CAN FD bus); on a
    J1939 machine the output channel also lets the node's Requests and Address Claimed through."""
    filters = can_filters(inputs, channel.name)
    if cfg.j1939.enabled and channel.name == cfg.output_channel:
        filters = [f for f in filters if f is not NOTHING] + NODE_FILTERS
    kw: dict[str, Any] = {
        "interface": cfg.bus.interface,
        "channel": channel.name,
        "bitrate": channel.bitrate or cfg.bus.bitrate,
        "can_filters": filters,
        "receive_own_messages": False,
    }
    if channel.fd:
        kw["fd"] = True
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


class Link:
    """One bus the daemon keeps open: its channel name, how to open it, and its back-off."""

    def __init__(self, name: str, open_bus: Callable[[], can.BusABC]) -> None:
        self.name = name
        self.open_bus = open_bus
        self.bus: can.BusABC | None = None
        self.retry_at = -math.inf
        self.backoff_s = 0.0
        self.down_reason = ""  # why the bus is closed, for the status ("" before the first try)
        self.opens = 0  # times it was opened


class Daemon:
    """``open_bus`` opens the configured bus.channel; a mapping of channel name to opener opens each
    configured channel (the first entry is where frames without a channel go)."""

    def __init__(
        self,
        cfg: Config,
        monitor: Monitor,
        store: StateStore | None,
        open_bus: Callable[[], can.BusABC] | Mapping[str, Callable[[], can.BusABC]],
        notifier: Notifier | None = None,
        options: DaemonOptions | None = None,
        clock: Callable[[], float] = time.monotonic,
        uplink: UplinkFeed | None = None,
        boot_clock: Callable[[], float] | None = None,
        sleep: Callable[[float], object] | None = None,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        """``sleep(seconds)`` is how the loop waits when it has nothing to read (every link down): at
        most that long, less when :meth:`stop` or :meth:`request_reload` wake it (the default); tests
        pass one that moves their ``clock`` on."""
        self.cfg = cfg
        self.monitor = monitor
        self.store = store
        self._set_links(open_bus)
        self.notifier = notifier or Notifier(env={})
        self.opt = options or DaemonOptions()
        self.clock = clock
        self.stop_event = threading.Event()
        self.stats = {"bus_opens": 0, "bus_errors": 0, "tx_frames": 0, "tx_dropped": 0, "internal_errors": 0}
        self.ratelog = RateLimitedLog(clock=clock)
        self.save_every_s = cfg.state.save_every_s
        self.uplink = uplink  # queues events and summaries for the outbox; never blocks
        if uplink is not None:  # it hears every tick, and reads the counters of the monitor running now
            uplink.attach(lambda: (self.monitor, self.stats))
            monitor.listeners.append(uplink)
        # Frame time against a clock that neither steps nor stops in suspend: a jump of their
        # difference is the wall clock stepping (the kernel stamps frames with the wall clock).
        self.boot_clock = boot_clock or _boot_time
        self.wall_clock = wall_clock  # what a kernel bus stamps frames with (the idle bus before any frame)
        self._wall_minus_boot: float | None = None
        self._last_stamp: float | None = None
        # Transport packets wait until the configured gap after the packet before has gone out.
        self._tp_gap_s = cfg.j1939.bam_packet_gap_ms / 1000.0
        self._tp_last_sent = -math.inf
        self._tp_waiting: deque[Frame] = deque()
        self.reloader: Callable[[], Reloaded] | None = None  # builds a validated configuration (SIGHUP)
        self._reload_requested = threading.Event()
        self._reloading: threading.Thread | None = None  # a reload being built
        self._reloaded: queue.SimpleQueue[Reloaded | BaseException] = queue.SimpleQueue()  # what it built
        self.stop_signal: int | None = None  # the signal that stopped the daemon, if one did
        # While run() runs, stop() and request_reload() write a byte here to end a wait: safe from a
        # signal handler, where setting a threading.Event could deadlock on the lock the wait holds.
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._sleep = sleep or self._wait
        self.loop = _LoopState(next_wd=clock(), next_status=clock(), last_save=clock())
        self._node_seen: tuple[object, int] = (None, 0)  # the claim whose events were told, and how many

    def _set_links(self, open_bus: Callable[[], can.BusABC] | Mapping[str, Callable[[], can.BusABC]]) -> None:
        opens = dict(open_bus) if isinstance(open_bus, Mapping) else {self.cfg.bus.channel: open_bus}
        self.links = [Link(name, fn) for name, fn in opens.items()]
        self._link_of = {x.name: x for x in self.links}
        self._input_channels = {m.channel or self.cfg.bus.channel for m in self.monitor.inputs}
        self._live: list[Link] = []  # the links whose bus is open
        self._merge: list[tuple[Link, can.Message]] = []  # several buses: read, not yet handed on
        self._mark: dict[str, float] = {}  # per bus, the timestamp of the last frame read
        self._selectable: bool | None = None

    @property
    def bus(self) -> can.BusABC | None:
        """The first channel's bus (None while it is closed)."""
        return self.links[0].bus

    # -- the loop --------------------------------------------------------------------------------------

    def run(self) -> None:
        """The loop: requests first, housekeeping (watchdog, status, state), the links, then a wait
        for frames and their handling, or the idle step; each a method a test can drive."""
        self._start()
        while not self.stop_event.is_set():
            self.handle_requests()
            now = self.clock()
            self.housekeeping(now)
            live = self.links_up(now)
            if not live:
                self.wait_for_links()
                continue
            batch = self.receive(live)
            if batch:
                self.handle_frames(batch)
            if batch is not None:  # (None: the bus failed, and is being reopened)
                self.idle()  # what is due by now goes, flood or silence
        self._shutdown()

    def _start(self) -> None:
        now = self.clock()
        self.loop = _LoopState(next_wd=now, next_status=now, last_save=now, started=now)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_w.setblocking(False)
        self._state_notes()
        self._baseline_request()  # one left while no daemon ran (cmcan baseline reset then writes the state)
        self.notifier.ready(self._status_text())
        log.info("cmcan running on %s %s", self.cfg.bus.interface, ", ".join(x.name for x in self.links))

    def handle_requests(self) -> None:
        """A reload asked for by SIGHUP (signal handlers only set the flag and wake the loop) is built
        off the loop, in a thread: reading files and loading a model, however long they take, must
        not stop the loop answering SIGTERM and the watchdog. What it built is swapped in here,
        between two frames."""
        if self._reload_requested.is_set() and self._reloading is None:
            self._reload_requested.clear()
            self._begin_reload()
        try:
            built = self._reloaded.get_nowait()
        except queue.Empty:
            return
        self._reloading = None
        self._finish_reload(built)
        for x in self.links:  # a reload is also "try again now" (the adapter was just plugged in)
            if x.bus is None:
                x.retry_at = -math.inf

    def housekeeping(self, now: float) -> None:
        """The watchdog ping, the status line, and the state saved: on every warning change at once,
        else periodically while the core evaluates (an idle gateway does not wear its flash
        rewriting unchanged totals)."""
        st = self.loop
        wd_every = self.notifier.watchdog_interval_s
        if wd_every is not None and now >= st.next_wd:
            self.notifier.watchdog()
            st.next_wd = now + wd_every
        # the status line's snapshot and a save take tens of ms on a slow gateway: they wait for a gap
        # before the next output, at most HOUSEKEEPING_WAIT_S (the frames keep their period)
        gap = not self._live or self.until_due(now) >= HOUSEKEEPING_GAP_S  # (no bus: nothing to send)
        if now >= st.next_status and (gap or now >= st.next_status + HOUSEKEEPING_WAIT_S):
            self.notifier.status(self._status_text())
            st.next_status = now + self.opt.status_every_s
        ticks = self.monitor.n_ticks
        changed = self._baseline_news()
        if (
            self.store is not None
            and st.save_since is None
            and (
                changed
                or self.monitor.transitions_since_save
                or (now - st.last_save >= self.save_every_s and ticks != st.saved_ticks)
            )
        ):
            st.save_since = now
        if st.save_since is not None and (gap or now >= st.save_since + HOUSEKEEPING_WAIT_S):
            self._save()
            st.last_save, st.saved_ticks, st.save_since = now, ticks, None

    def _baseline_news(self) -> bool:
        """Say a change of the on-board baseline's state in the journal (a suspect machine as a
        warning, with by how much); True on a change, which is saved at once."""
        bl = self.monitor.baseline
        state = None if bl is None else MODE_NAMES[bl.mode]
        before, self.loop.baseline_state = self.loop.baseline_state, state
        if bl is None or state == before:
            return False
        if bl.mode == Mode.SUSPECT:
            log.warning(
                "baseline_suspect (%s): this machine lies %+.2f l/min from its type model, the part of it that does "
                "not grow with the flow %+.2f l/min (units of the type differ by up to %.2f l/min): the type model "
                "stays its reference; check the drive for a leak or a sensor",
                " and ".join(bl.suspect_by) or "mean",
                bl.distance_lpm,
                bl.pressure_part_lpm,
                bl.p.suspect_lpm,
            )
        elif bl.mode == Mode.MONITORING:
            log.info(
                "baseline learned (%.2f h, %.0f %% of the envelope): monitoring against the machine's own baseline, "
                "%+.2f l/min from its type model",
                bl.learned_h,
                bl.coverage_pct,
                bl.distance_lpm,
            )
        else:
            log.info(
                "baseline learning (%.2f h learned, %.0f %% of the envelope covered)", bl.learned_h, bl.coverage_pct
            )
        return before is not None

    def _until_watchdog(self, now: float) -> float:
        """No wait lasts past the next watchdog ping, whatever the links do."""
        return self.loop.next_wd - now if self.notifier.watchdog_interval_s is not None else math.inf

    def links_up(self, now: float) -> list[Link]:
        """The open links, after trying those whose back-off has passed."""
        return self._live if len(self._live) == len(self.links) else self._open_due(now)

    def wait_for_links(self) -> None:
        """Every link down: wait for the first retry, the next ping or status, or a request."""
        now = self.clock()  # an open that fails may take its time (a USB adapter's driver)
        retry = min(x.retry_at for x in self.links) - now
        wait = min(retry, self.opt.backoff_max_s, self._until_watchdog(now), self.loop.next_status - now)
        self._sleep(max(0.0, wait))

    def receive(self, live: list[Link]) -> Sequence[tuple[Link, can.Message]] | None:
        """The frames that arrived within the receive timeout (shorter while transport packets wait,
        and never past the next output due: :meth:`until_due`); None when the one bus failed."""
        now = self.clock()
        timeout = min(self.opt.recv_timeout_s, self._until_watchdog(now), self.until_due(now))
        if self._tp_waiting:
            timeout = min(timeout, self._tp_last_sent + self._tp_gap_s - now)
        timeout = max(0.0, timeout)  # a ping already due (a loop that fell behind): look, do not wait
        if len(live) > 1:
            return self._receive(live, timeout)
        x = live[0]  # one bus: as it comes, and what has already arrived behind it in one go
        bus = x.bus
        batch: list[tuple[Link, can.Message]] = []
        try:
            msg = bus.recv(timeout=timeout)  # type: ignore[union-attr]
            while msg is not None:
                batch.append((x, msg))
                if len(batch) >= DRAIN:
                    break
                msg = bus.recv(timeout=0)  # type: ignore[union-attr]
        except (can.CanError, OSError, ValueError) as exc:
            self._bus_failed(x, "receive", exc)
            return batch or None  # the frames read before the failure are still handled
        return batch

    def handle_frames(self, batch: Sequence[tuple[Link, can.Message]]) -> None:
        """Each frame to the core, what it returns onto the buses. A frame the core cannot handle is
        counted and logged, never the daemon's end."""
        st = self.loop
        now = self.clock()
        # one read for the batch: its frames were all stamped before it was read
        boot = self.boot_clock() if self.opt.stamps_on_wall_clock else math.nan
        inputs = False
        for link, msg in batch:
            if msg.is_error_frame:
                self.ratelog(
                    logging.WARNING,
                    "errframe",
                    "error frame on %s: id 0x%X data %s",
                    link.name,
                    msg.arbitration_id,
                    bytes(msg.data).hex(),
                )
                if msg.arbitration_id & CAN_ERR_RESTARTED and link.name == self.cfg.output_channel:
                    self._node_start(msg.timestamp, "controller restarted after bus-off")
            try:
                out = self._feed(link, msg, st.last_frame_t, boot)
            except Exception:  # the core must never take the daemon down: log, count, go on
                self._internal_error()
                out = []
            if out or self._tp_waiting:
                self._send(out)
            st.last_rx_wall = now
            st.last_frame_t = msg.timestamp
            inputs = inputs or not (msg.is_extended_id and ids.pdu_format(msg.arbitration_id) in NODE_PFS)
        if inputs:  # a request is no input: the idle clock runs on; a long batch is no silence
            st.last_input_wall = self.clock()
        if self.monitor.node is not None:
            self._node_news()

    def _feed(self, link: Link, msg: can.Message, last_frame_t: float, boot_s: float) -> list[Frame]:
        if self.opt.stamps_on_wall_clock:
            self._watch_wall_clock(msg.timestamp, boot_s)
        mon = self.monitor
        counts = mon.clock.counts  # (Monitor.clock_steps, without a property call per frame)
        steps = counts["clock_steps"]
        out = mon.feed(from_message(msg, link.name))
        if counts["clock_steps"] != steps:  # the core found a step back
            log.warning(
                "the wall clock stepped back by %.3f s; monitoring goes on on the new time base",
                last_frame_t - msg.timestamp,
            )
        return out

    def frame_now(self, now: float) -> float:
        """Frame time at the loop's clock ``now``: the wall clock where the bus stamps frames with it,
        else (and across a step of the wall clock) the last frame's time plus the time since it came;
        before any frame the time the bus would stamp one with (NaN where that is no wall clock)."""
        st = self.loop
        wall = self.wall_clock() if self.opt.stamps_on_wall_clock else math.nan
        if st.last_rx_wall is None or not math.isfinite(st.last_frame_t):
            return wall
        est = st.last_frame_t + (now - st.last_rx_wall)
        # the bus stamps with the wall clock: read it (no jitter of when a batch was handled), unless it
        # stepped since the last frame (that frame's step check moves the monitor; until then, the estimate)
        return wall if abs(wall - est) < WALL_STEP_S else est

    def inputs_silent(self, now: float) -> bool:
        """No input frame for ``idle_after_s`` (requests and claims do not count): ticks then come
        from the wall clock."""
        st = self.loop
        return now - (st.last_input_wall if st.last_input_wall is not None else st.started) >= self.opt.idle_after_s

    def until_due(self, now: float) -> float:
        """Seconds of the loop's clock until the next output is due: the core's next queued frame,
        and while the inputs are silent its next tick (until then, the moment they fall silent)."""
        st = self.loop
        if now < st.idle_failed + self.opt.recv_timeout_s:  # a core that fails: not woken again at once
            return st.idle_failed + self.opt.recv_timeout_s - now
        due = self.monitor.next_due_t
        if self.inputs_silent(now):
            clock = self.monitor.clock  # no tick yet: the first idle step starts the tick clock
            due = min(due, clock.next_k * clock.period + TICK_LAG_S if clock.next_k is not None else -math.inf)
            silence = math.inf
        else:
            since = st.last_input_wall if st.last_input_wall is not None else st.started
            silence = since + self.opt.idle_after_s - now
        t = self.frame_now(now)
        return max(0.0, min(silence, due - t if t == t else math.inf))

    def idle(self) -> None:
        """After every receive: while no input frame came for ``idle_after_s`` time goes on in the
        core on the wall clock (ticks keep coming on a silent bus), and the queued output frames due
        by now go out (transport packets, a delayed Cannot Claim), whatever else arrives."""
        now = self.clock()
        t = self.frame_now(now)
        out: list[Frame] = []
        try:
            if self.inputs_silent(now):
                out = self.monitor.advance(t)
            if t == t and self.monitor.next_due_t <= t:
                out += self.monitor.due(t)
        except Exception:
            self.loop.idle_failed = now
            self._internal_error()
        if out or self._tp_waiting:
            self._send(out)
        if self.monitor.node is not None:
            self._node_news()

    def _watch_wall_clock(self, frame_t: float, boot_s: float) -> None:
        """A step of the wall clock forward moves the monitor onto the new time base (a step back the
        core finds by itself); otherwise it would look like the machine had been off that long.

        Frame time minus boot time is steady while frames are handled as they come; frames handled
        late (a backlog after a stall) make it dip and then come back, never rise above where it
        was. So a step is a rise above the highest value seen since the last step back of the frames'
        own time (where the core re-bases and the reference starts anew). ``boot_s`` is the boot
        clock when the frame's batch was read."""
        diff = frame_t - boot_s
        if not math.isfinite(diff):
            return
        ref, last = self._wall_minus_boot, self._last_stamp
        self._last_stamp = frame_t
        if ref is None or (last is not None and frame_t < last - STEP_BACK_S):
            self._wall_minus_boot = diff
            return
        if diff - ref > WALL_STEP_S:
            log.warning("the wall clock stepped forward by %.3f s; monitoring goes on on the new time base", diff - ref)
            self.monitor.shift_time(diff - ref)
        if diff > ref:
            self._wall_minus_boot = diff

    def stop(self, signum: int | None = None) -> None:
        """Stop after the current step (safe from a signal handler); the state is saved on the way out."""
        if signum is not None and self.stop_signal is None:
            self.stop_signal = signum
        self.stop_event.set()
        self._wake()

    def _wake(self) -> None:
        """End the loop's current wait (from any thread or a signal handler)."""
        w = self._wake_w
        if w is not None:  # before run(), the flags alone do: the loop looks at them first
            with contextlib.suppress(OSError):  # bytes already waiting (buffer full), or the loop has ended
                w.send(b"!")

    def _wait(self, seconds: float) -> None:
        """Sleep up to ``seconds``, less if woken; the wake-ups that came meanwhile are used up."""
        r = self._wake_r
        if r is None:  # not running
            self.stop_event.wait(seconds)
            return
        with contextlib.suppress(OSError):  # TimeoutError: nobody woke it
            r.settimeout(max(0.0, seconds))
            r.recv(4096)

    def _internal_error(self) -> None:
        self.stats["internal_errors"] += 1
        self.ratelog(logging.ERROR, "internal", "internal error processing a frame", exc_info=True)

    # -- reload ----------------------------------------------------------------------------------------

    def request_reload(self) -> None:
        """Reload between two frames, at once if the loop is waiting (safe from a signal handler: it
        sets a flag and writes a byte)."""
        self._reload_requested.set()
        self._wake()

    @property
    def reload_pending(self) -> bool:
        """A reload asked for and not yet swapped in (or refused)."""
        return self._reload_requested.is_set() or self._reloading is not None

    def _begin_reload(self) -> None:
        if self.reloader is None:
            log.warning("reload requested, but this daemon has nothing to reload from")
            return
        self.notifier.reloading()
        reloader = self.reloader

        def build() -> None:
            try:
                built: Reloaded | BaseException = reloader()
            except Exception as exc:  # said by the loop, which goes on with the running configuration
                built = exc
            self._reloaded.put(built)
            self._wake()

        self._reloading = threading.Thread(target=build, name="cmcan-reload", daemon=True)
        self._reloading.start()

    def _finish_reload(self, new: Reloaded | BaseException) -> None:
        """Swap in the configuration and model the reloader built and checked; if it could not (a bad
        file, a model that does not fit), say why and go on with the running ones."""
        if isinstance(new, BaseException):  # a CmcanError names the file and field; anything else is a bug
            log.error(
                "reload failed, running on with the previous configuration: %s",
                new,
                exc_info=(type(new), new, new.__traceback__) if not _named(new) else None,
            )
            self._baseline_request()  # a reset waiting for this reload needs no new configuration
            self.notifier.ready(self._status_text())
            return
        old_cfg, old_mon = self.cfg, self.monitor
        afresh = new.monitor.take_over(old_mon)
        self.cfg, self.monitor = new.cfg, new.monitor
        self.save_every_s = new.cfg.state.save_every_s
        self._tp_gap_s = new.cfg.j1939.bam_packet_gap_ms / 1000.0
        kept = []
        if new.cfg.state.directory != old_cfg.state.directory:
            kept.append(f"state.directory stays {old_cfg.state.directory} until a restart")
        if new.cfg.uplink != old_cfg.uplink:
            kept.append("the uplink settings take effect at a restart")
        buses_same = new.cfg.bus == old_cfg.bus and new.cfg.channel_list == old_cfg.channel_list
        if not buses_same or list(new.monitor.inputs) != list(old_mon.inputs):
            for x in self.links:  # reopened by the loop with the new settings and kernel filters
                self._close(x)
            self._set_links(new.opens)
            afresh.append("the bus connections (new bus settings or input identifiers)")
        log.info(
            "reloaded %s: totals, warning state, filter and counters kept; started afresh: %s%s",
            new.cfg.source,
            "; ".join(afresh) or "nothing",
            "".join(f"; {k}" for k in kept),
        )
        self._state_notes()
        self._baseline_request()
        self.notifier.ready(self._status_text())

    def _state_notes(self) -> None:
        """What of the saved state the monitor does not go on with though the file is sound (a damaged
        file is kept aside and said as it is read): the baseline learning afresh under a changed
        envelope, the prognosis beginning a new history. Said once, where it happens."""
        pg = self.monitor.prognosis
        for part, note in (("baseline", self.monitor.baseline_note), ("prognosis", pg.note if pg else None)):
            if note:
                where = self.store.path if self.store is not None else "the saved state"
                log.warning("%s: %s: %s", where, part, note)

    def _baseline_request(self) -> None:
        """A baseline reset ``cmcan baseline reset`` left in the state directory (it then asks for a
        reload): carried out by this, the state's only writer, and saved at once."""
        if self.store is None:
            return
        req = read_baseline_request(self.store.dir)
        if req is None:
            return
        if req.get("bad"):
            log.error("baseline reset not carried out: %s", req["reason"])
        elif self.monitor.reset_baseline(req["reason"], req["at"] or None):
            log.info("baseline reset (%s): learning afresh, the old baseline kept in the history", req["reason"])
            self._save()
        else:
            log.error("baseline reset asked for, but the configuration has no baseline section enabled")
        done_baseline_request(self.store.dir)  # after the save: the waiting command reads the state next

    # -- bus handling ----------------------------------------------------------------------------------

    def _open_due(self, now: float) -> list[Link]:
        """The open links, after trying to open those whose back-off has passed."""
        for x in self.links:
            if x.bus is None and now >= x.retry_at and not self._open(x):
                x.backoff_s = min(max(x.backoff_s * 2, self.opt.backoff_min_s), self.opt.backoff_max_s)
                x.retry_at = now + x.backoff_s
        self._live = [x for x in self.links if x.bus is not None]
        return self._live

    def _receive(self, live: list[Link], timeout: float) -> list[tuple[Link, can.Message]]:
        """The frames several buses received, merged in order of their timestamps.

        The buses are read in turns until a whole turn finds every one empty: a frame still to come
        then arrived after all those read, so none becomes late because another bus was read first.
        Under a backlog (MAX_BATCH frames read) only the frames up to the newest one read from each
        bus that carries inputs go on; the rest wait for the next call."""
        held = self._merge
        if not held:
            if self._selectable is None:
                self._selectable = all(_fileno(x.bus) is not None for x in live)
            if self._selectable:
                try:
                    r, _, _ = select.select([_fileno(x.bus) for x in live], [], [], timeout)
                except (OSError, ValueError):
                    r = [1]
                if not r:
                    return []
        total, capped = 0, False
        while True:
            n = 0
            for x in live:
                if x.bus is None:
                    continue
                try:
                    for _ in range(DRAIN):
                        msg = x.bus.recv(timeout=0)
                        if msg is None:
                            break
                        held.append((x, msg))
                        self._mark[x.name] = msg.timestamp
                        n += 1
                except (can.CanError, OSError, ValueError) as exc:
                    self._bus_failed(x, "receive", exc)
            total += n
            if n == 0:
                break
            if total >= MAX_BATCH:
                capped = True
                break
        if not held:
            if not self._selectable:
                self._sleep(min(timeout, 0.002))  # buses without a file descriptor: poll
            return []
        held.sort(key=lambda p: p[1].timestamp)
        if not capped:
            self._merge = []
            return held
        marks = [self._mark.get(x.name, math.inf) for x in live if x.name in self._input_channels]
        horizon = min(marks) if marks else math.inf
        cut = next((i for i, (_, m) in enumerate(held) if m.timestamp > horizon), len(held))
        self._merge = held[cut:]
        return held[:cut]

    def _open(self, x: Link) -> bool:
        try:
            x.bus = x.open_bus()
        except (can.CanError, OSError, ValueError) as exc:
            self.stats["bus_errors"] += 1
            x.down_reason = f"cannot open: {_short(exc)}"
            self.ratelog(
                logging.WARNING,
                f"open-{x.name}",
                "cannot open the bus %s (%s); retrying with a back-off of up to %g s",
                x.name,
                exc,
                self.opt.backoff_max_s,
            )
            self.notifier.status(self._status_text())
            return False
        self.stats["bus_opens"] += 1
        self._selectable = None
        x.backoff_s = 0.0
        x.down_reason = ""
        x.opens += 1
        if self.stats["bus_opens"] > len(self.links):
            log.info("bus %s reopened", x.name)
        if x.name == self.cfg.output_channel and x.opens > 1:  # the J1939 node claims again when the link is back
            t = self.wall_clock() if self.opt.stamps_on_wall_clock else math.nan
            self._node_start(t, "link back")
        self.notifier.status(self._status_text())
        return True

    def _node_start(self, t: float, why: str) -> None:
        """The J1939 node's address claim at frame time ``t`` when the output link is back or the
        controller restarted after a bus-off. At the start the core claims by itself, at the first
        frame (or the first idle step on a silent bus): at the time a replay of the same frames
        claims, and before anything else goes out."""
        if self.monitor.node is None or not math.isfinite(t):
            return
        try:
            out = self.monitor.start(t, why)
        except Exception:
            self._internal_error()
            return
        self._send(out)
        self._node_news()

    def _node_news(self) -> None:
        """The node's claim events since the last call: into the journal and the state directory's
        node file (which ``cmcan uplink`` puts into its health messages)."""
        node = self.monitor.node
        c = node.claim if node is not None else None
        if c is None or not c.events or (c.n_events == self._node_seen[1] and c is self._node_seen[0]):
            return  # no claim yet (no NAME, or before the first frame), or nothing new
        seen = self._node_seen[1] if c is self._node_seen[0] else 0
        for e in c.events[-min(c.n_events - seen, len(c.events)) :]:
            _log_claim(e, c.name_value)
        self._node_seen = (c, c.n_events)
        if self.store is not None:
            try:
                write_node_status(self.store.dir, node.describe() | {"t_s": c.events[-1].t_s})  # type: ignore[union-attr]
            except OSError as exc:
                self.ratelog(logging.WARNING, "node-file", "cannot write the J1939 node file: %s", exc)

    def _close(self, x: Link) -> None:
        if x.bus is not None:
            try:
                x.bus.shutdown()
            except Exception as exc:  # a failing shutdown of a dead bus is expected
                log.debug("bus shutdown: %s", exc)
            x.bus = None
            self._selectable = None
            self._live = [y for y in self.links if y.bus is not None]

    def _bus_failed(self, x: Link, what: str, exc: BaseException) -> None:
        self.stats["bus_errors"] += 1
        code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
        hint = " (network down)" if code == errno.ENETDOWN else ""
        self.ratelog(
            logging.WARNING, f"fail-{what}-{x.name}", "bus %s %s failed%s: %s; reopening", x.name, what, hint, exc
        )
        self._close(x)
        x.down_reason = f"{what} failed: {_short(exc)}"
        self.notifier.status(self._status_text())
        x.backoff_s = min(max(x.backoff_s * 2, self.opt.backoff_min_s), self.opt.backoff_max_s)
        x.retry_at = self.clock() + x.backoff_s

    def _send(self, frames: list[Frame]) -> None:
        """Send each frame on its channel. A J1939 transport packet (TP.CM, TP.DT) goes out at its frame
        time but never sooner than ``bam_packet_gap_ms`` after the one before: when a tick was late, the
        rest of its session moves with it, so the packets keep J1939-21's spacing on the wire."""
        now = self.clock()
        claim = self.monitor.node.claim if self.monitor.node is not None else None
        claiming = claim is not None and claim.claiming
        for f in frames:
            if _is_transport(f):
                self._tp_waiting.append(f)
                continue
            self._send_one(f)
            if claiming and claim is not None:  # J1939-81's 250 ms run from when the claim was on the bus
                late = self.frame_now(now) - f.timestamp_s
                if 0.0 < late < CLAIM_LATE_MAX_S:  # a loop behind its bus; not a frame time of another base
                    claim.on_air(f.timestamp_s + late, f)
        while self._tp_waiting and now >= self._tp_last_sent + self._tp_gap_s:
            self._send_one(self._tp_waiting.popleft())
            self._tp_last_sent = now = self.clock()

    def _send_one(self, f: Frame) -> None:
        x = self._link_of.get(f.channel, self.links[0]) if f.channel else self.links[0]
        if x.bus is None:
            self.stats["tx_dropped"] += 1
            return
        kwargs = to_message_kwargs(f)
        kwargs["channel"] = x.name  # the link it goes out on
        msg = can.Message(**kwargs)
        try:
            x.bus.send(msg, timeout=self.opt.send_timeout_s)
            self.stats["tx_frames"] += 1
        except (can.CanError, OSError) as exc:
            self.stats["tx_dropped"] += 1
            code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
            if code in (errno.ENETDOWN, errno.ENODEV, errno.EBADF):
                self._bus_failed(x, "send", exc)
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
        if len(self.links) == 1:
            bus = f"bus {_updown(self.links[0])}"
        else:
            bus = ", ".join(f"{x.name} {_updown(x)}" for x in self.links)
        health = "".join(
            f", {k.replace('_', ' ')} {c[k]}"
            for k in (
                "checksum",
                "counter_frozen",
                "counter_jump",
                "counter_not_available",
                "checksum_not_available",
                "timeout",
                "bad_fd",
                "unknown_channel",
            )
            if c[k]
        )
        node = self.monitor.node
        if node is not None and node.claim is not None:
            a = node.address
            bus += f", J1939 {node.state}" + (f" 0x{a:02X}" if a is not None else "")
        if node is not None:  # a flood of requests: what was not answered (the global rate, the bound)
            dm = self.monitor.dm1_producer
            refused, dropped = node.limit.refused_global, dm.dropped if dm is not None else 0
            if refused or dropped:
                bus += f", answers refused {refused} (rate), dropped {dropped} (queue)"
        return (
            f"{s['level']} ({s['reason']}), ratio {ratio}, {s['warning_count']} warnings, {bus}; "
            f"frames {c['frames_total']} (inputs {c['accepted']}, bad length {c['bad_length']}, "
            f"out of range {c['out_of_range']}, unknown {c['unknown_id']}, late {c['late']}){health}, "
            f"sent {self.stats['tx_frames']}, dropped {self.stats['tx_dropped']}"
        )

    @property
    def links_down(self) -> list[str]:
        """The channels whose bus is not open (not there yet, lost, waiting for their retry)."""
        return [x.name for x in self.links if x.bus is None]

    def _shutdown(self) -> None:
        if self.stop_signal is not None:
            log.info("stopping on %s: saving state", _signal_name(self.stop_signal))
        self.notifier.stopping()
        if self.store is not None:
            self._save()
        if self.uplink is not None:  # the period's last summary, then the queue written out
            self.uplink.close()
        for x in self.links:
            self._close(x)
        for sock in (self._wake_r, self._wake_w):
            if sock is not None:
                sock.close()
        c = self.monitor.counters
        log.info(
            "stopped: %d frames (%d inputs, %d unknown id, %d bad length, %d out of range, %d checksum, "
            "%d counter frozen, %d counter jump), %d sent, %d dropped",
            c["frames_total"],
            c["accepted"],
            c["unknown_id"],
            c["bad_length"],
            c["out_of_range"],
            c["checksum"],
            c["counter_frozen"],
            c["counter_jump"],
            self.stats["tx_frames"],
            self.stats["tx_dropped"],
        )


def _log_claim(e: Any, mine: int) -> None:
    """One J1939 address-claim event in the journal: a loss is a warning (cmcan goes silent)."""
    addr = f"0x{e.address:02X}" if e.address is not None else "none"
    if e.state == "lost":
        log.warning(
            "J1939: cannot claim an address (%s; NAME %s won, cmcan's is 0x%016X): Cannot Claim sent, cmcan sends "
            "nothing more until its link comes back or it restarts",
            e.detail,
            f"0x{e.by_name:016X}" if e.by_name is not None else "?",
            mine,
        )
    elif e.state == "claiming":
        log.info("J1939: claiming address %s with NAME 0x%016X (%s)", addr, mine, e.detail)
    else:
        log.info("J1939: address %s claimed (%s)", addr, e.detail)


def _is_transport(f: Frame) -> bool:
    return f.extended and ids.pdu_format(f.arbitration_id) in (transport.PGN_TP_CM >> 8, transport.PGN_TP_DT >> 8)


def _fileno(bus: Any) -> int | None:
    try:
        fd = bus.fileno()
    except (NotImplementedError, AttributeError, OSError, ValueError):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


def _updown(x: Link) -> str:
    if x.bus is not None:
        return "up"
    return f"down ({x.down_reason})" if x.down_reason else "down"


def _short(exc: BaseException) -> str:
    """An exception on one line for the status (systemctl status shows one line)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 80 else text[:77] + "..."


def _named(exc: BaseException) -> bool:
    return isinstance(exc, CmcanError)


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"
