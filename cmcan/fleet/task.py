"""One log, start to finish, inside a Dask worker: probe (hash, first frame), then skip or replay,
reduce, commit or quarantine.

A task gets paths (the log, its configuration and model), the data set's folder and the monitor
state to start from (:mod:`cmcan.fleet.chain`), never a monitor or a model session: the worker builds
those itself, and keeps the loaded DBC and model of each (configuration, model) pair for the next
log. Every failure of a log is caught here and recorded in the quarantine table, so one bad log
never stops a run; a failure of the data set itself (a full disk, no permission) is no fault of the
log: the task returns it as an error and the run stops with it (:class:`cmcan.fleet.dataset.DatasetError`).

Quarantine reasons are one line of what went wrong with the file, never its content: the readers'
messages quote the line they could not read, and a file named as a log may be anything
(:func:`safe_reason`).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import re
import stat
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cmcan import config as cfgmod
from cmcan.assemble import build_monitor, dbc_for, load_model_for, model_file
from cmcan.can.frame import Frame
from cmcan.errors import CmcanError
from cmcan.fitcheck import FitWindow
from cmcan.fleet import dataset as ds
from cmcan.fleet.aggregate import RUN_SHIFT, Downsampler, LogStats
from cmcan.fleet.chain import Carry, without_history
from cmcan.io.candump import Cut
from cmcan.monitor.gating import Gate
from cmcan.monitor.tick import LEVEL_NAMES, TickColumns
from cmcan.monitor.totals import Totals
from cmcan.monitor.warnings import Level, Reason
from cmcan.replay import ReplaySummary, replay_file

GATE_NAMES = np.array([g.name.lower() for g in sorted(Gate)], dtype=object)
LEVEL_NAME_ARR = np.array([LEVEL_NAMES[lv] for lv in sorted(Level)], dtype=object)
REASON_NAMES = np.array([r.name.lower() for r in sorted(Reason)], dtype=object)
NAMED = {"gate": GATE_NAMES, "warning_level": LEVEL_NAME_ARR, "warning_reason": REASON_NAMES}
# A log whose input frames mostly fail to decode was recorded with another signal layout.
MAX_UNDECODABLE_SHARE = 0.5
MAX_REASON_CHARS = 300


@dataclass(frozen=True)
class LogJob:
    machine: str
    log: str
    config: str | None = None  # None: the shipped configuration
    model: str | None = None  # None: the configuration's model
    origin: str = ""  # where the log was named (a manifest's line), for messages about it
    # filled in by the probe (:func:`probe_log`)
    log_hash: str | None = None
    size: int = -1
    mtime_ns: int = -1
    first_t: float | None = None
    move_from: tuple[str, ...] = ()  # machines the log (by its hash) had results under before


@dataclass(frozen=True)
class Options:
    dataset: str
    rate_hz: float = 1.0
    timeout_s: float | None = 3600.0
    retry_quarantined: bool = False
    engine: str = "columnar"
    keep_truncated: bool = False  # replay a log whose last line was cut up to its last whole line


class LogTimeout(Exception):
    pass


@dataclass(frozen=True)
class Inputs:
    cfg: cfgmod.Config
    db: Any
    model: Any
    config_hash: str
    dbc_hash: str
    model_hash: str

    @property
    def hashes(self) -> tuple[str, str, str]:
        return (self.config_hash, self.dbc_hash, self.model_hash)


def _stamp(path: Path) -> tuple[str, int, int]:
    st = path.stat()
    return str(path.resolve()), st.st_mtime_ns, st.st_size


@functools.lru_cache(maxsize=16)
def _inputs_cached(config: tuple[str, int, int] | None, model: tuple[str, int, int] | None) -> Inputs:
    cfg = cfgmod.load(config[0] if config else None)
    db = dbc_for(cfg)
    m = load_model_for(cfg, model[0] if model else None)
    cfg_path = Path(config[0]) if config else cfgmod.default_config_path()
    model_path = Path(model[0]) if model else model_file(cfg)
    return Inputs(cfg, db, m, ds.sha256_file(cfg_path), ds.sha256_file(cfg.dbc_path), ds.sha256_file(model_path))


def load_inputs(config: str | None, model: str | None) -> Inputs:
    """Configuration, DBC and model with their hashes, once per worker and file version."""
    return _inputs_cached(_stamp(Path(config)) if config else None, _stamp(Path(model)) if model else None)


# -- what a quarantine row may say ------------------------------------------------------------------

# A quoted piece of text (a repr: 'x', "x", b'x'): what a reader quotes of the line it could not read.
_QUOTED = re.compile(r"""b?'(?:[^'\\\n]|\\.)*'|b?"(?:[^"\\\n]|\\.)*\"""")


def safe_reason(text: str, keep: Sequence[str | None] = ()) -> str:
    """One line of an error for the quarantine table and the report: the first line, quoted
    pieces (a reader's quote of the line it could not read, a configuration's bad value) left out,
    unprintable characters replaced, at most ``MAX_REASON_CHARS``. The paths in ``keep`` (the
    log's, its configuration's: the user's names) stay as they are."""
    line = (text or "").splitlines()[0] if text else ""
    marks: dict[str, str] = {}
    for i, p in enumerate(sorted({k for k in keep if k}, key=len, reverse=True)):
        mark = f"\x00{i}\x00"
        if p in line:
            line = line.replace(p, mark)
            marks[mark] = p
    stripped = _QUOTED.sub("(...)", line)
    if stripped != line:
        stripped += " [quoted content left out]"
    for mark, p in marks.items():
        stripped = stripped.replace(mark, p)
    out = "".join(ch if ch.isprintable() else "?" for ch in stripped)
    return out if len(out) <= MAX_REASON_CHARS else out[: MAX_REASON_CHARS - 3] + "..."


# -- the results --------------------------------------------------------------------------------------


def path_key(log: str) -> str:
    return hashlib.sha256(os.path.abspath(log).encode()).hexdigest()[:16] + "-" + "0" * 12


def hash_key(log_hash: str) -> str:
    return f"{log_hash[:16]}-{'0' * 12}"


def _quarantine(
    opt: Options, job: LogJob, key: str, stage: str, reason: str, prov: ds.Provenance | None, started: float
) -> dict[str, Any]:
    root = Path(opt.dataset)
    reason = safe_reason(reason, (job.log, job.config, job.model, os.path.basename(job.log)))
    row = {
        "log": job.log,
        "config": job.config,
        "model": job.model,
        "stage": stage,
        "reason": reason,
        "options": prov.options if prov else "",
        "quarantined_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **(
            prov.columns()
            if prov
            else {
                "log_hash": job.log_hash,
                "config_hash": None,
                "dbc_hash": None,
                "model_hash": None,
                "cmcan_version": ds.__version__,
            }
        ),
    }
    ds.write_quarantine(root, job.machine, key, row)
    return _result(job, "quarantined", key, started, reason=f"{stage}: {reason}")


def _result(job: LogJob, status: str, key: str, started: float, **extra: Any) -> dict[str, Any]:
    return {
        "machine": job.machine,
        "log": job.log,
        "status": status,
        "key": key,
        "seconds": time.monotonic() - started,
        "frames": 0,
        **extra,
    }


def _error(job: LogJob, exc: ds.DatasetError, started: float) -> dict[str, Any]:
    """The data set cannot be written: no fault of the log, the run stops with this."""
    return _result(job, "error", "", started, kind=exc.kind.name, message=str(exc))


# -- probe: a regular file, its hash and its first frame, within the time limit ----------------------


def _hash_open_file(fd: int, deadline: float | None) -> str:
    h = hashlib.sha256()
    while chunk := os.read(fd, ds.HASH_CHUNK):
        h.update(chunk)
        if deadline is not None and time.monotonic() > deadline:
            raise LogTimeout
    return h.hexdigest()


def probe_log(job: LogJob, opt: Options, first_frame: bool = True) -> dict[str, Any]:
    """A log's hash, size, modification time and first frame's time (``status`` "probed", the job
    filled in under ``job``), or its quarantine. The file is opened without blocking and must be a
    regular file (a FIFO or a device named as a log would hang the run or never end); the hashing
    counts against ``--timeout-s``."""
    started = time.monotonic()
    cpu0 = time.process_time()
    try:
        res = _probe(job, opt, first_frame, started)
    except ds.DatasetError as exc:
        res = _error(job, exc, started)
    res["cpu_s"] = time.process_time() - cpu0
    return res


def _probe(job: LogJob, opt: Options, first_frame: bool, started: float) -> dict[str, Any]:
    deadline = started + opt.timeout_s if opt.timeout_s else None
    named = f" (named in {job.origin})" if job.origin and " line " in job.origin else ""
    try:
        fd = os.open(job.log, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        return _quarantine(opt, job, path_key(job.log), "read", f"cannot read the log: {why}{named}", None, started)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            return _quarantine(
                opt,
                job,
                path_key(job.log),
                "read",
                f"not a regular file (mode {stat.filemode(st.st_mode)}): not read",
                None,
                started,
            )
        try:
            log_hash = _hash_open_file(fd, deadline)
        except LogTimeout:
            return _quarantine(
                opt, job, path_key(job.log), "timeout", f"hashing took longer than {opt.timeout_s:g} s", None, started
            )
        except OSError as exc:
            return _quarantine(
                opt, job, path_key(job.log), "read", f"cannot read the log: {exc.strerror or exc}", None, started
            )
    finally:
        os.close(fd)
    job = dataclasses.replace(job, log_hash=log_hash, size=st.st_size, mtime_ns=st.st_mtime_ns)
    # read now: an earlier row for its path (refused, unreadable, timed out) is history
    ds.remove_quarantine(Path(opt.dataset), job.machine, [path_key(job.log)], None)
    if first_frame:
        row = ds.quarantine_row(Path(opt.dataset), job.machine, hash_key(log_hash))
        if row is not None and row.get("stage") == "read" and not opt.retry_quarantined:
            return _result(job, "skipped", hash_key(log_hash), started, reason="quarantined before")
        try:
            job = dataclasses.replace(job, first_t=_first_time(job.log))
        except (CmcanError, ValueError, OSError, EOFError, UnicodeError) as exc:
            if isinstance(exc, ds.DatasetError):
                raise
            prov = ds.Provenance(log_hash, "", "", "")
            return _quarantine(opt, job, hash_key(log_hash), "read", f"cannot read as a CAN log: {exc}", prov, started)
    return {**_result(job, "probed", "", started), "job": job}


def _first_time(log: str) -> float | None:
    from cmcan.io.candump import iter_frames

    it = iter_frames(log)
    try:
        f = next(it, None)
    finally:
        it.close()
    return None if f is None else float(f.timestamp_s)


# -- the sink -----------------------------------------------------------------------------------------


class FleetSink:
    """Ticks to timeline rows at the configured rate, to the log's statistics and its fit window;
    stops a replay that runs past its time limit."""

    wants_ticks = True
    wants_frames = False

    def __init__(self, writer: ds.LogWriter, rate_hz: float, deadline: float | None) -> None:
        self.writer = writer
        self.down = Downsampler(rate_hz)
        self.stats = LogStats()
        self.fit = FitWindow()
        self.deadline = deadline
        self.t0 = 0.0

    def start(self, t0: float) -> None:
        self.t0 = t0
        self.stats.t0 = t0
        self.fit.t0 = t0

    def _rows(self, rows: dict[str, Any]) -> None:
        if not rows:
            return
        for col, names in NAMED.items():
            if col in rows:
                rows[col] = names[np.asarray(rows[col], dtype=np.int64)]
        t = rows["time_s"]
        shift = rows.pop(RUN_SHIFT)  # the wall clock's steps undone: log time never runs backwards
        out = {
            "time_s": t,
            "log_time_h": (t + shift - self.t0) / 3600.0,
            **{k: v for k, v in rows.items() if k != "time_s"},
        }
        self.writer.add_rows("timeline", out)

    def ticks(self, chunk: TickColumns) -> None:
        if self.deadline is not None and time.monotonic() > self.deadline:
            raise LogTimeout
        self.stats.add(chunk)
        self.fit.add(chunk)
        self._rows(self.down.add(chunk))

    def frames(self, frames: Sequence[Frame]) -> None:
        pass

    def close(self) -> None:
        self._rows(self.down.finish())

    def abort(self) -> None:
        pass


# -- the readers --------------------------------------------------------------------------------------


def replay_log(job: LogJob, mon: Any, sinks: Sequence[Any], opt: Options) -> tuple[ReplaySummary, int | None]:
    """The fleet's one call of the readers: the summary, and where a log cut short was cut (its last,
    partial line; with ``--keep-truncated`` the log is replayed up to its last whole frame, without
    it a cut log is refused)."""
    cuts: list[Cut] = []
    res = replay_file(job.log, mon, sinks, engine=opt.engine, keep_truncated=opt.keep_truncated, on_cut=cuts.append)
    if not cuts:
        return res, None
    line = cuts[0].line
    return res, (line if line is not None else -1)  # -1: a binary log, cut after its last whole frame


# -- the whole life of a log ---------------------------------------------------------------------------


def process_log(job: LogJob, opt: Options, carry: Carry | None = None) -> dict[str, Any]:
    """The whole life of one log in the data set; never raises for a bad log (quarantines it) nor
    for a data set that cannot be written (status "error", the run stops). ``carry`` is the state
    the log starts from (default: fresh). A job without its hash is probed first. The result says
    what happened, with the task's wall-clock and CPU seconds (for progress and benchmarks, never
    for the data), and for the next log of the machine the state at its end (``end``)."""
    cpu0 = time.process_time()
    started = time.monotonic()
    try:
        if job.log_hash is None:
            probed = probe_log(job, opt, first_frame=False)
            if probed["status"] != "probed":
                probed["cpu_s"] = time.process_time() - cpu0
                return probed
            job = probed["job"]
        res = _process_log(job, opt, carry or Carry(), started)
    except ds.DatasetError as exc:
        res = _error(job, exc, started)
    res["cpu_s"] = time.process_time() - cpu0
    return res


def _changed(job: LogJob) -> str | None:
    try:
        st = os.stat(job.log)
    except OSError as exc:
        return f"cannot read the log: {exc.strerror or exc}"
    if job.size >= 0 and (st.st_size, st.st_mtime_ns) != (job.size, job.mtime_ns):
        return "the log changed while the run went on (size or modification time); run again to replay it"
    return None


def _process_log(job: LogJob, opt: Options, carry: Carry, started: float) -> dict[str, Any]:
    root = Path(opt.dataset)
    assert job.log_hash is not None
    log_hash = job.log_hash
    changed = _changed(job)
    if changed is not None:
        return _quarantine(opt, job, path_key(job.log), "read", changed, None, started)
    try:
        inp = load_inputs(job.config, job.model)
    except (CmcanError, OSError, ValueError) as exc:
        prov = ds.Provenance(log_hash, "", "", "")
        return _quarantine(opt, job, hash_key(log_hash), "inputs", str(exc), prov, started)
    if carry.carried and carry.inputs is not None and carry.inputs != inp.hashes:
        carry = carry.fresh_because("the previous log was replayed with another configuration, DBC or model")
    prov = ds.Provenance(
        log_hash,
        inp.config_hash,
        inp.dbc_hash,
        inp.model_hash,
        state_hash=carry.state_hash,
        options="keep_truncated" if opt.keep_truncated else "",  # (changes what a cut log gives)
    )
    redone = None
    try:
        record = ds.check_committed(root, job.machine, prov.key)
    except ds.Damaged as exc:
        record = None
        redone = "; ".join(exc.problems[:3])
        ds.remove_log(root, job.machine, log_hash[:16])
    if record is not None:
        for other in job.move_from:  # committed here already: only the old machine's rows go
            if other != job.machine:
                ds.remove_log(root, other, log_hash[:16])
                ds.remove_quarantine(root, other, [path_key(job.log)], log_hash[:16])
        ds.remove_quarantine(root, job.machine, [path_key(job.log)], None)  # an earlier failure to read it
        return _result(job, "skipped", prov.key, started, end=_end_of(record, inp), log_hash=log_hash)
    q = ds.quarantine_row(root, job.machine, prov.key)
    if q is not None and not opt.retry_quarantined:
        return _result(job, "skipped", prov.key, started, reason="quarantined before", log_hash=log_hash)
    writer = ds.LogWriter(root, job.machine, prov)
    try:
        res = _replay_and_commit(job, opt, inp, prov, writer, carry, started)
        if redone is not None and res["status"] == "done":
            res["redone"] = redone
        return res
    except LogTimeout:
        writer.abort()
        return _quarantine(opt, job, prov.key, "timeout", f"replay took longer than {opt.timeout_s:g} s", prov, started)
    except ds.DatasetError:
        writer.abort()
        raise
    except (ValueError, OSError, EOFError, UnicodeError) as exc:
        writer.abort()
        return _quarantine(opt, job, prov.key, "replay", f"cannot read as a CAN log: {exc}", prov, started)
    except Exception as exc:  # a bug must not stop the fleet: record it with where it happened
        writer.abort()
        where = traceback.extract_tb(exc.__traceback__)[-1]
        reason = f"internal error {type(exc).__name__}: {exc} ({Path(where.filename).name}:{where.lineno})"
        return _quarantine(opt, job, prov.key, "replay", reason, prov, started)
    except BaseException:  # KeyboardInterrupt, a worker shutting down: nothing of the log stays
        writer.abort()
        raise


def _end_of(record: dict[str, Any], inp: Inputs) -> dict[str, Any]:
    """What the next log of the machine needs from a committed log (``chain.LogEnd``'s fields)."""
    return {
        "log_hash": record["log_hash"],
        "log_name": record["log_name"],
        "last_t": float(record["last_time_s"]),
        "state": json.loads(record["state_out"]),
        "inputs": inp.hashes,
    }


def _levels(t: dict[str, Any]) -> dict[str, float]:
    return {k: float(v) for k, v in t["time_in_level_s"].items()}


def _replay_and_commit(
    job: LogJob,
    opt: Options,
    inp: Inputs,
    prov: ds.Provenance,
    writer: ds.LogWriter,
    carry: Carry,
    started: float,
) -> dict[str, Any]:
    deadline = started + opt.timeout_s if opt.timeout_s else None
    before = Totals.from_dict(carry.state) if carry.state is not None else Totals()
    before_levels = dict(before.time_in_level_s)
    before_eval_s = before.evaluated_s
    mon = build_monitor(inp.cfg, inp.db, inp.model, Totals.from_dict(before.to_dict()))
    sink = FleetSink(writer, opt.rate_hz, deadline)
    res, cut_line = replay_log(job, mon, [sink], opt)
    c = res.counters
    problem = None
    inputs_seen = c["accepted"] + c["bad_length"] + c["out_of_range"]
    if res.first_t is None:
        problem = "no frames in the log"
    elif c["accepted"] == 0:
        ids = ", ".join(f"0x{i:X}" for i in sorted(m.frame_id for m in mon.inputs))
        problem = (
            f"none of its {c['frames_total']} frames is an input message of {inp.cfg.dbc_path.name} ({ids}): "
            "wrong DBC or configuration for this machine?"
        )
    elif (c["bad_length"] + c["out_of_range"]) > MAX_UNDECODABLE_SHARE * inputs_seen:
        problem = (
            f"{c['bad_length'] + c['out_of_range']} of {inputs_seen} input frames do not decode with "
            f"{inp.cfg.dbc_path.name} (wrong length or out of range): wrong DBC for this machine?"
        )
    if problem is not None:
        writer.abort()
        return _quarantine(opt, job, prov.key, "check", problem, prov, started)

    t0 = float(res.first_t)
    t1 = float(res.last_t if res.last_t is not None else t0)
    ev = res.warnings  # this log's level changes: the carried state has no history
    if ev:
        writer.add_rows(
            "events",
            {
                "time_s": np.array([w["t_s"] for w in ev], dtype=np.float64),
                "log_time_h": np.array([w["operating_h"] for w in ev], dtype=np.float64),
                "from_level": np.array([w["from"] for w in ev], dtype=object),
                "to_level": np.array([w["to"] for w in ev], dtype=object),
                "reason": np.array([w["reason"] for w in ev], dtype=object),
                "cm_ratio_filt_pct": np.array(
                    [math.nan if w["ratio_filt_pct"] is None else w["ratio_filt_pct"] for w in ev], dtype=np.float64
                ),
            },
        )
    state_out = without_history(mon.save_totals().to_dict())
    tot = res.totals
    first_warn = next((w["t_s"] for w in ev if w["to"] in ("low", "high")), None)
    first_fault = next((w["t_s"] for w in ev if w["to"] == "fault"), None)
    fit = sink.fit.verdict() if not carry.carried else None  # judged where a machine's life starts afresh
    after_levels = _levels(tot)
    summary: dict[str, Any] = {
        "log": job.log,
        "log_name": os.path.basename(job.log),
        "log_size_bytes": job.size,
        "first_time_s": t0,
        "last_time_s": t1,
        "duration_h": res.duration_h,
        "ticks": c["ticks"],
        "evaluated": c["evaluated"],
        "evaluated_h": (float(tot["evaluated_s"]) - before_eval_s) / 3600.0,
        **sink.stats.row(),
        "warnings_low": sum(1 for w in ev if w["to"] == "low"),
        "warnings_high": sum(1 for w in ev if w["to"] == "high"),
        "faults": sum(1 for w in ev if w["to"] == "fault"),
        "first_warning_time_s": math.nan if first_warn is None else first_warn,
        "first_fault_time_s": math.nan if first_fault is None else first_fault,
        **{f"time_{k}_h": (v - before_levels.get(k, 0.0)) / 3600.0 for k, v in after_levels.items()},
        "final_level": res.snapshot["level"],
        "final_reason": res.snapshot["reason"],
        **{f"count_{k}": int(v) for k, v in c.items()},
        # the configuration's drive facts a type model needs (``cmcan fleet train``): one quantity, V_M, oil
        "quantity": inp.cfg.quantity,
        "motor_disp_cc": None if inp.cfg.motor_disp_cc is None else float(inp.cfg.motor_disp_cc),
        "oil_nu40_cst": float(inp.cfg.oil.nu40_cst),
        "oil_nu100_cst": float(inp.cfg.oil.nu100_cst),
        "threshold_low_pct": float(inp.cfg.thresholds.low_pct),
        "threshold_high_pct": float(inp.cfg.thresholds.high_pct),
        # the band that judges while the on-board baseline learns (the report draws it where it did)
        **_learning_band(inp.cfg),
        # what the prognosis counts to, where it is on (``cmcan fleet plan`` says it per machine)
        **_end_of_life(inp.cfg),
        # fleet train's verdict on this machine in the model's metadata (the plan flags it)
        "type_verdict": type_verdict(inp.model, job.machine),
        "timeline_rate_hz": float(opt.rate_hz),
        "engine": opt.engine,
        "replay_s": time.monotonic() - started,
        "state_in": "carried" if carry.carried else "fresh",
        "state_note": carry.note,
        "carried_from": carry.from_log_hash,
        "state_out": json.dumps(state_out, sort_keys=True),
        "cut_line": cut_line,
        "fit": fit.verdict if fit else None,
        "fit_median_pct": fit.median_pct if fit else None,
        "fit_points": fit.points if fit else None,
    }
    writer.commit(summary, ds.day_of(t0), move_from=job.move_from, path_keys=(path_key(job.log),))
    end = {
        "log_hash": job.log_hash,
        "log_name": os.path.basename(job.log),
        "last_t": t1,
        "state": state_out,
        "inputs": inp.hashes,
    }
    moved = [m for m in job.move_from if m != job.machine]
    return _result(
        job,
        "done",
        prov.key,
        started,
        frames=int(c["frames_total"]),
        end=end,
        moved_from=moved,
        log_hash=job.log_hash,
        cut_line=cut_line,
    )


def _learning_band(cfg: Any) -> dict[str, Any]:
    """The logs table's learning thresholds: NULL where no baseline is learned on board."""
    if not cfg.baseline.enabled:
        return {"learning_low_pct": None, "learning_high_pct": None}
    b = cfg.baseline.settings
    return {"learning_low_pct": float(b.learning_low_pct), "learning_high_pct": float(b.learning_high_pct)}


def type_verdict(model: Any, machine: str) -> str | None:
    """Why ``cmcan fleet train`` left ``machine`` out of the type model (the model's training metadata
    names it: arrives leaking, does not fit the type), else None: a unit the on-board guard may learn
    as its own baseline when its leak lies within the type's allowance, named on the plan all the same."""
    training = getattr(getattr(model, "meta", None), "training", None)
    spread = training.get("unit_spread") if isinstance(training, dict) else None
    outliers = spread.get("outliers") if isinstance(spread, dict) else None
    v = outliers.get(machine) if isinstance(outliers, dict) else None
    why = v.get("why") if isinstance(v, dict) else None
    return why if isinstance(why, str) and why else None


def _end_of_life(cfg: Any) -> dict[str, Any]:
    """The logs table's end-of-life columns: NULL where the prognosis is off."""
    if not cfg.prognosis.enabled:
        return {"eol_kind": None, "eol_value": None, "eol_high_pct": None, "end_of_life": None}
    p = cfg.prognosis.params
    return {
        "eol_kind": p.eol_kind,
        "eol_value": float(p.eol_value),
        "eol_high_pct": float(p.eol_high_pct),
        "end_of_life": p.end_of_life_text,
    }
