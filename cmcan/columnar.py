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
from cmcan.frame import Frame, FrameColumns
from cmcan.monitor.clock import STEP_BACK_S
from cmcan.monitor.core import _HIGH, _LOW, _WINDOW, Monitor
from cmcan.monitor.gating import EVALUATED, Gate, gate_columns, predictions_ok
from cmcan.monitor.payloads import OutputMessage
from cmcan.monitor.tick import LEVEL_NAMES, Tick
from cmcan.monitor.warnings import Level, Reason
from cmcan.monitor.windows import TIME_EPS_S, Affine, RoleWindow, mean_std
from cmcan.replay import NoFrames, ReplaySummary, Sink, TickColumns, summarize
from cmcan.roles import DP, MODEL_INPUTS

_EVALUATED = np.array(sorted(int(g) for g in EVALUATED), dtype=np.int8)

_I64_SAFE = 1 << 20  # raw values below this: window sums and n*S2 - S1^2 stay exact in int64


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
        self.pending_frames: list[Frame] = []
        # per input message: (role or None, kind) of each decoded value, as the core routes them
        self.targets: dict[int, list[tuple[str | None, int]]] = {}
        roles_of = {id(w): r for r, w in monitor.windows.items()}
        for fid, plan in monitor._plans.items():
            self.targets[fid] = [(roles_of.get(id(win)) if win is not None else None, kind) for win, kind in plan]
        self._low_after: int | None = None

    # -- output plumbing ------------------------------------------------------------------------------

    def scalar_out(self, frames: list[Frame]) -> None:
        """Frames (and ticks on the monitor's timeline) from the streaming path, in order."""
        if self.want_frames and frames:
            self.pending_frames.extend(frames)
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
            self.n_frames_out += len(self.pending_frames)
            for s in self.sinks:
                if s.wants_frames:
                    s.frames(self.pending_frames)
            self.pending_frames = []

    def drain(self) -> None:
        self.drain_timeline()
        self._push_frames()

    # -- a chunk --------------------------------------------------------------------------------------

    def chunk(self, cols: FrameColumns) -> None:
        m = self.m
        c = m.counters
        n = len(cols)
        err, rtr, ext = cols.error, cols.remote, cols.extended
        fid = cols.arbitration_id.astype(np.int64)
        known = np.zeros(n, dtype=bool)
        need_len = np.zeros(n, dtype=np.int64)
        for f, spec in m.inputs.items():
            hit = fid == f
            known |= hit
            need_len[hit] = spec.length
        plain = ~(err | rtr | ext)
        known &= plain
        good_len = known & (cols.dlc >= need_len)
        # frames that never reach the clock: counted in bulk (their order does not matter)
        c["frames_total"] += int(n - good_len.sum())
        c["error_frame"] += int(err.sum())
        c["remote_frame"] += int((rtr & ~err).sum())
        c["unknown_id"] += int((ext & ~err & ~rtr).sum() + (plain & ~known).sum())
        c["bad_length"] += int((known & ~good_len).sum())
        idx = np.flatnonzero(good_len)
        if not len(idx):
            return
        t = cols.timestamp_s[idx]
        ids = fid[idx]
        raws, ok, row = self._decode(cols, idx, ids)
        pos = 0
        while pos < len(idx):
            if m.clock.next_k is None or not math.isfinite(t[pos]):
                self._scalar(cols, int(idx[pos]))
                pos += 1
                continue
            end = self._stretch(t, ids, raws, row, ok, pos)
            if end == pos:  # the first frame is irregular: the streaming core takes it
                self._scalar(cols, int(idx[pos]))
                pos += 1
            else:
                pos = end

    def _scalar(self, cols: FrameColumns, i: int) -> None:
        self.drain_timeline()
        self.scalar_out(self.m.feed(cols.frame(i)))

    def _decode(
        self, cols: FrameColumns, idx: NDArray[np.int64], ids: NDArray[np.int64]
    ) -> tuple[dict[int, NDArray[np.int64]], NDArray[np.bool_], NDArray[np.int64]]:
        """Per message id the raw values (its frames x its values), the DBC range check per frame,
        and each frame's row in its message's array."""
        ok = np.ones(len(idx), dtype=bool)
        row = np.zeros(len(idx), dtype=np.int64)
        raws: dict[int, NDArray[np.int64]] = {}
        for f, spec in self.m.inputs.items():
            sel = np.flatnonzero(ids == f)
            if not len(sel):
                continue
            data = self._payloads(cols, idx[sel], spec.size)
            vals = codec.extract_all(data, spec.layouts, spec.size)
            arr = np.stack(vals, axis=1) if vals else np.zeros((len(sel), 0), dtype=np.int64)
            good = np.ones(len(sel), dtype=bool)
            for j, lay in enumerate(spec.layouts):
                phys = arr[:, j] * lay.scale + lay.offset
                good &= (lay.minimum <= phys) & (phys <= lay.maximum)
            ok[sel] = good
            row[sel] = np.arange(len(sel))
            raws[f] = arr
        return raws, ok, row

    @staticmethod
    def _payloads(cols: FrameColumns, rows: NDArray[np.int64], size: int) -> NDArray[np.uint8]:
        if size <= 8:
            return cols.data[rows]
        out = np.zeros((len(rows), size), dtype=np.uint8)
        for i, r in enumerate(rows.tolist()):
            d = cols.payload(r)[:size]
            out[i, : len(d)] = np.frombuffer(d, dtype=np.uint8)
        return out

    # -- a regular stretch ----------------------------------------------------------------------------

    def _stretch(
        self,
        t_all: NDArray[np.float64],
        ids_all: NDArray[np.int64],
        raws_all: dict[int, NDArray[np.int64]],
        row_all: NDArray[np.int64],
        ok_all: NDArray[np.bool_],
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
        kmax = np.maximum.accumulate(np.concatenate([[float(k0)], g]))
        k_prev = kmax[:-1]
        late_t = (k_prev - 1) * P - eps
        due_t = k_prev * P + eps
        late = t < late_t
        advances = t > due_t
        accepted = ok & ~late
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
        sl = slice(0, stop)
        t, ok, late, accepted = t[sl], ok[sl], late[sl], accepted[sl]
        k_after = np.where(late, k_prev[sl], np.maximum(k_prev[sl], g[sl])).astype(np.int64)
        k_end = int(k_after[-1])
        ids = ids_all[pos : pos + stop]
        c = m.counters
        c["frames_total"] += stop
        c["late"] += int(late.sum())
        c["out_of_range"] += int((~ok & ~late).sum())
        c["accepted"] += int(accepted.sum())
        # samples per role, in arrival order, from the accepted frames
        samples = self._samples(t, ids, raws_all, row_all[pos : pos + stop], accepted)
        ticks_k = np.arange(k0, k_end, dtype=np.int64)
        trig = np.searchsorted(k_after, ticks_k, side="right")  # index of the frame that completes each tick
        if len(ticks_k):
            self._evaluate(ticks_k, trig, samples)
        # write the state back
        clock.resume(k_end, float(lf[stop]))
        for role, smp in samples.items():
            smp.write_back(m.windows[role])
        if self._low_after is not None:
            m._low = self._low_after
        return pos + stop

    def _samples(
        self,
        t: NDArray[np.float64],
        ids: NDArray[np.int64],
        raws_all: dict[int, NDArray[np.int64]],
        row: NDArray[np.int64],
        accepted: NDArray[np.bool_],
    ) -> dict[str, _RoleSamples]:
        m = self.m
        n = len(t)
        per_role: dict[str, list[tuple[NDArray[np.int64], NDArray[np.int64]]]] = {r: [] for r in m.windows}
        high_rows: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []
        low_rows: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []
        for f, targets in self.targets.items():
            mine = np.flatnonzero((ids == f) & accepted)
            if not len(mine):
                continue
            arr = raws_all[f][row[mine]]
            for j, (role, kind) in enumerate(targets):
                if kind == _WINDOW and role is not None:
                    per_role[role].append((mine, arr[:, j]))
                elif kind == _HIGH:
                    high_rows.append((mine, arr[:, j]))
                elif kind == _LOW:
                    low_rows.append((mine, arr[:, j]))
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
            if parts:
                fi = np.concatenate([r for r, _ in parts])
                rv = np.concatenate([v for _, v in parts])
                order = np.argsort(fi, kind="stable")
                fi, rv = fi[order], rv[order]
            else:
                fi, rv = np.empty(0, np.int64), np.empty(0, np.int64)
            out[role] = _RoleSamples(m.windows[role], fi, t[fi], rv, n)
        return out

    def _evaluate(self, ks: NDArray[np.int64], trig: NDArray[np.int64], samples: dict[str, _RoleSamples]) -> None:
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
        level = np.empty(n, dtype=np.int8)
        reason = np.empty(n, dtype=np.int8)
        below = np.empty(n)
        wcount = np.empty(n, dtype=np.int64)
        step = machine.step
        record = m._record
        t_list = t_k.tolist()
        g_list = [Gate(g) for g in gates.tolist()]
        arg = np.where(valid & evaluated, filt, np.nan).tolist()
        ok_level, low, high = Level.OK, Level.LOW, Level.HIGH
        none = Reason.NONE
        for i in range(n):
            a = arg[i]
            cond_before, fault_before = machine.condition, machine.fault_reason
            for tr in step(t_list[i], P, g_list[i], None if a != a else a):
                record(tr.t_s, tr.level_from, tr.level_to, tr.reason, tr.ratio_pct)
            cond = machine.condition
            if cond != cond_before and cond in (low, high):
                totals.warning_count += 1
            if fault_before == none and machine.fault_reason != none:
                totals.fault_count += 1
            level[i] = machine.level
            reason[i] = machine.reason
            below[i] = machine.time_below_s
            wcount[i] = totals.warning_count
        _ = ok_level
        totals.condition = LEVEL_NAMES[machine.condition]
        # time in each level and evaluated time: the same float additions, in the same order
        for lv in Level:
            cnt = int((level == lv).sum())
            if cnt:
                totals.time_in_level_s[LEVEL_NAMES[lv]] = _add_repeat(totals.time_in_level_s[LEVEL_NAMES[lv]], P, cnt)
        totals.evaluated_s = _add_repeat(totals.evaluated_s, P, int(evaluated.sum()))
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
        )
        frames = self._frames(ks, cols, wcount) if self.want_frames else []
        if self.want_frames:
            self.pending_frames.extend(frames)
        if self.want_ticks:
            self._push_ticks(cols)
        elif self.want_frames:
            self._push_frames()

    def _frames(self, ks: NDArray[np.int64], c: TickColumns, wcount: NDArray[np.int64]) -> list[Frame]:
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
        # interleave: per tick ratio, speed, warning
        order_t, order_kind, order_row = [], [], []
        for kind, (rows, _payloads) in enumerate((enc["ratio"], enc["speed"], enc["warning"])):
            order_t.append(rows)
            order_kind.append(np.full(len(rows), kind))
            order_row.append(np.arange(len(rows)))
        tick_of = np.concatenate(order_t)
        kind_of = np.concatenate(order_kind)
        row_of = np.concatenate(order_row)
        order = np.lexsort((kind_of, tick_of))
        msgs = (o.ratio, o.quantity, o.warning)
        payloads = [enc["ratio"][1], enc["speed"][1], enc["warning"][1]]
        ch = o.channel
        t_list = c.t_s.tolist()
        return [
            Frame(t_list[ti], ch, msgs[k].frame_id, msgs[k].extended, False, False, False, payloads[k][r])
            for ti, k, r in zip(tick_of[order].tolist(), kind_of[order].tolist(), row_of[order].tolist(), strict=True)
        ]


def _encode(
    msg: OutputMessage, rows: NDArray[np.int64], values: dict[str, NDArray[np.float64]]
) -> tuple[NDArray[np.int64], list[bytes]]:
    """Payloads of ``msg`` for the tick rows, as its per-frame encoder gives them."""
    if not len(rows):
        return rows, []
    data = codec.encode_all(msg.layouts, msg.size, msg.length, {k: v[rows] for k, v in values.items()})
    return rows, [r.tobytes() for r in data]


def _add_repeat(start: float, step: float, times: int) -> float:
    """``start`` plus ``step``, ``times`` times, one addition after the other (as the core does)."""
    acc = np.empty(times + 1)
    acc[0] = start
    acc[1:] = step
    return float(np.cumsum(acc)[-1])


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
    sum_r = _exact_window_sums(all_r, lo, done)
    sum_l = _exact_window_sums(all_l, lo, done)
    with np.errstate(invalid="ignore", divide="ignore"):
        filt = np.where(cnt > 0, sum_r / np.maximum(cnt, 1), 0.0)
        filt_leak = np.where(cnt > 0, sum_l / np.maximum(cnt, 1), 0.0)
    flt.ratios = deque(all_r[-size:], maxlen=size)
    flt.leaks = deque(all_l[-size:], maxlen=size)
    return filt, filt_leak, cnt


def _exact_window_sums(values: list[float], lo: NDArray[np.int64], hi: NDArray[np.int64]) -> NDArray[np.float64]:
    """math.fsum(values[lo:hi]) for each window: exact sums of the floats as integers scaled by a
    power of two, rounded once (Python's int division is correctly rounded, as fsum is)."""
    if not values:
        return np.zeros(len(lo))
    mant, expo = np.frexp(np.asarray(values, dtype=np.float64))
    ints = (mant * float(1 << 53)).astype(np.int64)  # exact: value = ints * 2^(expo - 53)
    shift = expo - 53
    base = int(shift.min())
    exact = np.empty(len(values) + 1, dtype=object)
    exact[0] = 0
    exact[1:] = [int(i) << int(s - base) for i, s in zip(ints.tolist(), shift.tolist(), strict=True)]
    prefix = np.cumsum(exact)
    sums = prefix[hi] - prefix[lo]
    scale = 2 ** (-base) if base < 0 else None
    if scale is None:
        return np.array([float(s << base) for s in sums.tolist()])
    return np.array([s / scale for s in sums.tolist()])


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
        self.rmax = np.maximum.accumulate(self.ts) if len(self.ts) else self.ts
        self.last_t0 = win.last_t
        zero = 0 if self.big else np.int64(0)
        self.c1 = np.concatenate([[zero], np.cumsum(self.raw)])
        self.c2 = np.concatenate([[zero], np.cumsum(self.raw * self.raw)])
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
