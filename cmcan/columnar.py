"""The columnar replay engine: a log in chunks of arrays through the monitor, with the output the
streaming core (the daemon's) gives, byte for byte.

It drives the very :class:`~cmcan.monitor.core.Monitor` the streaming engine drives. A chunk of frames
is split into *regular stretches* — input frames whose times move forward without gaps, time
resets or unreadable stamps — and the frames between them. A stretch is done with array
operations: its frames are decoded per message, the tick clock's decisions follow from running
maxima, each tick's window sums from prefix sums of the exact integer raw values (the window's front
from the running maximum of sample times, as a deque trimmed from the front has it), the gate for
all ticks at once, the model in one batched call, the filter from exact integer sums, and then only
the warning state machine runs tick by tick. The monitor's state is written back at the end of the
stretch, and an irregular frame goes through ``Monitor.feed`` itself: where the two engines could
differ, they are the same code.

The model is the one place where the engines may differ in the last bits: onnxruntime's kernels
round a row of a batch and a row alone alike only to about 1e-15 relative, far below anything the
outputs carry (0.01 % ratio resolution, three decimals in the timeline).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import NDArray

from cmcan import codec
from cmcan.checksums import TSC1_FOLD, crc8_ok, id_sum
from cmcan.frame import Frame, FrameColumns
from cmcan.monitor.clock import STEP_BACK_S
from cmcan.monitor.core import _HIGH, _LOW, _MISS, _WINDOW, Monitor, _Input
from cmcan.monitor.exactsum import window_fsums
from cmcan.monitor.gating import EVALUATED, Gate, gate_columns, predictions_ok
from cmcan.monitor.health import CHECKSUM, COUNTER_FROZEN, COUNTER_JUMP, OK, OUT_OF_RANGE, REASONS, Stream
from cmcan.monitor.payloads import OutputMessage
from cmcan.monitor.tick import LEVEL_NAMES, Tick
from cmcan.monitor.warnings import Level, Reason, add_repeat
from cmcan.monitor.windows import TIME_EPS_S, Affine, RoleWindow, mean_std
from cmcan.replay import CHUNK_TICKS, NoFrames, ReplaySummary, Sink, TickColumns, summarize
from cmcan.roles import DP, MODEL_INPUTS

_EVALUATED = np.array(sorted(int(g) for g in EVALUATED), dtype=np.int8)

_I64_SAFE = 1 << 20  # raw values below this: window sums and n*S2 - S1^2 stay exact in int64
_TSC1_FOLD = np.array(TSC1_FOLD, dtype=np.uint8)
# why a frame matched no input message (``_Engine._match``); 0 and up: the message's index
_UNKNOWN_ID, _UNKNOWN_CHANNEL, _BAD_FD, _NOT_DATA = -1, -2, -3, -4


# -- the engine ---------------------------------------------------------------------------------------


def replay_columns(monitor: Monitor, chunks: Iterable[FrameColumns], sinks: Sequence[Sink] = ()) -> ReplaySummary:
    """Replay chunks of frames through ``monitor``: the same ticks, frames and totals as
    :func:`cmcan.replay.replay` over the same frames one by one."""
    eng = _Engine(monitor, sinks)
    first = last = None
    try:
        for cols in chunks:
            if not len(cols):
                continue
            if first is None:
                first = float(cols.timestamp_s[0])
                for s in sinks:
                    s.start(first)
            last = float(cols.timestamp_s[-1])
            eng.chunk(cols)
        if first is None:
            raise NoFrames("no frames in the log")
        eng.scalar_out(monitor.flush())
        eng.drain()
    except BaseException:
        for s in sinks:
            s.abort()
        raise
    for s in sinks:
        s.close()
    return summarize(monitor, first, last, eng.n_frames_out)


class _Engine:
    def __init__(self, monitor: Monitor, sinks: Sequence[Sink]) -> None:
        self.m = monitor
        self.sinks = sinks
        self.want_ticks = any(s.wants_ticks for s in sinks)
        self.want_frames = any(s.wants_frames for s in sinks)
        monitor.keep_timeline = self.want_ticks
        self.n_frames_out = 0
        self.pending_frames: list[FrameColumns] = []  # in order: scalar pieces and stretches
        self._scalar_frames: list[Frame] = []  # from the streaming path, not yet a piece
        # the mapped input messages as the core holds them, and per message the (role or None, kind)
        # of each decoded value as the core routes them, and each value's raw range
        self.inps = list(monitor._inputs.values())
        roles_of = {id(w): r for r, w in monitor.windows.items()}
        self.targets = [[(roles_of.get(id(w)) if w is not None else None, k) for w, k in x.plan] for x in self.inps]
        self.bounds = [[codec.raw_bounds(lay) for lay in x.spec.layouts] for x in self.inps]
        self._index = {id(x): j for j, x in enumerate(self.inps)}
        # matching results of the log so far: sorted keys (channel, format, identifier) and codes
        self._m_keys = np.empty(0, dtype=np.int64)
        self._m_codes = np.empty(0, dtype=np.int64)
        self._m_names: tuple[str, ...] = ()
        self._low_after: int | None = None

    # -- output plumbing ------------------------------------------------------------------------------

    def scalar_out(self, frames: list[Frame]) -> None:
        """Frames (and ticks on the monitor's timeline) from the streaming path, in order: gathered
        into chunks as the streaming replay does (a sink per tick would cost more than the tick)."""
        if self.want_frames and frames:
            self._scalar_frames.extend(frames)
        if len(self.m.timeline) >= CHUNK_TICKS or len(self._scalar_frames) >= 3 * CHUNK_TICKS:
            self.flush_scalar()

    def flush_scalar(self) -> None:
        """What the streaming path gathered goes on, before anything the array path makes."""
        if self._scalar_frames:
            self.pending_frames.append(FrameColumns.from_frames(self._scalar_frames))
            self._scalar_frames = []
        self.drain_timeline()

    def drain_timeline(self) -> None:
        tl = self.m.timeline
        if tl:
            chunk = TickColumns.from_ticks(tl)
            tl.clear()
            self._push_ticks(chunk)

    def _push_ticks(self, chunk: TickColumns) -> None:
        self._push_frames()
        for s in self.sinks:
            if s.wants_ticks:
                s.ticks(chunk)

    def _push_frames(self) -> None:
        if self.pending_frames:
            for piece in self.pending_frames:
                self.n_frames_out += len(piece)
                for s in self.sinks:
                    if s.wants_frames:
                        s.frames(piece)
            self.pending_frames = []

    def drain(self) -> None:
        self.flush_scalar()
        self._push_frames()

    # -- a chunk --------------------------------------------------------------------------------------

    def chunk(self, cols: FrameColumns) -> None:
        m = self.m
        c = m.counters
        n = len(cols)
        err, rtr = cols.error, cols.remote
        live = ~(err | rtr)
        which = self._match(cols, live)
        mapped = which >= 0
        need_len = np.array([x.length for x in self.inps], dtype=np.int64)[np.where(mapped, which, 0)]
        good_len = mapped & (cols.dlc >= need_len)
        short = mapped & ~good_len
        # frames that never reach the clock: counted in bulk (their order does not matter)
        c["frames_total"] += int(n - good_len.sum())
        c["error_frame"] += int(err.sum())
        c["remote_frame"] += int((rtr & ~err).sum())
        c["unknown_channel"] += int(np.count_nonzero(which == _UNKNOWN_CHANNEL))
        c["bad_fd"] += int(np.count_nonzero(which == _BAD_FD))
        c["unknown_id"] += int(np.count_nonzero(which == _UNKNOWN_ID))
        if short.any():
            c["bad_length"] += int(short.sum())
            for j, cnt in enumerate(np.bincount(which[short], minlength=len(self.inps)).tolist()):
                if cnt:
                    self.inps[j].stream.counts["bad_length"] += cnt
        idx = np.flatnonzero(good_len)
        if not len(idx):
            return
        t = cols.timestamp_s[idx]
        ids = which[idx]
        del which, need_len, good_len, short, mapped, live  # (a chunk's peak memory)
        groups = _groups(ids, len(self.inps))
        raws, ok, row, ctr, cs_ok = self._decode(cols, idx, groups)
        pos = 0
        while pos < len(idx):
            if m.clock.next_k is None or not math.isfinite(t[pos]):
                self._scalar(cols, int(idx[pos]))
                pos += 1
                continue
            end = self._stretch(t, groups, raws, row, ok, ctr, cs_ok, pos)
            if end == pos:  # the first frame is irregular: the streaming core takes it
                self._scalar(cols, int(idx[pos]))
                pos += 1
            else:
                pos = end

    def _match(self, cols: FrameColumns, live: NDArray[np.bool_]) -> NDArray[np.int64]:
        """Each frame's input message (its index in ``inps``) or why none (a negative code), by the
        core's own matching (:mod:`cmcan.monitor.inputs`, memoized in the monitor as ``feed`` does):
        a pure function of channel, identifier, format and FD flag, so asked once per combination.
        Error and remote frames are left unmatched (the core counts them before matching)."""
        which = np.full(len(cols), _NOT_DATA, dtype=np.int64)
        sel: NDArray[np.int64] | slice = slice(None) if live.all() else np.flatnonzero(live)
        key = cols.arbitration_id[sel].astype(np.int64)
        if not len(key):
            return which
        # the key's other parts where a frame has them (the usual chunk: one channel, classic frames)
        for part, shift in ((cols.extended, 29), (cols.fd, 30), (cols.channel, 31)):
            if part.any():
                key |= part[sel].astype(np.int64) << shift
        names = cols.channel_names
        if names[: len(self._m_names)] != self._m_names:  # channel codes mean other names now
            self._m_keys, self._m_codes = np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
        self._m_names = names
        at = np.searchsorted(self._m_keys, key)
        hit = self._m_keys[np.minimum(at, len(self._m_keys) - 1)] == key if len(self._m_keys) else at < 0
        if not hit.all():  # combinations not seen before in this log: ask the core's matching
            new = _distinct(key[~hit])
            codes = np.array([self._code(k, names) for k in new.tolist()], dtype=np.int64)
            keys = np.concatenate([self._m_keys, new])
            order = np.argsort(keys, kind="stable")
            self._m_keys, self._m_codes = keys[order], np.concatenate([self._m_codes, codes])[order]
            at = np.searchsorted(self._m_keys, key)
        which[sel] = self._m_codes[at]
        return which

    def _one_id(self, x: _Input) -> int | None:
        """The identifier of every frame matched to ``x`` so far, when there is only one (a sender
        that kept its address), from the table of matched combinations."""
        keys = self._m_keys[self._m_codes == self._index[id(x)]]
        if len(keys) and bool((keys & 0x1FFFFFFF == keys[0] & 0x1FFFFFFF).all()):
            return int(keys[0] & 0x1FFFFFFF)
        return None

    def _code(self, key: int, names: tuple[str, ...]) -> int:
        m = self.m
        fid, ext, fd, name = key & 0x1FFFFFFF, bool(key >> 29 & 1), bool(key >> 30 & 1), names[key >> 31]
        ch = m._chans.get(name) or m._channel(name)
        if ch.index < 0:
            return _UNKNOWN_CHANNEL
        if fd and not ch.fd:
            return _BAD_FD
        inp = (ch.ext if ext else ch.std).get(fid, _MISS)
        if inp is _MISS:
            inp = m._lookup(ch, fid, ext)
        return _UNKNOWN_ID if inp is None else self._index[id(inp)]

    def _scalar(self, cols: FrameColumns, i: int) -> None:
        self.scalar_out(self.m.feed(cols.frame(i)))

    def _decode(
        self, cols: FrameColumns, idx: NDArray[np.int64], groups: list[NDArray[np.int64]]
    ) -> tuple[
        dict[int, list[NDArray[np.int64]]], NDArray[np.bool_], NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]
    ]:
        """Per input message the raw values (one array per value, over its frames), the DBC range
        check per frame (on the raw values, as the core's decoder checks them), each frame's row in
        its message's arrays, and its message counter and checksum verdict (:meth:`_integrity`).
        ``groups``: each input message's frames (:func:`_groups`)."""
        ok = np.ones(len(idx), dtype=bool)
        row = np.zeros(len(idx), dtype=np.int64)
        ctr = np.zeros(len(idx), dtype=np.int64)
        cs_ok = np.ones(len(idx), dtype=bool)
        raws: dict[int, list[NDArray[np.int64]]] = {}
        for j, x in enumerate(self.inps):
            sel = groups[j]
            if not len(sel):
                continue
            spec = x.spec
            rows = idx[sel]
            data = self._payloads(cols, rows, max(spec.size, x.spec.health.nbytes))
            vals = codec.extract_all(data[:, : spec.size], spec.layouts, spec.size)
            good = np.ones(len(sel), dtype=bool)
            for v, (lo, hi) in zip(vals, self.bounds[j], strict=True):
                good &= (lo <= v) & (v <= hi)
            ok[sel] = good
            row[sel] = np.arange(len(sel))
            raws[j] = vals
            if x.checked:
                ctr[sel], cs_ok[sel] = self._integrity(cols, rows, x, data)
        return raws, ok, row, ctr, cs_ok

    def _integrity(
        self, cols: FrameColumns, rows: NDArray[np.int64], x: _Input, data: NDArray[np.uint8]
    ) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """The message counter (0 where none) and whether the checksum holds (True where none) of
        each frame of one checked message, pure functions of the frame, as
        :meth:`cmcan.monitor.health.Stream.check` reads them. ``data``: the frames' payloads (the
        message's bytes: a frame longer than its message is checked on those, as in the core)."""
        n = len(rows)
        st, spec = x.stream, x.spec.health
        # a TSC1 message is 8 bytes long (the core's length check passed): its checksum covers those 8,
        # the first 8 of any CAN FD frame padded beyond them (``data`` holds them)
        if st.tsc1:
            # J1939-71's TSC1 layout: counter and checksum in byte 8, the sum over the message and the id
            d7 = data[:, 7]
            words = (
                data if data.shape[1] == 8 and data.flags.c_contiguous else np.ascontiguousarray(data[:, :8])
            ).view("<u8")[:, 0]
            # bytes 1-7, the counter (the low half of byte 8) and the identifier's four bytes
            s = byte_sums(words, 0x0FFF_FFFF_FFFF_FFFF)
            one_id = self._one_id(x)
            if one_id is not None:  # one identifier matched to this message so far: one sum
                s += np.uint64(id_sum(one_id))
            else:
                s += byte_sums(cols.arbitration_id[rows])
            cs_ok = (d7 >> 4) == _TSC1_FOLD[s.view(np.int64)]  # a signed index gathers ~3x faster
            ctr = d7 & 0x0F
            return ctr, cs_ok
        ctr = np.zeros(n, dtype=np.int64)
        cs_ok = np.ones(n, dtype=bool)
        if (
            spec.algorithm == "crc8_sae_j1850"
            and spec.checksum_layout is not None
            and (ok := crc8_ok(x.length, spec.checksum_layout, data)) is not None
        ):
            cs_ok = ok
            if spec.counter is not None:
                ctr[:] = codec.extract_all(data[:, : spec.nbytes], [spec.counter], spec.nbytes)[0]
        elif st.tsc1 or st.checksum is not None:  # anything else: the stream's own check, per frame
            probe = Stream(spec)
            for i, r in enumerate(rows.tolist()):
                f = cols.frame(r)
                probe.prev = None
                cs_ok[i] = probe.check(0.0, f.arbitration_id, f.data[: x.length]) != CHECKSUM  # as the core
                ctr[i] = probe.prev if probe.prev is not None else 0
        elif spec.counter is not None:
            ctr[:] = codec.extract_all(data[:, : spec.nbytes], [spec.counter], spec.nbytes)[0]
        return ctr, cs_ok

    @staticmethod
    def _payloads(cols: FrameColumns, rows: NDArray[np.int64], size: int) -> NDArray[np.uint8]:
        if size <= 8:
            d = cols.data
            if d.shape[1] == 8 and d.flags.c_contiguous:  # a row as one 64-bit word: a 1-D gather, ~10x faster
                return d.view("<u8")[:, 0][rows].view(np.uint8).reshape(-1, 8)
            return d[rows]
        out = np.zeros((len(rows), size), dtype=np.uint8)
        for i, r in enumerate(rows.tolist()):
            d = cols.payload(r)[:size]
            out[i, : len(d)] = np.frombuffer(d, dtype=np.uint8)
        return out

    # -- a regular stretch ----------------------------------------------------------------------------

    def _stretch(
        self,
        t_all: NDArray[np.float64],
        groups_all: list[NDArray[np.int64]],
        raws_all: dict[int, list[NDArray[np.int64]]],
        row_all: NDArray[np.int64],
        ok_all: NDArray[np.bool_],
        ctr_all: NDArray[np.int64],
        cs_all: NDArray[np.bool_],
        pos: int,
    ) -> int:
        """Process the regular stretch of clocked frames starting at ``pos``; returns its end."""
        m = self.m
        clock = m.clock
        P = clock.period
        eps = TIME_EPS_S
        t = t_all[pos:]
        ok = ok_all[pos:]
        n = len(t)
        k0 = int(clock.next_k)  # type: ignore[arg-type]
        lf0 = clock.last_frame_t
        finite = np.isfinite(t)
        # g: the clock's next tick after a frame at t that completes ticks: the smallest k with k P >= t - eps
        u = t - eps
        g = np.ceil(u / P)
        for _ in range(2):
            g = np.where(g * P < u, g + 1, g)
            g = np.where((g - 1) * P >= u, g - 1, g)
        g = np.where(finite, g, -np.inf)
        kmax = _running_max(np.concatenate([[float(k0)], g]))
        k_prev = kmax[:-1]
        late_t = (k_prev - 1) * P - eps
        due_t = k_prev * P + eps
        late = t < late_t
        advances = t > due_t
        # the health checks of the frames that reach them (not late), then the DBC range
        # each message's frames from pos on that reach the checks (not late), in arrival order
        reach = [g[np.searchsorted(g, pos) :] - pos for g in groups_all] if pos else groups_all
        reach = [g[~late[g]] for g in reach]
        checks = self._counter_checks(t, reach, ctr_all[pos:], cs_all[pos:])
        verdict = np.where(checks != OK, checks, np.where(ok, OK, OUT_OF_RANGE)).astype(np.int8)
        accepted = (verdict == OK) & ~late
        lf = np.maximum.accumulate(np.concatenate([[lf0], np.where(accepted, t, -np.inf)]))
        lf_prev = lf[:-1]
        gap = advances & (t - lf_prev > clock.max_gap_s)
        step_back = late & (t < lf_prev - STEP_BACK_S)  # the wall clock stepped back: the core re-bases
        # a frame in step must not move the clock (ulp edge cases of t - eps against k P + eps)
        odd_step = ~late & ~advances & (g > k_prev)
        irregular = ~finite | step_back | gap | odd_step
        stop = int(np.argmax(irregular)) if irregular.any() else n
        if stop == 0:
            return pos
        # the chunk's temporaries go before the samples are made (the peak memory of a chunk)
        lf_end = float(lf[stop])
        del u, finite, kmax, late_t, due_t, advances, lf, lf_prev, gap, step_back, odd_step, irregular, checks
        sl = slice(0, stop)
        t, late, accepted, verdict = t[sl], late[sl], accepted[sl], verdict[sl]
        k_after = np.where(late, k_prev[sl], np.maximum(k_prev[sl], g[sl])).astype(np.int64)
        del k_prev, g
        k_end = int(k_after[-1])
        reach = [g[: np.searchsorted(g, stop)] for g in reach]  # within the stretch
        c = m.counters
        c["frames_total"] += stop
        c["late"] += int(late.sum())
        reached_v = verdict[~late]
        for code in (CHECKSUM, COUNTER_FROZEN, COUNTER_JUMP, OUT_OF_RANGE):
            c[REASONS[code]] += int(np.count_nonzero(reached_v == code))
        c["accepted"] += int(accepted.sum())
        self._write_counters(stop)
        # samples per role, in arrival order, from the accepted frames
        samples = self._samples(t, reach, raws_all, row_all[pos : pos + stop], accepted)
        ticks_k = np.arange(k0, k_end, dtype=np.int64)
        trig = np.searchsorted(k_after, ticks_k, side="right")  # index of the frame that completes each tick
        erratic = self._health(t, reach, verdict, trig, ticks_k.astype(np.float64) * P)
        if len(ticks_k):
            self._evaluate(ticks_k, trig, samples, erratic)
        # write the state back
        clock.resume(k_end, lf_end)
        for role, smp in samples.items():
            smp.write_back(m.windows[role])
        if self._low_after is not None:
            m._low = self._low_after
        return pos + stop

    def _samples(
        self,
        t: NDArray[np.float64],
        reach: list[NDArray[np.int64]],
        raws_all: dict[int, list[NDArray[np.int64]]],
        row: NDArray[np.int64],
        accepted: NDArray[np.bool_],
    ) -> dict[str, _RoleSamples]:
        m = self.m
        n = len(t)
        per_role: dict[str, list[tuple[NDArray[np.int64], NDArray[np.int64]]]] = {r: [] for r in m.windows}
        high_rows: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []
        low_rows: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []
        for f, targets in enumerate(self.targets):
            mine = reach[f][accepted[reach[f]]]
            if not len(mine):
                continue
            at = row[mine]
            vals = raws_all[f]
            for j, (role, kind) in enumerate(targets):
                if kind == _WINDOW and role is not None:
                    per_role[role].append((mine, vals[j][at]))
                elif kind == _HIGH:
                    high_rows.append((mine, vals[j][at]))
                elif kind == _LOW:
                    low_rows.append((mine, vals[j][at]))
        self._low_after = None
        hl = m.params.dp_from_high_low
        if hl is not None and high_rows:
            # dp at each frame with high pressure, with the newest low pressure at or before it
            li = np.concatenate([r for r, _ in low_rows]) if low_rows else np.empty(0, np.int64)
            lv = np.concatenate([v for _, v in low_rows]) if low_rows else np.empty(0, np.int64)
            order = np.argsort(li, kind="stable")
            li, lv = li[order], lv[order]
            hi_idx = np.concatenate([r for r, _ in high_rows])
            hv = np.concatenate([v for _, v in high_rows])
            order = np.argsort(hi_idx, kind="stable")
            hi_idx, hv = hi_idx[order], hv[order]
            j = np.searchsorted(li, hi_idx, side="right") - 1
            low_val = np.where(j >= 0, lv[np.maximum(j, 0)], 0)
            has_low = j >= 0
            if m._low is not None:
                low_val = np.where(has_low, low_val, m._low)
                has_low = np.ones_like(has_low)
            per_role[DP].append((hi_idx[has_low], hl.p * hv[has_low] - hl.q * low_val[has_low]))
        if low_rows:
            li = np.concatenate([r for r, _ in low_rows])
            lv = np.concatenate([v for _, v in low_rows])
            self._low_after = int(lv[np.argmax(li)])
        out = {}
        for role, parts in per_role.items():
            if len(parts) == 1:  # one message's frames: in arrival order already
                fi, rv = parts[0]
            elif parts:
                fi = np.concatenate([r for r, _ in parts])
                rv = np.concatenate([v for _, v in parts])
                order = np.argsort(fi, kind="stable")
                fi, rv = fi[order], rv[order]
            else:
                fi, rv = np.empty(0, np.int64), np.empty(0, np.int64)
            out[role] = _RoleSamples(m.windows[role], fi, t[fi], rv, n)
        return out

    def _counter_checks(
        self,
        t: NDArray[np.float64],
        reach: list[NDArray[np.int64]],
        ctr: NDArray[np.int64],
        cs_ok: NDArray[np.bool_],
    ) -> NDArray[np.int8]:
        """Steps 1 and 2 of :mod:`cmcan.monitor.health` for the frames that reach them (``reach``: each
        stream's, in arrival order): a failed checksum, else the counter against the previous frame
        that passed the checksum (within the timeout). Keeps each stream's passing frames for the
        write-back."""
        out = np.zeros(len(t), dtype=np.int8)
        self._passing: list[tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]] | None] = []
        for j, x in enumerate(self.inps):
            st = x.stream
            if not x.checked:
                self._passing.append(None)
                continue
            mine = reach[j]
            passed = cs_ok[mine]
            out[mine[~passed]] = CHECKSUM
            if not (st.tsc1 or st._at >= 0 or st._read is not None):  # a checksum and no counter
                self._passing.append(None)
                continue
            p = mine[passed]
            self._passing.append((p, ctr[p], t[p]))
            if not len(p):
                continue
            c = ctr[p]
            tp = t[p]
            prev_c = np.concatenate([[st.prev if st.prev is not None else 0], c[:-1]])
            prev_t = np.concatenate([[st.prev_t], tp[:-1]])
            has_prev = np.ones(len(p), dtype=bool)
            has_prev[0] = st.prev is not None
            within = has_prev & (tp - prev_t <= st.timeout_s)
            d = (c - prev_c) % st.modulo
            out[p] = np.where(within & (d == 0), COUNTER_FROZEN, np.where(within & (d > st.max_step), COUNTER_JUMP, OK))
        return out

    def _write_counters(self, stop: int) -> None:
        """Each stream's previous counter and its time as the core leaves them after ``stop`` frames."""
        for x, passing in zip(self.inps, self._passing, strict=True):
            if passing is None:
                continue
            p, c, tp = passing
            n = int(np.searchsorted(p, stop))
            if n:
                x.stream.prev = int(c[n - 1])
                x.stream.prev_t = float(tp[n - 1])

    def _health(
        self,
        t: NDArray[np.float64],
        reach: list[NDArray[np.int64]],
        verdict: NDArray[np.int8],
        trig: NDArray[np.int64],
        t_k: NDArray[np.float64],
    ) -> NDArray[np.bool_]:
        """Input health over a stretch (:mod:`cmcan.monitor.health`): each message stream's newest frame
        and its verdict at every tick (the frames before the one that completes the tick), whether
        some stream is erratic there, the timeouts counted at the ticks where some stream is alive;
        the streams' state and counts written back. ``reach``: each stream's frames that got to the
        checks (not late); ``verdict``: theirs (OK, or why a frame was rejected)."""
        n_ticks = len(t_k)
        erratic = np.zeros(n_ticks, dtype=bool)
        alive = np.zeros(n_ticks, dtype=bool)
        outs = []
        ends = []
        for j, x in enumerate(self.inps):
            st = x.stream
            f = reach[j]  # this stream's frames, in arrival order
            if len(f):
                tf, vf = t[f], verdict[f]
                # newest_t before each of its frames, and the frames that set it (t >= newest_t: later
                # ones win ties); a tick sees the frames before the one that completes it
                run = np.concatenate([[st.newest_t], tf])
                if tf[0] >= st.newest_t and (tf[1:] >= tf[:-1]).all():  # in order (the usual): each sets it
                    ok_after = vf == OK
                else:
                    run = np.maximum.accumulate(run)
                    upd = tf >= run[:-1]
                    last = np.maximum.accumulate(np.where(upd, np.arange(len(f)), -1))
                    ok_after = np.where(last >= 0, vf[np.maximum(last, 0)] == OK, st.newest_ok)
                seen = np.searchsorted(f, trig)
                nt = run[seen]
                ok_t = np.where(seen > 0, ok_after[np.maximum(seen - 1, 0)], st.newest_ok)
                for code in (CHECKSUM, COUNTER_FROZEN, COUNTER_JUMP, OUT_OF_RANGE):
                    st.counts[REASONS[code]] += int(np.count_nonzero(vf == code))
                ends.append((float(run[-1]), bool(ok_after[-1])))
            else:
                nt = np.full(n_ticks, st.newest_t)
                ok_t = np.full(n_ticks, st.newest_ok)
                ends.append((st.newest_t, st.newest_ok))
            tmo = st.timeout_s
            with np.errstate(invalid="ignore"):
                age = t_k - nt
                erratic |= ~ok_t & (nt <= t_k) & (age <= tmo)
                silent = (nt == -np.inf) | (age > tmo)
            if tmo < math.inf:
                alive |= ~silent
            outs.append((nt > -np.inf) & silent)
        live = np.flatnonzero(alive)
        for (x, out), (nt_end, ok_end) in zip(zip(self.inps, outs, strict=True), ends, strict=True):
            st = x.stream
            if len(live):
                o = out[live]
                prev = np.concatenate([[st.timed_out], o[:-1]])
                went = int(np.count_nonzero(o & ~prev))
                st.counts["timeout"] += went
                self.m.counters["timeout"] += went
                st.timed_out = bool(o[-1])
            st.newest_t, st.newest_ok = nt_end, ok_end
        return erratic

    def _evaluate(
        self,
        ks: NDArray[np.int64],
        trig: NDArray[np.int64],
        samples: dict[str, _RoleSamples],
        erratic: NDArray[np.bool_],
    ) -> None:
        m = self.m
        p = m.params
        P = m.period
        t_k = ks.astype(np.float64) * P
        window_s = p.limits.window_s
        cut = t_k - window_s + TIME_EPS_S
        mean, std, count, age = {}, {}, {}, {}
        for role, smp in samples.items():
            mean[role], std[role], count[role], age[role] = smp.stats(trig, cut, t_k, p.affine[role])
        n = len(ks)
        for role, value in m._constants:  # a role the machine holds constant: fresh, steady
            mean[role], std[role] = np.full(n, value), np.zeros(n)
            count[role], age[role] = np.full(n, p.limits.min_samples, dtype=np.int64), np.zeros(n)
        gates = gate_columns(mean, std, count, age, p.limits, p.max_age_s, p.envelope)
        gates[erratic] = Gate.IMPLAUSIBLE_INPUT  # an erratic input message (Monitor._health_gate)
        out = p.output_role
        meas = np.where(count[out] > 0, mean[out], 0.0)
        pred = np.zeros(n)
        wb = np.zeros(n)
        ev = np.flatnonzero(np.isin(gates, _EVALUATED))
        if len(ev):
            x = np.column_stack([mean[r][ev] for r in MODEL_INPUTS])
            try:
                pe, we = m.model.predict(x)  # type: ignore[attr-defined]
            except Exception:  # as the streaming core: a failing model call is a model error
                pe, we = np.full(len(ev), np.nan), np.zeros(len(ev))
            pe = np.asarray(pe, dtype=np.float64)
            bad = ~predictions_ok(pe, p.limits)
            m.counters["model_errors"] += int(bad.sum())
            gates[ev[bad]] = Gate.MODEL_ERROR
            pred[ev] = np.where(bad, 0.0, pe)
            wb[ev] = np.where(bad, 0.0, we)
        evaluated = np.isin(gates, _EVALUATED)
        e_idx = np.flatnonzero(evaluated)
        raw = np.zeros(n)
        raw[e_idx] = meas[e_idx] / pred[e_idx] * 100.0
        leak = (pred[e_idx] - meas[e_idx]) * p.lpm_per_unit
        filt, filt_leak, filt_n = _filter(m, raw[e_idx], leak, e_idx, n)
        m.counters["evaluated"] += len(e_idx)
        m.counters["extrapolated"] += int((gates[e_idx] == Gate.EXTRAPOLATED).sum())
        self._warnings(ks, t_k, gates, meas, pred, wb, raw, filt, filt_leak, filt_n, evaluated)

    def _warnings(
        self,
        ks: NDArray[np.int64],
        t_k: NDArray[np.float64],
        gates: NDArray[np.int8],
        meas: NDArray[np.float64],
        pred: NDArray[np.float64],
        wb: NDArray[np.float64],
        raw: NDArray[np.float64],
        filt: NDArray[np.float64],
        filt_leak: NDArray[np.float64],
        filt_n: NDArray[np.int64],
        evaluated: NDArray[np.bool_],
    ) -> None:
        """The warning state machine tick by tick, then totals, timeline and frames of the ticks."""
        m = self.m
        p = m.params
        P = m.period
        machine = m.machine
        totals = m.totals
        n = len(ks)
        valid = filt_n >= p.filter_min_samples
        step = machine.step
        record = m._record
        t_list = t_k.tolist()
        g_list = gates.tolist()  # the machine compares gates as ints (they are IntEnum values)
        ratio_arg = np.where(valid & evaluated, filt, np.nan)
        arg = ratio_arg.tolist()
        cond = np.zeros(n, dtype=np.int8)
        creason = np.zeros(n, dtype=np.int8)
        fault = np.zeros(n, dtype=np.int8)
        below = np.zeros(n, dtype=np.float64)
        wcount = np.zeros(n, dtype=np.int64)
        # runs of quiet ticks in the ok state are skipped over in one step; the rest go tick by tick
        quiet = machine.quiet(gates, ratio_arg)
        quiet_l = quiet.tolist()
        loud = np.append(np.flatnonzero(~quiet), n)
        wc, fc = totals.warning_count, totals.fault_count
        low, high = int(Level.LOW), int(Level.HIGH)
        i = 0
        while i < n:
            if quiet_l[i] and machine.can_skip():
                j = int(loud[np.searchsorted(loud, i)])
                below[i:j] = machine.skip(gates[i:j], ratio_arg[i:j], P)
                creason[i:j] = machine.condition_reason
                wcount[i:j] = wc
                i = j
                continue
            a = arg[i]
            cb, fb = machine.condition, machine.fault_reason
            trs = step(t_list[i], P, g_list[i], None if a != a else a)
            for tr in trs:
                record(tr.t_s, tr.level_from, tr.level_to, tr.reason, tr.ratio_pct)
            c, f = machine.condition, machine.fault_reason
            if c != cb and c in (low, high):
                wc += 1
            if fb == 0 and f != 0:
                fc += 1
            cond[i] = c
            creason[i] = machine.condition_reason
            fault[i] = f
            below[i] = machine.time_below_s
            wcount[i] = wc
            i += 1
        totals.warning_count, totals.fault_count = wc, fc
        dm1_now = self._dm1(ks, t_k, gates, cond, fault, filt, valid) if m._dm1 is not None else None
        level = np.where(fault != 0, np.int8(Level.FAULT), cond).astype(np.int8)
        reason = np.where(fault != 0, fault, creason).astype(np.int8)
        totals.condition = LEVEL_NAMES[machine.condition]
        # time in each level and evaluated time: the same float additions, in the same order
        for lv in Level:
            cnt = int((level == lv).sum())
            if cnt:
                totals.time_in_level_s[LEVEL_NAMES[lv]] = add_repeat(totals.time_in_level_s[LEVEL_NAMES[lv]], P, cnt)
        totals.evaluated_s = add_repeat(totals.evaluated_s, P, int(evaluated.sum()))
        m.counters["ticks"] += n
        ratio_raw = np.where(evaluated, raw, 0.0)
        cols = TickColumns(
            t_s=t_k,
            gate=gates.astype(np.int8),
            measured=meas,
            predicted=pred,
            whitebox=wb,
            ratio_raw_pct=ratio_raw,
            ratio_filt_pct=filt,
            extra_leak_lpm=filt_leak,
            filt_valid=valid,
            level=level,
            reason=reason,
            time_below_s=below,
            run_shift_s=np.full(n, m.run_shift_s),  # no clock step within a stretch
        )
        last = n - 1
        m.last_tick = Tick(
            t_s=float(t_k[last]),
            gate=Gate(int(gates[last])),
            measured=float(meas[last]),
            predicted=float(pred[last]),
            whitebox=float(wb[last]),
            ratio_raw_pct=float(ratio_raw[last]),
            ratio_filt_pct=float(filt[last]),
            extra_leak_lpm=float(filt_leak[last]),
            filt_valid=bool(valid[last]),
            level=Level(int(level[last])),
            reason=Reason(int(reason[last])),
            time_below_s=float(below[last]),
            run_shift_s=m.run_shift_s,
        )
        self.flush_scalar()  # the streaming path's ticks and frames before this stretch's
        # the pending transport packets due by the last tick go out with the ticks' frames, in time order
        later = m.due(t_list[-1])
        if self.want_frames:
            frames = self._frames(ks, cols, wcount)
            if dm1_now is not None or later:
                frames = _merge(frames, dm1_now, FrameColumns.from_frames(later))
            self.pending_frames.append(frames)
        if self.want_ticks:
            self._push_ticks(cols)
        elif self.want_frames:
            self._push_frames()

    def _dm1(
        self,
        ks: NDArray[np.int64],
        t_k: NDArray[np.float64],
        gates: NDArray[np.int8],
        cond: NDArray[np.int8],
        fault: NDArray[np.int8],
        filt: NDArray[np.float64],
        valid: NDArray[np.bool_],
    ) -> FrameColumns | None:
        """DM1 tick by tick through the core's own step: the frames due at their ticks, in order (None
        when there are none); transport packets for later are queued in the monitor as the streaming
        core queues them.

        A tick is stepped where the step could do something: a tick due by the period, a change of
        condition or fault, a change still waiting to go out (``changed``), or anywhere while the
        severity could move (a ratio beyond a severe threshold, or a severe flag set). Any other tick
        would find its state unchanged and nothing due, and return nothing. And a run of due ticks
        with nothing changed since a step that left one cached single frame resends that frame,
        which is what the step would do at each of them (its fast path), so they are not stepped."""
        m = self.m
        d = m._dm1
        assert d is not None
        p = d.p
        ratio = np.where(valid & (gates == Gate.EVALUATING), filt, np.nan)  # NaN: none
        with np.errstate(invalid="ignore"):
            severe = (ratio < p.low_severe_pct) | (ratio > p.high_severe_pct)
        n = len(ks)
        if d.low_severe or d.high_severe or severe.any():
            must = event = np.ones(n, dtype=bool)
        else:  # the severity flags stay as they are: only these ticks can change anything
            event = np.zeros(n, dtype=bool)
            # the first tick against the state the producer was left in (by the stretch before)
            event[0] = d.changed or d._last != (int(cond[0]), int(fault[0]), d.low_severe, d.high_severe)
            event[1:] = (cond[1:] != cond[:-1]) | (fault[1:] != fault[:-1])
            must = event | (ks % p.every_ticks == 0)
        now: list[Frame] = []
        now_at: list[int] = []  # the tick of each frame in ``now``
        resend: list[tuple[NDArray[np.int64], bytes]] = []  # ticks that resend a cached frame, and it
        step, queue = d.step, m.queue
        must_i = np.flatnonzero(must)
        events = np.flatnonzero(event)

        def stepped(i: int) -> int:  # the last tick stepped
            while True:
                r, t = float(ratio[i]), float(t_k[i])
                dm = step(int(ks[i]), t, int(cond[i]), int(fault[i]), None if r != r else r)  # type: ignore[arg-type]
                if dm:
                    queue(dm, t, now)
                    now_at.extend([i] * (len(now) - len(now_at)))
                if not d.changed or i + 1 >= n:
                    return i
                i += 1  # a change waits to go out: every tick until it has

        q = 0
        while q < len(must_i):
            i = int(must_i[q])
            pl = d._payload
            if (
                not event[i]
                and not d.changed
                and pl is not None
                and len(pl[1]) <= 8
                and d._last == (int(cond[i]), int(fault[i]), d.low_severe, d.high_severe)
                and float(t_k[i]) > d.busy_until
            ):
                # the due ticks up to the next event resend the cached frame (times only grow: all of
                # them are past any transport in progress)
                end = events[np.searchsorted(events, i)] if len(events) and events[-1] > i else n
                q_end = int(np.searchsorted(must_i, end))
                resend.append((must_i[q:q_end], pl[1]))
                q = q_end
                continue
            q = int(np.searchsorted(must_i, stepped(i), side="right"))
        if not now and not resend:
            return None
        parts, at = [], []
        if now:
            parts.append(FrameColumns.from_frames(now))
            at.append(np.array(now_at, dtype=np.int64))
        if resend:
            r = np.concatenate([run for run, _ in resend])
            data = np.zeros((len(r), 8), dtype=np.uint8)
            dlc = np.zeros(len(r), dtype=np.int16)
            at_run = 0
            for run, payload in resend:  # the frame cached when the run began
                data[at_run : at_run + len(run), : len(payload)] = np.frombuffer(payload, dtype=np.uint8)
                dlc[at_run : at_run + len(run)] = len(payload)
                at_run += len(run)
            no = np.zeros(len(r), dtype=bool)
            parts.append(
                FrameColumns(
                    timestamp_s=t_k[r],
                    channel=np.zeros(len(r), dtype=np.int16),
                    channel_names=(p.channel,),
                    arbitration_id=np.full(len(r), d.frame_id, dtype=np.uint32),
                    extended=np.ones(len(r), dtype=bool),
                    remote=no,
                    error=no,
                    fd=no,
                    dlc=dlc,
                    data=data,
                )
            )
            at.append(r)
        cols = FrameColumns.concat(parts) if len(parts) > 1 else parts[0]
        if len(parts) > 1:  # in tick order; a tick's own frames keep their order
            cols = cols.take(np.argsort(np.concatenate(at), kind="stable"))
        return cols

    def _frames(self, ks: NDArray[np.int64], c: TickColumns, wcount: NDArray[np.int64]) -> FrameColumns:
        """The CM frames of the ticks, as :class:`~cmcan.monitor.payloads.Payloads` builds them."""
        pl = self.m.payloads
        o = pl.outputs
        n = len(ks)
        evaluated = np.isin(c.gate, _EVALUATED).astype(np.float64)
        is_ratio = ks % o.ratio.every_ticks == 0
        is_speed = ks % o.quantity.every_ticks == 0
        # the alive counter a tick's frames carry: its value before this tick's ratio frame counts it
        counted = np.cumsum(is_ratio) - is_ratio
        alive = (pl.alive + counted) % 16
        pl.alive = int((pl.alive + int(is_ratio.sum())) % 16)
        state = c.level.astype(np.int64) * 256 + c.reason.astype(np.int64)
        prev = np.empty(n, dtype=np.int64)
        prev[0] = -1 if pl.last_warning is None else pl.last_warning[0] * 256 + pl.last_warning[1]
        prev[1:] = state[:-1]
        is_warn = (state != prev) | (ks % o.warning.every_ticks == 0)
        pl.last_warning = (int(c.level[-1]), int(c.reason[-1]))
        valid = c.filt_valid
        meas = np.where(np.isfinite(c.measured), c.measured, 0.0)
        name_meas, name_pred, name_wb, name_valid = o.quantity_signals
        enc = {}
        enc["ratio"] = _encode(
            o.ratio,
            np.flatnonzero(is_ratio),
            {
                "cm_ratio_raw_pct": c.ratio_raw_pct,
                "cm_ratio_filt_pct": np.where(valid, c.ratio_filt_pct, 0.0),
                "extra_leakage_lpm": np.where(valid, c.extra_leak_lpm, 0.0),
                "cm_raw_valid": evaluated,
                "cm_filt_valid": valid.astype(np.float64),
                "cm_gate": c.gate.astype(np.float64),
                "cm_alive_counter": alive.astype(np.float64),
            },
        )
        enc["speed"] = _encode(
            o.quantity,
            np.flatnonzero(is_speed),
            {
                name_meas: meas,
                name_pred: c.predicted,
                name_wb: c.whitebox,
                name_valid: evaluated,
                "cm_alive_counter": alive.astype(np.float64),
            },
        )
        enc["warning"] = _encode(
            o.warning,
            np.flatnonzero(is_warn),
            {
                "warning_level": c.level.astype(np.float64),
                "warning_reason": c.reason.astype(np.float64),
                "time_below_threshold_s": np.floor(c.time_below_s),
                "warning_count": (wcount % 65536).astype(np.float64),
            },
        )
        # interleave: per tick ratio, quantity, warning
        msgs = (o.ratio, o.quantity, o.warning)
        parts = (enc["ratio"], enc["speed"], enc["warning"])
        tick_of = np.concatenate([rows for rows, _ in parts])
        kind_of = np.concatenate([np.full(len(rows), k, dtype=np.int64) for k, (rows, _) in enumerate(parts)])
        data = np.zeros((len(tick_of), 8), dtype=np.uint8)
        at = 0
        for rows, payload in parts:
            data[at : at + len(rows), : payload.shape[1]] = payload[:, :8]
            at += len(rows)
        order = np.lexsort((kind_of, tick_of))
        tick_of, kind_of, data = tick_of[order], kind_of[order], data[order]
        ids = np.array([m.frame_id for m in msgs], dtype=np.uint32)[kind_of]
        ext = np.array([m.extended for m in msgs], dtype=bool)[kind_of]
        dlc = np.array([m.length for m in msgs], dtype=np.int16)[kind_of]
        no = np.zeros(len(tick_of), dtype=bool)
        return FrameColumns(
            timestamp_s=c.t_s[tick_of],
            channel=np.zeros(len(tick_of), dtype=np.int16),
            channel_names=(o.channel,),
            arbitration_id=ids,
            extended=ext,
            remote=no,
            error=no,
            fd=no,
            dlc=dlc,
            data=data,
        )


def _merge(ticks: FrameColumns, now: FrameColumns | None, later: FrameColumns) -> FrameColumns:
    """The ticks' CM frames with the DM1 frames of the same ticks (``now``, each after its tick's CM
    frames) and the transport packets due meanwhile (``later``, before a tick's frames of the same
    time), in the order the streaming core releases them (:meth:`Monitor._release`)."""
    extra = FrameColumns.concat([now, later]) if now is not None else later
    n_now = len(now) if now is not None else 0
    ts = ticks.timestamp_s
    t_x = extra.timestamp_s
    is_later = np.arange(len(extra)) >= n_now
    at = np.where(is_later, np.searchsorted(ts, t_x, side="left"), np.searchsorted(ts, t_x, side="right"))
    # at one place: by time, a transport packet before a DM1 frame, each kind in its own order
    order = np.lexsort((np.arange(len(extra)), ~is_later, t_x, at))
    extra = extra.take(order)
    pos = at[order] + np.arange(len(extra))  # rows in the result
    n = len(ticks) + len(extra)
    mine = np.ones(n, dtype=bool)
    mine[pos] = False
    return FrameColumns.concat([ticks, extra]).take(np.argsort(np.concatenate([np.flatnonzero(mine), pos])))


def _encode(
    msg: OutputMessage, rows: NDArray[np.int64], values: dict[str, NDArray[np.float64]]
) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
    """Payloads of ``msg`` for the tick rows (n, length), as its per-frame encoder gives them."""
    if msg.length > 8:
        raise ValueError("an output message longer than 8 bytes: the columnar replay writes classic frames")
    data = codec.encode_all(msg.layouts, msg.size, msg.length, {k: v[rows] for k, v in values.items()})
    if msg.fill:  # J1939: the bits of no signal sent as 1
        data |= np.frombuffer(msg.fill, dtype=np.uint8)[None, : msg.length]
    return rows, data


def _filter(
    m: Monitor, ratios: NDArray[np.float64], leaks: NDArray[np.float64], e_idx: NDArray[np.int64], n_ticks: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """The moving average at every tick: math.fsum of the ring over its length, from exact sums."""
    flt = m.filter
    size = flt.samples
    old_r, old_l = list(flt.ratios), list(flt.leaks)
    all_r = old_r + ratios.tolist()
    all_l = old_l + leaks.tolist()
    # ring contents after each tick: the last `size` of the values evaluated so far
    done = np.searchsorted(e_idx, np.arange(n_ticks), side="right") + len(old_r)  # values up to each tick
    lo = np.maximum(done - size, 0)
    cnt = done - lo
    sum_r = window_fsums(np.array(all_r), lo, done)
    sum_l = window_fsums(np.array(all_l), lo, done)
    with np.errstate(invalid="ignore", divide="ignore"):
        filt = np.where(cnt > 0, sum_r / np.maximum(cnt, 1), 0.0)
        filt_leak = np.where(cnt > 0, sum_l / np.maximum(cnt, 1), 0.0)
    flt.ratios = deque(all_r[-size:], maxlen=size)
    flt.leaks = deque(all_l[-size:], maxlen=size)
    return filt, filt_leak, cnt


_LANES = np.uint64(0x00FF_00FF_00FF_00FF)
_FOLD16 = np.uint64(0x0001_0001_0001_0001)


def byte_sums(words: NDArray[np.unsignedinteger], mask: int | None = None) -> NDArray[np.uint64]:
    """The sum of the bytes of each (up to 64-bit) word, ``mask`` applied first, in a few array passes
    instead of a reduction over rows of 8 bytes: pairs of bytes added into four 16-bit lanes, the
    lanes added by one multiplication into the top lane (at most 8 x 255 = 2040, no carry out of a
    lane). Two arrays are made; the rest is done in place."""
    w = words.astype(np.uint64) if mask is None else words & np.uint64(mask)
    hi = w >> np.uint64(8)
    hi &= _LANES
    w &= _LANES
    w += hi
    w *= _FOLD16
    w >>= np.uint64(48)
    return w


def _running_max(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``np.maximum.accumulate(x)``; ``x`` itself when it never falls (the usual log: in time order),
    which is checked faster than the running maximum is made."""
    if len(x) < 2 or (x[1:] >= x[:-1]).all():
        return x
    return np.maximum.accumulate(x)


def _groups(ids: NDArray[np.int64], n: int) -> list[NDArray[np.int64]]:
    """The positions of each of the ``n`` input messages' frames (``ids``: 0 to n-1), each in arrival
    order: one stable sort (a radix sort on small integers) instead of a pass over all frames per
    message."""
    if n == 1:
        return [np.arange(len(ids))]
    small = ids.astype(np.int16 if n < (1 << 15) else np.int64)
    order = np.argsort(small, kind="stable")
    bounds = np.searchsorted(small[order], np.arange(n + 1))
    return [order[bounds[j] : bounds[j + 1]] for j in range(n)]


def _distinct(keys: NDArray[np.int64], few: int = 16) -> NDArray[np.int64]:
    """The distinct values, sorted: a pass per value while there are few (a bus has a handful of
    identifiers), a sort beyond."""
    found: list[int] = []
    rest = keys
    while len(rest) and len(found) < few:
        k = int(rest[0])
        found.append(k)
        rest = rest[rest != k]
    if len(rest):
        found += np.unique(rest).tolist()
    return np.array(sorted(found), dtype=np.int64)


class _RoleSamples:
    """One role's samples for a stretch: the window's deque at its start, then the new ones."""

    def __init__(
        self,
        win: RoleWindow,
        frame_idx: NDArray[np.int64],
        ts: NDArray[np.float64],
        raw: NDArray[np.int64],
        n_frames: int,
    ) -> None:
        self.win = win
        old_t = np.fromiter(win.ts, np.float64, len(win.ts))
        old_r = list(win.rs)
        self.n_old = len(old_t)
        self.ts = np.concatenate([old_t, ts])
        self.big = (max((abs(r) for r in old_r), default=0) >= _I64_SAFE) or (
            len(raw) and int(np.abs(raw).max()) >= _I64_SAFE
        )
        if self.big:
            self.raw = np.array(old_r + [int(x) for x in raw.tolist()], dtype=object)
        else:
            self.raw = np.concatenate([np.asarray(old_r, dtype=np.int64), raw.astype(np.int64)])
        self.frame_idx = frame_idx
        self.rmax = _running_max(self.ts)
        self.last_t0 = win.last_t
        if self.big:
            self.c1 = np.concatenate([[0], np.cumsum(self.raw)])
            self.c2 = np.concatenate([[0], np.cumsum(self.raw * self.raw)])
        else:  # the prefix sums written in place after their leading zero
            self.c1 = np.zeros(len(self.raw) + 1, dtype=np.int64)
            self.c2 = np.zeros(len(self.raw) + 1, dtype=np.int64)
            np.cumsum(self.raw, out=self.c1[1:])
            np.cumsum(self.raw * self.raw, out=self.c2[1:])
        self.front = 0  # the deque's front after the last tick of the stretch

    def stats(
        self, trig: NDArray[np.int64], cut: NDArray[np.float64], t_k: NDArray[np.float64], f: Affine
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
        # samples available at a tick: the old ones plus the new ones from frames before its trigger
        avail = self.n_old + np.searchsorted(self.frame_idx, trig, side="left")
        front = np.minimum(avail, np.searchsorted(self.rmax, cut, side="right"))
        front = np.maximum.accumulate(np.maximum(front, 0))
        self.front = int(front[-1])
        n = avail - front
        s1 = self.c1[avail] - self.c1[front]
        s2 = self.c2[avail] - self.c2[front]
        if self.big:
            mean = np.array([f.mean(a, b) if b else math.nan for a, b in zip(s1.tolist(), n.tolist(), strict=True)])
            std = np.array(
                [
                    f.std(a, b2, b) if b else math.nan
                    for a, b2, b in zip(s1.tolist(), s2.tolist(), n.tolist(), strict=True)
                ]
            )
        else:
            mean, std = mean_std(s1.astype(np.int64), s2.astype(np.int64), n, f)
        newest_new = np.where(
            avail > self.n_old, self.rmax[np.maximum(avail - 1, 0)] if len(self.rmax) else -np.inf, -np.inf
        )
        last_t = np.maximum(self.last_t0, newest_new)
        return mean, std, n.astype(np.int64), t_k - last_t

    def write_back(self, win: RoleWindow) -> None:
        """The window as the streaming core leaves it: samples from the last front on, their sums."""
        ts = self.ts[self.front :].tolist()
        rs = [int(x) for x in self.raw[self.front :].tolist()]
        win.ts = deque(ts)
        win.rs = deque(rs)
        win.s1 = sum(rs)
        win.s2 = sum(r * r for r in rs)
        if len(self.ts) > self.n_old:
            win.last_t = max(win.last_t, float(self.rmax[-1]))
