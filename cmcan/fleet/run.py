"""The fleet run's driver: logs out to Dask workers, results counted as they come.

By default an embedded ``distributed.LocalCluster`` with one single-threaded worker process per core
(a replay is Python code holding the GIL); ``scheduler`` connects to an existing cluster instead and
runs the same tasks there (its workers need cmcan installed and the same paths to the logs, models
and the data set). The scheduler is reached before anything is created.

Two rounds of tasks. First every log is probed (a regular file? its hash, its first frame's time;
:func:`cmcan.fleet.task.probe_log`), so that a log named twice (the same content under two names) is
taken once, a log that had results under another machine is moved, and each machine's logs can be
put in time order. Then each machine's logs run as a chain: one task per log, the next submitted
when the previous is done, with the monitor state at its end (:mod:`cmcan.fleet.chain`); machines
run side by side. At most a few tasks per worker thread are in flight, so a run over a hundred
thousand logs does not flood the scheduler. A task that dies with its worker is quarantined here; a
data set that cannot be written (a full disk, no permission) stops the run with the path named.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import socket
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cmcan.errors import CmcanError, Kind
from cmcan.fleet import dataset as ds
from cmcan.fleet.chain import LogEnd, next_carry
from cmcan.fleet.sources import Refused
from cmcan.fleet.task import LogJob, Options, hash_key, path_key, probe_log, process_log, safe_reason

log = logging.getLogger("cmcan.fleet")
CLOSE_TIMEOUT_S = 10.0  # closing the Dask client or cluster, after the work
IN_FLIGHT_PER_THREAD = 2
WORKERS_END_S = 15.0  # how long a cleanup after the workers were stopped waits for them to end


@dataclass
class RunReport:
    logs: int
    counts: Counter = field(default_factory=Counter)
    frames: int = 0
    seconds: float = 0.0
    workers: int = 0
    orphans_removed: int = 0
    quarantined: list[dict[str, Any]] = field(default_factory=list)
    refused: list[dict[str, Any]] = field(default_factory=list)
    moved: list[dict[str, Any]] = field(default_factory=list)
    redone: list[dict[str, Any]] = field(default_factory=list)
    cut: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    interrupted: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {
            "logs": self.logs,
            "done": self.counts["done"],
            "skipped": self.counts["skipped"],
            "quarantined": self.counts["quarantined"],
            "refused": len(self.refused),
            "frames": self.frames,
            "seconds": round(self.seconds, 2),
            "frames_per_s": round(self.frames / self.seconds, 1) if self.seconds > 0 else None,
            "workers": self.workers,
            "orphans_removed": self.orphans_removed,
            "quarantine": self.quarantined,
            "refused_sources": self.refused,
            "moved": self.moved,
            "redone": self.redone,
            "cut": self.cut,
            "notes": self.notes,
            "interrupted": self.interrupted,
        }


def require_dask() -> None:
    try:
        import distributed  # noqa: F401
        import pyarrow  # noqa: F401
    except ImportError as exc:
        raise CmcanError(
            f"this needs the 'fleet' extra: pip install 'cmcan[fleet]' ({exc.name} is missing)", Kind.UNAVAILABLE
        ) from None


SCHEDULER_CONNECT_S = 10.0


def check_scheduler(address: str, timeout_s: float = SCHEDULER_CONNECT_S) -> None:
    """A TCP scheduler address answers a connection (fails in a moment where Dask's client would retry
    for its whole timeout); other transports are left to the client."""
    if not address.startswith("tcp://") and "://" in address:
        return
    hostport = address.removeprefix("tcp://").split("/", 1)[0]
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise CmcanError(f"--scheduler {address}: expected tcp://HOST:PORT", Kind.USAGE)
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except OSError as exc:
        raise CmcanError(
            f"cannot reach the Dask scheduler at {address}: {exc.strerror or exc}; nothing was written",
            Kind.UNAVAILABLE,
        ) from None


def make_client(scheduler: str | None, workers: int | None, memory_limit: str = "auto") -> Any:
    """A client of the given scheduler, or of an embedded LocalCluster sized to this machine."""
    import dask
    from distributed import Client, LocalCluster

    quiet = logging.getLogger().getEffectiveLevel() > logging.INFO
    if quiet:  # distributed talks at INFO; cmcan -v shows it
        for name in ("distributed", "tornado"):
            logging.getLogger(name).setLevel(logging.ERROR)

    if scheduler:
        check_scheduler(scheduler)
        try:
            return Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise CmcanError(
                f"cannot reach the Dask scheduler at {scheduler}: {exc}; nothing was written", Kind.UNAVAILABLE
            ) from None
    n = workers or os.cpu_count() or 1
    # Workers of an embedded cluster die with their parent; no dashboard (no port to take).
    dask.config.set({"distributed.worker.daemon": True, "distributed.admin.tick.limit": "30s"})
    # Dask's nanny sets MALLOC_TRIM_THRESHOLD_ in its workers, which also freezes glibc's mmap threshold
    # at 128 KiB: every array of a replay chunk is then mapped and faulted in afresh, and a log costs
    # about 1.6x the CPU it costs in one process (bench/bench_fleet.py). glibc's own thresholds here.
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    if quiet:
        # A worker whose heartbeat meets the scheduler closing (the run ended, or gave up on a full
        # disk) logs that with a traceback at ERROR; a task's own failure reaches the client as its
        # exception. A worker reads its log levels from the environment as it starts (LocalCluster's
        # silence_logs reaches only the nanny's logger there), so without -v it says nothing below
        # CRITICAL.
        environ["DASK_LOGGING__DISTRIBUTED"] = "critical"
    dask.config.set({"distributed.nanny.pre-spawn-environ": environ})
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        memory_limit=memory_limit,
        dashboard_address=None,
        silence_logs=logging.ERROR if quiet else logging.INFO,
    )
    return Client(cluster)


def close_client(client: Any) -> None:
    """The client closed, and an embedded cluster with it. Called when the work is done (or given up):
    a close that times out on a loaded machine is said, never the command's end (an embedded
    cluster's workers are daemonic: they end with this process)."""
    cluster = getattr(client, "cluster", None)
    for what, part in (("client", client), ("cluster", cluster)):
        if part is None:
            continue
        try:
            part.close(timeout=CLOSE_TIMEOUT_S)
        except (TimeoutError, OSError) as exc:
            log.warning("the Dask %s did not close within %g s (%s); its work is done", what, CLOSE_TIMEOUT_S, exc)


def check_target(root: Path) -> None:
    """The data set folder can be used (an existing data set, or nothing there yet), without creating it."""
    if (root / "_dataset.json").exists():
        ds.open_dataset(root, create=False)
        return
    if root.exists() and not root.is_dir():
        raise CmcanError(f"{root}: exists and is not a folder", Kind.CANT_CREATE)
    if root.is_dir() and any(root.iterdir()):
        raise CmcanError(f"{root}: folder exists, is not empty and is not a cmcan fleet data set", Kind.CANT_CREATE)


def run_fleet(
    jobs: list[LogJob],
    opt: Options,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: Callable[[dict[str, Any], RunReport], None] | None = None,
    client: Any = None,
    refused: list[Refused] | None = None,
) -> RunReport:
    """Every job through the cluster; returns the counts. KeyboardInterrupt stops the run: committed
    logs stay, nothing half-written does, and the next run does the rest. ``refused`` (source
    entries not read) get a quarantine row each where their machine is known."""
    require_dask()
    root = Path(opt.dataset)
    check_target(root)
    own = client is None
    if own:
        client = make_client(scheduler, workers)  # an unreachable scheduler: nothing created yet
    report = RunReport(logs=len(jobs) + len(refused or []))
    started = time.monotonic()
    failed = None
    try:
        _run(client, root, jobs, opt, report, progress, refused or [], started)
    except ds.DatasetError as exc:
        failed = ds.DatasetError(
            f"{exc}; the logs committed so far stay, run the same command again when it is fixed", exc.kind
        )
    finally:
        if own:
            close_client(client)
            if report.interrupted:  # the staging folders of the workers just stopped (kept while they ran)
                _clean(root, locked=False, writers_wait_s=WORKERS_END_S)
    if failed is not None:
        if (root / "_dataset.json").exists():
            # what the tasks were staging when the data set failed them (if it can)
            _clean(root, locked=False, writers_wait_s=WORKERS_END_S if own else 0.0)
        raise failed
    return report


def _run(
    client: Any,
    root: Path,
    jobs: list[LogJob],
    opt: Options,
    report: RunReport,
    progress: Callable[[dict[str, Any], RunReport], None] | None,
    refused: list[Refused],
    started: float,
) -> None:
    root = ds.open_dataset(root, create=True)
    opt = dataclasses.replace(opt, dataset=os.path.abspath(root))
    with ds.writer_lock(root):
        report.orphans_removed = ds.remove_orphans(root)
        try:
            report.workers = len(client.scheduler_info(n_workers=-1)["workers"])
            _record_refused(root, refused, report, progress)
            probed = _probe_all(client, jobs, opt, report, progress)
            _run_chains(client, _plan(probed, ds.log_index(root), report), opt, report, progress)
        except KeyboardInterrupt:
            report.interrupted = True
            raise
        finally:
            report.seconds = time.monotonic() - started
            if report.interrupted:  # what the killed workers were staging
                _clean(root)


def _clean(root: Path, locked: bool = True, writers_wait_s: float = 0.0) -> None:
    """What the tasks left (``locked``: this run holds the writer lock; else it is taken, and
    another run that holds it meanwhile cleans for itself); workers that are ending waited for up
    to ``writers_wait_s``."""
    with contextlib.suppress(CmcanError):
        if locked:
            ds.remove_orphans(root, writers_wait_s=writers_wait_s)
            return
        with ds.writer_lock(root):
            ds.remove_orphans(root, writers_wait_s=writers_wait_s)


def _record_refused(
    root: Path, refused: list[Refused], report: RunReport, progress: Callable[[dict[str, Any], RunReport], None] | None
) -> None:
    for r in refused:
        report.refused.append({"path": r.path, "machine": r.machine, "origin": r.origin, "reason": r.reason})
        res = {"machine": r.machine, "log": r.path, "status": "refused", "reason": r.reason, "frames": 0}
        if r.machine is not None:
            ds.write_quarantine(
                root,
                r.machine,
                path_key(r.path),
                {
                    "log": r.path,
                    "config": None,
                    "model": None,
                    "stage": "source",
                    "reason": r.reason,
                    "options": "",
                    "quarantined_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                    "log_hash": None,
                    "config_hash": None,
                    "dbc_hash": None,
                    "model_hash": None,
                    "cmcan_version": ds.__version__,
                },
            )
        if progress:
            progress(res, report)


def _window(client: Any) -> int:
    threads = sum(w.get("nthreads", 1) for w in client.scheduler_info(n_workers=-1)["workers"].values()) or 1
    return max(2, IN_FLIGHT_PER_THREAD * threads)


def _count(
    res: dict[str, Any], job: LogJob, report: RunReport, progress: Callable[[dict[str, Any], RunReport], None] | None
) -> None:
    """A log's final result into the report."""
    if res["status"] == "error":  # the data set cannot be written: stop here
        raise ds.DatasetError(res["message"], Kind[res["kind"]])
    report.counts[res["status"]] += 1
    report.frames += res.get("frames", 0)
    if res["status"] == "quarantined":
        report.quarantined.append({"machine": job.machine, "log": job.log, "reason": res.get("reason")})
    for m in res.get("moved_from") or ():
        report.moved.append({"log": job.log, "from": m, "to": job.machine})
    if res.get("redone"):
        report.redone.append({"machine": job.machine, "log": job.log, "damage": res["redone"]})
    if res.get("cut_line") is not None:
        report.cut.append({"machine": job.machine, "log": job.log, "cut_line": res["cut_line"]})
    if progress:
        progress(res, report)


def _submit(client: Any, fn: Callable[..., Any], job: LogJob, *args: Any) -> Any:
    # pure=False: a rerun must run again (the data set changed), not reuse a cached result
    return client.submit(fn, job, *args, pure=False, key=f"{fn.__name__}-{job.machine}-{time.monotonic_ns()}")


def _gather(
    client: Any,
    todo: deque[tuple[Callable[..., Any], LogJob, tuple[Any, ...]]],
    opt: Options,
    on_result: Callable[[LogJob, dict[str, Any]], list[tuple[Callable[..., Any], LogJob, tuple[Any, ...]]]],
) -> None:
    """Run the tasks in ``todo`` with a bounded window; ``on_result`` may queue more."""
    from distributed import as_completed

    window = _window(client)
    by_future: dict[Any, LogJob] = {}
    ac = as_completed([])

    def fill() -> None:
        while todo and len(by_future) < window:
            fn, job, args = todo.popleft()
            fut = _submit(client, fn, job, *args)
            by_future[fut] = job
            ac.add(fut)

    fill()
    try:
        for fut in ac:
            job = by_future.pop(fut)
            try:
                res = fut.result()
            except Exception as exc:  # the worker died (KilledWorker) or the task could not run there
                res = _worker_failure(opt, job, exc)
            todo.extend(on_result(job, res))
            fill()
    except BaseException:
        for f in list(by_future):
            f.cancel()
        raise


def _probe_all(
    client: Any,
    jobs: list[LogJob],
    opt: Options,
    report: RunReport,
    progress: Callable[[dict[str, Any], RunReport], None] | None,
) -> list[tuple[LogJob, float]]:
    """Every log probed: the probed jobs (with the probe's CPU seconds); the others counted."""
    probed: list[tuple[LogJob, float]] = []

    def on_result(job: LogJob, res: dict[str, Any]) -> list[Any]:
        if res["status"] == "probed":
            probed.append((res["job"], res.get("cpu_s", 0.0)))
        else:
            _count(res, job, report, progress)
        return []

    _gather(client, deque((probe_log, j, (opt,)) for j in jobs), opt, on_result)
    order = {(j.machine, j.log): i for i, j in enumerate(jobs)}
    return sorted(probed, key=lambda p: order[(p[0].machine, p[0].log)])


@dataclass
class _Plan:
    chains: dict[str, deque[tuple[LogJob, float]]]
    duplicates: list[tuple[LogJob, LogJob]]


def _plan(probed: list[tuple[LogJob, float]], index: dict[str, set[str]], report: RunReport) -> _Plan:
    """One log per content (the first named wins, a note names both), each moved from the machines
    it had rows under, and each machine's logs in time order."""
    first_of: dict[str, LogJob] = {}
    chains: dict[str, list[tuple[LogJob, float]]] = {}
    duplicates = []
    for job, cpu in probed:
        assert job.log_hash is not None
        kept = first_of.get(job.log_hash)
        if kept is not None:
            duplicates.append((job, kept))
            report.notes.append(
                f"{job.log} (machine {job.machine}) has the same content as {kept.log} (machine {kept.machine}): "
                "replayed once, as the latter"
            )
            res = {"machine": job.machine, "log": job.log, "status": "skipped", "frames": 0, "reason": "same content"}
            _count(res, job, report, None)
            continue
        first_of[job.log_hash] = job
        others = index.get(job.log_hash[:16], set()) | index.get(path_key(job.log)[:16], set())
        job = dataclasses.replace(job, move_from=tuple(sorted(others - {job.machine})))
        chains.setdefault(job.machine, []).append((job, cpu))
    ordered = {
        m: deque(sorted(c, key=lambda jc: (jc[0].first_t is None, jc[0].first_t or 0.0, jc[0].log_hash)))
        for m, c in chains.items()
    }
    return _Plan(ordered, duplicates)


def _run_chains(
    client: Any,
    plan: _Plan,
    opt: Options,
    report: RunReport,
    progress: Callable[[dict[str, Any], RunReport], None] | None,
) -> None:
    """Each machine's logs one after the other (the state at one's end starts the next), machines
    side by side."""
    ends: dict[str, LogEnd | None] = dict.fromkeys(plan.chains)
    cpu_of: dict[tuple[str, str], float] = {}

    def next_of(machine: str) -> list[Any]:
        chain = plan.chains[machine]
        if not chain:
            return []
        job, cpu = chain.popleft()
        cpu_of[(job.machine, job.log)] = cpu
        return [(process_log, job, (opt, next_carry(ends[machine], job.first_t)))]

    def on_result(job: LogJob, res: dict[str, Any]) -> list[Any]:
        res["cpu_s"] = res.get("cpu_s", 0.0) + cpu_of.pop((job.machine, job.log), 0.0)
        _count(res, job, report, progress)
        end = res.get("end")
        if end is not None:
            ends[job.machine] = LogEnd(
                end["log_hash"], end["log_name"], float(end["last_t"]), end["state"], tuple(end["inputs"])
            )
        return next_of(job.machine)

    todo: deque[Any] = deque()
    for m in plan.chains:
        todo.extend(next_of(m))
    _gather(client, todo, opt, on_result)


def _worker_failure(opt: Options, job: LogJob, exc: BaseException) -> dict[str, Any]:
    key = hash_key(job.log_hash) if job.log_hash else path_key(job.log)
    reason = safe_reason(f"{type(exc).__name__}: {exc}", (job.log, job.config, job.model))
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
            "options": "",
            "quarantined_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "log_hash": job.log_hash,
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
