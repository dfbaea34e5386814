"""Which logs a fleet run covers, and which machine each belongs to.

A source is a manifest CSV, a folder, a glob pattern or a single log:

- manifest (``*.csv`` with a header ``machine,log[,config][,model]``): one row per log; relative
  paths are relative to the manifest's folder; an empty config or model falls back to the run's
  ``--config`` / ``--model``;
- folder: every log below it (``.log``, ``.log.gz``, ``.asc``, ``.blf``, ``.trc``, ``.mf4``,
  ``.db``; CSV logs only through a manifest). The machine is the first folder below the given one
  (``fleet/exc-017/2026/01/a.log`` -> ``exc-017``); a log directly in the given folder belongs to the
  machine named by its file name up to the first ``_`` (``exc-017_20260102.log`` -> ``exc-017``);
- glob (``'fleet/*/2026-01-*.log'``, ``**`` allowed): the matches, with the same rule below the
  pattern's folder part (the part before the first wildcard);
- a single log: the machine from its file name as above.
"""

from __future__ import annotations

import csv
import glob
import os
from pathlib import Path

from cmcan.errors import CmcanError, Kind
from cmcan.fleet.dataset import check_machine
from cmcan.fleet.task import LogJob

LOG_SUFFIXES = (".log", ".log.gz", ".asc", ".asc.gz", ".blf", ".trc", ".trc.gz", ".mf4", ".db")
MANIFEST_COLUMNS = ("machine", "log", "config", "model")


def is_log(path: Path) -> bool:
    return path.name.lower().endswith(LOG_SUFFIXES)


def machine_of(log: Path, root: Path) -> str:
    """The machine rule for folders and globs (see the module's notes)."""
    rel = log.relative_to(root)
    if len(rel.parts) > 1:
        return check_machine(rel.parts[0], str(log))
    name = log.name
    stem = name.split("_", 1)[0] if "_" in name else name.split(".", 1)[0]
    return check_machine(stem, str(log))


def _abs(p: str | Path) -> str:
    return os.path.abspath(os.fspath(p))


def read_manifest(path: Path, config: str | None, model: str | None) -> list[LogJob]:
    base = path.parent
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            reader.fieldnames = [h.strip() for h in (reader.fieldnames or [])]
            header = list(reader.fieldnames)
            rows = list(reader)
    except (OSError, UnicodeError, csv.Error) as exc:
        raise CmcanError(f"{path}: cannot read the manifest: {exc}", Kind.NO_INPUT) from None
    missing = [c for c in ("machine", "log") if c not in header]
    if missing:
        raise CmcanError(
            f"{path}: manifest lacks column(s) {', '.join(missing)}; expected a header {','.join(MANIFEST_COLUMNS)}",
            Kind.DATA,
        )
    unknown = [c for c in header if c not in MANIFEST_COLUMNS]
    if unknown:
        raise CmcanError(f"{path}: unknown manifest column(s) {', '.join(unknown)}", Kind.DATA)
    jobs = []
    for i, row in enumerate(rows, start=2):
        machine = (row.get("machine") or "").strip()
        log = (row.get("log") or "").strip()
        if not machine or not log:
            raise CmcanError(f"{path}: line {i}: machine and log must not be empty", Kind.DATA)
        check_machine(machine, f"{path}: line {i}")
        cfg = (row.get("config") or "").strip()
        mdl = (row.get("model") or "").strip()
        jobs.append(
            LogJob(
                machine=machine,
                log=_abs(base / log),
                config=_abs(base / cfg) if cfg else config,
                model=_abs(base / mdl) if mdl else model,
                origin=f"{path} line {i}",
            )
        )
    return jobs


def _glob_root(pattern: str) -> Path:
    parts = Path(pattern).parts
    keep = []
    for p in parts:
        if glob.has_magic(p):
            break
        keep.append(p)
    return Path(*keep) if keep else Path(".")


def discover(sources: list[str], config: str | None = None, model: str | None = None) -> list[LogJob]:
    """Jobs for every log the sources name, each log once, in (machine, path) order."""
    config = _abs(config) if config else None
    model = _abs(model) if model else None
    jobs: list[LogJob] = []
    for src in sources:
        p = Path(src)
        if p.is_file() and p.suffix.lower() == ".csv":
            jobs += read_manifest(p, config, model)
        elif p.is_dir():
            found = sorted(f for f in p.rglob("*") if f.is_file() and is_log(f))
            jobs += [LogJob(machine_of(f, p), _abs(f), config, model) for f in found]
        elif glob.has_magic(src):
            root = _glob_root(src)
            found = sorted(Path(f) for f in glob.glob(src, recursive=True) if Path(f).is_file())
            jobs += [LogJob(machine_of(f, root), _abs(f), config, model) for f in found]
        elif p.is_file():
            jobs.append(LogJob(machine_of(p, p.parent), _abs(p), config, model))
        else:
            raise CmcanError(f"{src}: no such file, folder or matching glob", Kind.NO_INPUT)
    seen: set[str] = set()
    unique = []
    for j in sorted(jobs, key=lambda j: (j.machine, j.log)):
        if j.log not in seen:
            seen.add(j.log)
            unique.append(j)
    return unique
