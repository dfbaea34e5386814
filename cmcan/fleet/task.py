"""One log, start to finish, inside a Dask worker: hash, skip or replay, reduce, commit or quarantine.

A task gets paths (the log, its configuration and model) and the data set's folder, never a monitor
or a model session: the worker builds those itself, and keeps the loaded DBC and model of each
(configuration, model) pair for the next log. Every failure of a log is caught here and recorded in
the quarantine table, so one bad log never stops a run.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cmcan import config as cfgmod
from cmcan.assemble import build_monitor, dbc_for, load_model_for, model_file
from cmcan.errors import CmcanError
from cmcan.fleet import dataset as ds
from cmcan.fleet.aggregate import RUN_SHIFT, Downsampler, LogStats
from cmcan.frame import Frame
from cmcan.monitor.gating import Gate
from cmcan.monitor.tick import LEVEL_NAMES, TickColumns
from cmcan.monitor.warnings import Level, Reason
from cmcan.replay import replay_file

GATE_NAMES = np.array([g.name.lower() for g in sorted(Gate)], dtype=object)
LEVEL_NAME_ARR = np.array([LEVEL_NAMES[lv] for lv in sorted(Level)], dtype=object)
REASON_NAMES = np.array([r.name.lower() for r in sorted(Reason)], dtype=object)
NAMED = {"gate": GATE_NAMES, "warning_level": LEVEL_NAME_ARR, "warning_reason": REASON_NAMES}
# A log whose input frames mostly fail to decode was recorded with another signal layout.
MAX_UNDECODABLE_SHARE = 0.5


@dataclass(frozen=True)
class LogJob:
    machine: str
    log: str
    config: str | None = None  # None: the shipped configuration
    model: str | None = None  # None: the configuration's model
    origin: str = ""  # where the log was named (a manifest's line), for messages about it


@dataclass(frozen=True)
class Options:
    dataset: str
    rate_hz: float = 1.0
    timeout_s: float | None = 3600.0
    retry_quarantined: bool = False
    engine: str = "columnar"


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


class FleetSink:
    """Ticks to timeline rows at the configured rate and to the log's statistics; stops a replay
    that runs past its time limit."""

    wants_ticks = True
    wants_frames = False

    def __init__(self, writer: ds.LogWriter, rate_hz: float, deadline: float | None) -> None:
        self.writer = writer
        self.down = Downsampler(rate_hz)
        self.stats = LogStats()
        self.deadline = deadline
        self.t0 = 0.0

    def start(self, t0: float) -> None:
        self.t0 = t0
        self.stats.t0 = t0

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
        self._rows(self.down.add(chunk))

    def frames(self, frames: Sequence[Frame]) -> None:
        pass

    def close(self) -> None:
        self._rows(self.down.finish())

    def abort(self) -> None:
        pass


def path_key(log: str) -> str:
    return hashlib.sha256(os.path.abspath(log).encode()).hexdigest()[:16] + "-" + "0" * 12


def _quarantine(
    opt: Options, job: LogJob, key: str, stage: str, reason: str, prov: ds.Provenance | None, started: float
) -> dict[str, Any]:
    root = Path(opt.dataset)
    row = {
        "log": job.log,
        "config": job.config,
        "model": job.model,
        "stage": stage,
        "reason": reason,
        "quarantined_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **(
            prov.columns()
            if prov
            else {
                "log_hash": None,
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


def process_log(job: LogJob, opt: Options) -> dict[str, Any]:
    """The whole life of one log in the data set; never raises for a bad log (quarantines it).
    The result says what happened, with the task's wall-clock and CPU seconds (for progress and
    benchmarks, never for the data)."""
    cpu0 = time.process_time()
    res = _process_log(job, opt)
    res["cpu_s"] = time.process_time() - cpu0
    return res


def _process_log(job: LogJob, opt: Options) -> dict[str, Any]:
    started = time.monotonic()
    root = Path(opt.dataset)
    try:
        log_hash = ds.sha256_file(job.log)
    except OSError as exc:
        named = f" (named in {job.origin})" if job.origin else ""
        return _quarantine(opt, job, path_key(job.log), "read", f"cannot read the log: {exc}{named}", None, started)
    try:
        inp = load_inputs(job.config, job.model)
    except (CmcanError, OSError, ValueError) as exc:
        key = f"{log_hash[:16]}-{'0' * 12}"
        prov = ds.Provenance(log_hash, "", "", "")
        return _quarantine(opt, job, key, "inputs", str(exc), prov, started)
    prov = ds.Provenance(log_hash, inp.config_hash, inp.dbc_hash, inp.model_hash)
    if ds.is_committed(root, job.machine, prov.key):
        return _result(job, "skipped", prov.key, started)
    if ds.is_quarantined(root, job.machine, prov.key) and not opt.retry_quarantined:
        return _result(job, "skipped", prov.key, started, reason="quarantined before")
    writer = ds.LogWriter(root, job.machine, prov)
    try:
        return _replay_and_commit(job, opt, inp, prov, writer, started)
    except LogTimeout:
        writer.abort()
        return _quarantine(opt, job, prov.key, "timeout", f"replay took longer than {opt.timeout_s:g} s", prov, started)
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


def _replay_and_commit(
    job: LogJob, opt: Options, inp: Inputs, prov: ds.Provenance, writer: ds.LogWriter, started: float
) -> dict[str, Any]:
    deadline = started + opt.timeout_s if opt.timeout_s else None
    mon = build_monitor(inp.cfg, inp.db, inp.model)
    sink = FleetSink(writer, opt.rate_hz, deadline)
    res = replay_file(job.log, mon, [sink], engine=opt.engine)
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
    ev = res.warnings
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
    tot = res.totals
    first_warn = next((w["t_s"] for w in ev if w["to"] in ("low", "high")), None)
    first_fault = next((w["t_s"] for w in ev if w["to"] == "fault"), None)
    st = os.stat(job.log)
    summary: dict[str, Any] = {
        "log": job.log,
        "log_name": os.path.basename(job.log),
        "log_size_bytes": st.st_size,
        "first_time_s": t0,
        "last_time_s": t1,
        "duration_h": res.duration_h,
        "ticks": c["ticks"],
        "evaluated": c["evaluated"],
        "evaluated_h": tot["evaluated_s"] / 3600.0,
        **sink.stats.row(),
        "warnings_low": sum(1 for w in ev if w["to"] == "low"),
        "warnings_high": sum(1 for w in ev if w["to"] == "high"),
        "faults": sum(1 for w in ev if w["to"] == "fault"),
        "first_warning_time_s": math.nan if first_warn is None else first_warn,
        "first_fault_time_s": math.nan if first_fault is None else first_fault,
        **{f"time_{k}_h": v / 3600.0 for k, v in tot["time_in_level_s"].items()},
        "final_level": res.snapshot["level"],
        "final_reason": res.snapshot["reason"],
        **{f"count_{k}": int(v) for k, v in c.items()},
        "threshold_low_pct": float(inp.cfg.thresholds.low_pct),
        "threshold_high_pct": float(inp.cfg.thresholds.high_pct),
        "timeline_rate_hz": float(opt.rate_hz),
        "engine": opt.engine,
        "replay_s": time.monotonic() - started,
    }
    writer.commit(summary, ds.day_of(t0))
    return _result(job, "done", prov.key, started, frames=int(c["frames_total"]))
