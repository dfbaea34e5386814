"""The type model's points out of the data set, one Dask task per machine (``cmcan fleet train``).

The driver reads each machine's commit records (one-row files, cheap), checks that the machines were
replayed with one configuration's quantity, V_M and oil, and places each log on its machine's
operating-hour axis (the logged hours of its earlier logs, as the ``machine_logs`` view does). A task
per machine then checks the timeline files its records name (sizes, SHA-256, page checksums), reads
the columns a type model needs and keeps the healthy rows (:func:`cmcan.fleet.train.machine_points`):
what comes back is arrays, gathered in machine order.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cmcan.errors import CmcanError, Kind
from cmcan.fleet import dataset as ds
from cmcan.fleet.train import DriveFacts, MachinePoints, machine_points
from cmcan.roles import MODEL_INPUTS

TIMELINE_COLUMNS = ("time_s", "log_time_h", "ticks", "evaluated", "gate", "warning_level", "measured", *MODEL_INPUTS)
# Read where the data set has them: the replay model's prediction and its hash, the reference each
# machine is judged against (cmcan.fleet.train.off_reference), and the baseline's state (a monitoring
# baseline corrected that prediction by the machine's own).
REFERENCE_COLUMNS = ("predicted", "model_hash", "baseline_state")
FACT_COLUMNS = ("quantity", "motor_disp_cc", "oil_nu40_cst", "oil_nu100_cst")


@dataclass(frozen=True)
class MachineLogs:
    """What a machine's task needs: its committed logs' records and their offsets on its hour axis."""

    machine: str
    records: tuple[dict[str, Any], ...]
    offsets_h: tuple[float, ...]


def machine_logs(root: Path, machine: str) -> MachineLogs:
    """A machine's commit records (checked), in time order, with each log's operating-hour offset."""
    base = ds.partition(root, ds.SUMMARY_TABLE, machine)
    records, problems = [], []
    for f in sorted(base.glob("day=*/*.parquet")):
        if f.name.startswith("."):
            continue
        try:
            records.append(ds.read_record(f))
        except ds.Damaged as exc:
            problems += exc.problems
    if problems:
        raise ds.Damaged(problems)
    records.sort(key=lambda r: (r["first_time_s"], r["log_hash"]))
    offsets = np.concatenate([[0.0], np.cumsum([float(r["duration_h"]) for r in records])[:-1]]) if records else []
    return MachineLogs(machine, tuple(records), tuple(float(o) for o in offsets))


def drive_facts(logs: MachineLogs, dataset: str) -> DriveFacts:
    """The quantity, V_M and oil the machine's logs were replayed with: one set of them for the machine."""
    seen: dict[tuple[Any, ...], str] = {}
    for r in logs.records:
        if any(c not in r for c in FACT_COLUMNS) or r["quantity"] is None:
            raise CmcanError(
                f"{dataset}: machine {logs.machine}: log {r.get('log_name')} does not record the configuration's "
                "quantity, V_M and oil (replayed by an older cmcan); `cmcan fleet drop` the machine and replay its "
                "logs with this one",
                Kind.DATA,
            )
        key = tuple(None if r[c] is None else (r[c] if c == "quantity" else float(r[c])) for c in FACT_COLUMNS)
        seen.setdefault(key, r["log_name"])
    if len(seen) > 1:
        (a, la), (b, lb) = list(seen.items())[:2]
        i = next(i for i, (u, v) in enumerate(zip(a, b, strict=True)) if u != v)
        raise CmcanError(
            f"{dataset}: machine {logs.machine}: its logs were replayed with different {FACT_COLUMNS[i]} "
            f"({la}: {a[i]}, {lb}: {b[i]}); a type model needs one configuration per machine",
            Kind.DATA,
        )
    q, vm, nu40, nu100 = next(iter(seen))
    return DriveFacts(q, vm, nu40, nu100)


def read_machine(root: str, logs: MachineLogs, until_h: float, verify: bool) -> MachinePoints | list[str]:
    """A Dask task: a machine's timeline read (its files checked first unless ``verify`` is off) and its
    healthy points; or the problems of its damaged or too old files (the driver raises them)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    base = Path(root)
    parts: list[dict[str, Any]] = []
    problems: list[str] = []
    for rec, offset_h in zip(logs.records, logs.offsets_h, strict=True):
        if verify:
            problems += ds.check_files(base, logs.machine, rec, ("timeline",))
            if problems:
                continue
        for f in ds.data_files(base, logs.machine, rec, "timeline"):
            try:
                have = set(pq.read_schema(f).names)
                missing = [c for c in TIMELINE_COLUMNS if c not in have]
                if missing:
                    problems.append(
                        f"{f}: no column {', '.join(missing)} (replayed by an older cmcan): drop the machine and "
                        "replay its logs"
                    )
                    continue
                names = [*TIMELINE_COLUMNS, *(c for c in REFERENCE_COLUMNS if c in have)]
                t = pq.read_table(f, columns=names, page_checksum_verification=True)
            except (OSError, pa.ArrowException) as exc:
                problems.append(f"{f}: not readable ({str(exc).splitlines()[0][:120]})")
                continue
            cols = {c: t.column(c).to_numpy(zero_copy_only=False) for c in names}
            cols["operating_h"] = offset_h + np.asarray(cols["log_time_h"], dtype=np.float64)
            parts.append(cols)
    if problems:
        return problems
    names = [*TIMELINE_COLUMNS, *(c for c in REFERENCE_COLUMNS if parts and all(c in p for p in parts)), "operating_h"]
    cols = {c: np.concatenate([p[c] for p in parts]) if parts else np.array([]) for c in names}
    return machine_points(logs.machine, cols, until_h)


def gather_points(
    root: Path,
    machines: list[MachineLogs],
    until_h: float = math.inf,
    verify: bool = True,
    scheduler: str | None = None,
    workers: int | None = None,
    client: Any = None,
) -> list[MachinePoints]:
    """Every machine's healthy points, read on the cluster side by side, in machine order; a damaged
    file stops it with :class:`cmcan.fleet.dataset.Damaged` naming the files."""
    from cmcan.fleet.run import close_client, make_client, require_dask

    require_dask()
    own = client is None
    if own:
        client = make_client(scheduler, workers)
    try:
        futures = [
            client.submit(
                read_machine,
                str(root),
                m,
                until_h,
                verify,
                pure=False,
                key=f"fleet-train-{m.machine}-{time.monotonic_ns()}",
            )
            for m in machines
        ]
        results = client.gather(futures)
    finally:
        if own:
            close_client(client)
    problems = [p for r in results if isinstance(r, list) for p in r]
    if problems:
        raise ds.Damaged(problems)
    return sorted((r for r in results if isinstance(r, MachinePoints)), key=lambda mp: mp.machine)
