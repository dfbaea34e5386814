"""The fleet run's driver: logs out to Dask workers, one task per log, results counted as they come.

By default an embedded ``distributed.LocalCluster`` with one single-threaded worker process per core
(a replay is Python code holding the GIL); ``scheduler`` connects to an existing cluster instead and
runs the same tasks there (its workers need cmcan installed and the same paths to the logs, models
and the data set). At most a few tasks per worker thread are in flight, so a run over a hundred
thousand logs does not flood the scheduler. A task that dies with its worker is quarantined here.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cmcan.errors import CmcanError, Kind
from cmcan.fleet import dataset as ds
from cmcan.fleet.task import LogJob, Options, process_log

log = logging.getLogger("cmcan.fleet")
IN_FLIGHT_PER_THREAD = 2


@dataclass
class RunReport:
    logs: int
    counts: Counter = field(default_factory=Counter)
    frames: int = 0
    seconds: float = 0.0
    workers: int = 0
    orphans_removed: int = 0
    quarantined: list[dict[str, Any]] = field(default_factory=list)
    interrupted: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {
            "logs": self.logs,
            "done": self.counts["done"],
            "skipped": self.counts["skipped"],
            "quarantined": self.counts["quarantined"],
            "frames": self.frames,
            "seconds": round(self.seconds, 2),
            "frames_per_s": round(self.frames / self.seconds, 1) if self.seconds > 0 else None,
            "workers": self.workers,
            "orphans_removed": self.orphans_removed,
            "quarantine": self.quarantined,
            "interrupted": self.interrupted,
        }


def _require_dask() -> None:
    try:
        import distributed  # noqa: F401
        import pyarrow  # noqa: F401
    except ImportError as exc:
        raise CmcanError(
            f"this needs the 'fleet' extra: pip install 'cmcan[fleet]' ({exc.name} is missing)", Kind.UNAVAILABLE
        ) from None


def make_client(scheduler: str | None, workers: int | None, memory_limit: str = "auto") -> Any:
    """A client of the given scheduler, or of an embedded LocalCluster sized to this machine."""
    import dask
    from distributed import Client, LocalCluster

    if logging.getLogger().getEffectiveLevel() > logging.INFO:  # distributed talks at INFO; cmcan -v shows it
        for name in ("distributed", "tornado"):
            logging.getLogger(name).setLevel(logging.ERROR)

    if scheduler:
        try:
            return Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise CmcanError(f"cannot reach the Dask scheduler at {scheduler}: {exc}", Kind.UNAVAILABLE) from None
    n = workers or os.cpu_count() or 1
    # Workers of an embedded cluster die with their parent; no dashboard (no port to take).
    dask.config.set({"distributed.worker.daemon": True, "distributed.admin.tick.limit": "30s"})
    # Dask's nanny sets MALLOC_TRIM_THRESHOLD_ in its workers, which also freezes glibc's mmap threshold
    # at 128 KiB: every array of a replay chunk is then mapped and faulted in afresh, and a log costs
    # about 1.6x the CPU it costs in one process (bench/bench_fleet.py). glibc's own thresholds here.
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    dask.config.set({"distributed.nanny.pre-spawn-environ": environ})
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        memory_limit=memory_limit,
        dashboard_address=None,
        silence_logs=logging.ERROR,
    )
    return Client(cluster)


def _close(client: Any) -> None:
    cluster = getattr(client, "cluster", None)
    try:
        client.close(timeout=10)
    finally:
        if cluster is not None:
            cluster.close(timeout=10)


def run_fleet(
    jobs: list[LogJob],
    opt: Options,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: Callable[[dict[str, Any], RunReport], None] | None = None,
    client: Any = None,
) -> RunReport:
    """Every job through ``process_log`` on the cluster; returns the counts. KeyboardInterrupt stops
    the run: committed logs stay, nothing half-written does, and the next run does the rest."""
    _require_dask()
    root = ds.open_dataset(Path(opt.dataset), create=True)
    opt = dataclasses.replace(opt, dataset=os.path.abspath(root))
    report = RunReport(logs=len(jobs))
    started = time.monotonic()
    with ds.writer_lock(root):
        report.orphans_removed = ds.remove_orphans(root)
        own = client is None
        if own:
            client = make_client(scheduler, workers)
        try:
            report.workers = len(client.scheduler_info(n_workers=-1)["workers"])
            _drive(client, jobs, opt, report, progress)
        except KeyboardInterrupt:
            report.interrupted = True
            raise
        finally:
            report.seconds = time.monotonic() - started
            if own:
                _close(client)
            if report.interrupted:  # what the killed workers were staging
                ds.remove_orphans(root)
    return report


def _drive(
    client: Any,
    jobs: list[LogJob],
    opt: Options,
    report: RunReport,
    progress: Callable[[dict[str, Any], RunReport], None] | None,
) -> None:
    from distributed import as_completed

    threads = sum(w.get("nthreads", 1) for w in client.scheduler_info(n_workers=-1)["workers"].values()) or 1
    window = max(2, IN_FLIGHT_PER_THREAD * threads)
    pending = iter(jobs)
    by_future: dict[Any, LogJob] = {}

    def submit(n: int) -> list[Any]:
        out = []
        for _ in range(n):
            job = next(pending, None)
            if job is None:
                break
            # pure=False: a rerun must run again (the data set changed), not reuse a cached result
            fut = client.submit(
                process_log, job, opt, pure=False, key=f"log-{job.machine}-{len(by_future)}-{time.monotonic_ns()}"
            )
            by_future[fut] = job
            out.append(fut)
        return out

    ac = as_completed(submit(window))
    try:
        for fut in ac:
            job = by_future.pop(fut)
            try:
                res = fut.result()
            except Exception as exc:  # the worker died (KilledWorker) or the task could not run there
                res = _worker_failure(opt, job, exc)
            report.counts[res["status"]] += 1
            report.frames += res.get("frames", 0)
            if res["status"] == "quarantined":
                report.quarantined.append({"machine": job.machine, "log": job.log, "reason": res.get("reason")})
            if progress:
                progress(res, report)
            for f in submit(1):
                ac.add(f)
    except BaseException:
        for f in list(by_future):
            f.cancel()
        raise


def _worker_failure(opt: Options, job: LogJob, exc: BaseException) -> dict[str, Any]:
    from cmcan.fleet.task import path_key

    key = path_key(job.log)
    reason = f"{type(exc).__name__}: {exc}"
    ds.write_quarantine(
        Path(opt.dataset),
        job.machine,
        key,
        {
            "log": job.log,
            "config": job.config,
            "model": job.model,
            "stage": "worker",
            "reason": reason,
            "quarantined_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "log_hash": None,
            "config_hash": None,
            "dbc_hash": None,
            "model_hash": None,
            "cmcan_version": ds.__version__,
        },
    )
    return {
        "machine": job.machine,
        "log": job.log,
        "status": "quarantined",
        "key": key,
        "frames": 0,
        "reason": f"worker: {reason}",
    }
