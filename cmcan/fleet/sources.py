"""Which logs a fleet run covers, and which machine each belongs to; sources stay where the user said.

A source is a manifest CSV, a folder, a glob pattern or a single log:

- manifest (``*.csv`` with a header ``machine,log[,config][,model]``): one row per log; relative
  paths are relative to the manifest's folder; an empty config or model falls back to the run's
  ``--config`` / ``--model``. Every path of a manifest must lie under its **root** (the manifest's
  folder, or ``--manifest-root``), after resolving ``..`` and symbolic links: a row naming
  ``/etc/shadow`` or ``../../secret.key`` is refused, not read;
- folder: read through its ``manifest.csv`` when it has one (the simulated fleet's layout); else
  every log below it (``.log``, ``.log.gz``, ``.asc``, ``.blf``, ``.trc``, ``.mf4``, ``.db``; CSV logs
  only through a manifest). The machine is the first folder below the given one
  (``fleet/exc-017/2026/01/a.log`` -> ``exc-017``); a log directly in the given folder belongs to the
  machine named by its file name up to the first ``_`` (``exc-017_20260102.log`` -> ``exc-017``);
- glob (``'fleet/*/2026-01-*.log'``, ``**`` allowed): the matches, with the same rule below the
  pattern's folder part (the part before the first wildcard);
- a single log: the machine from its file name as above.

Inside a folder or a glob's folder, a symbolic link to a file or folder outside it is refused (not
opened) unless ``follow_symlinks``; anything that is not a regular file (a FIFO, a device) is refused
wherever it is named, since reading it could block or never end. Refused entries are listed with the
reason (:class:`Refused`) and the rest of the run goes on.

A log named by two sources is taken once: a manifest row before a folder, glob or single name (it
says which configuration the log needs), else the first source given; when the two differ in
machine, configuration or model, a note names both. A folder, glob or log that a ``manifest.csv``
of a folder above it names with its own configuration is not replayed with another unless
``--config`` says so: the run stops and says which manifest to give instead.
"""

from __future__ import annotations

import csv
import glob
import os
import stat
from dataclasses import dataclass, field, replace
from pathlib import Path

from cmcan.errors import CmcanError, Kind
from cmcan.fleet.dataset import check_machine
from cmcan.fleet.task import LogJob

LOG_SUFFIXES = (".log", ".log.gz", ".asc", ".asc.gz", ".blf", ".trc", ".trc.gz", ".mf4", ".db")
MANIFEST_COLUMNS = ("machine", "log", "config", "model")
FOLDER_MANIFEST = "manifest.csv"
MANIFEST_SEARCH_LEVELS = 3  # folders above a source searched for a manifest that names its logs


@dataclass(frozen=True)
class Refused:
    """A source entry that is not read: where, whose (when known) and why."""

    path: str
    reason: str
    machine: str | None = None
    origin: str = ""

    def line(self) -> str:
        return f"refused {self.path}{f' ({self.origin})' if self.origin else ''}: {self.reason}"


@dataclass
class Sources:
    jobs: list[LogJob]
    refused: list[Refused] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # what the user should know (a manifest used, a conflict)


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


def _under(path: str, root: str) -> bool:
    return path == root or path.startswith(root.rstrip(os.sep) + os.sep)


def _file_kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISDIR, "a folder"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def not_regular(path: str | Path) -> str | None:
    """Why ``path`` (after links) is no regular file to read, or None if it is one (or is missing:
    the task says that with the file's name)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return None if stat.S_ISREG(st.st_mode) else f"{_file_kind(st.st_mode)}, not a regular file: not read"


def _outside(path: str, root_real: str, root_shown: str | Path, follow: bool) -> str | None:
    """Why a file found below a folder is refused for lying outside it (None: it does not)."""
    if follow:
        return None
    real = os.path.realpath(path)
    if _under(real, root_real):
        return None
    return f"a symbolic link to outside {root_shown}: not read (--follow-symlinks reads it)"


# -- manifests ------------------------------------------------------------------------------------------


def _read_rows(path: Path) -> list[dict[str, str]]:
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
    return rows


def _in_root(value: str, base: Path, root: Path, follow: bool) -> tuple[str | None, str | None]:
    """A manifest's path value resolved against its folder: (absolute path, None) if it stays
    under the root, else (None, why)."""
    p = os.path.normpath(os.path.join(os.path.abspath(base), value))
    root_abs = os.path.abspath(root)
    if not _under(p, root_abs):
        return None, f"{value!r} is outside the manifest's root {root} (--manifest-root widens it)"
    if not follow:
        real = os.path.realpath(p)
        if not _under(real, os.path.realpath(root_abs)):
            return (
                None,
                f"{value!r} is a symbolic link to outside the manifest's root {root} (--follow-symlinks reads it)",
            )
    return p, None


def read_manifest(
    path: Path,
    config: str | None,
    model: str | None,
    root: Path | None = None,
    follow_symlinks: bool = False,
    refused: list[Refused] | None = None,
) -> list[LogJob]:
    """The manifest's jobs; rows whose paths leave the root (or name something that is not a
    regular file) go to ``refused`` (when not given: the first one raises)."""
    base = path.parent
    root = Path(root) if root is not None else base
    jobs = []
    for i, row in enumerate(_read_rows(path), start=2):
        machine = (row.get("machine") or "").strip()
        log = (row.get("log") or "").strip()
        where = f"{path} line {i}"
        if not machine or not log:
            raise CmcanError(f"{path}: line {i}: machine and log must not be empty", Kind.DATA)
        check_machine(machine, f"{path}: line {i}")
        resolved: dict[str, str | None] = {}
        why = None
        for col, value, default in (
            ("log", log, None),
            ("config", row.get("config"), config),
            ("model", row.get("model"), model),
        ):
            value = (value or "").strip()
            if not value:
                resolved[col] = default
                continue
            p, problem = _in_root(value, base, root, follow_symlinks)
            if problem is None and p is not None:
                kind = not_regular(p)
                problem = f"{col} {value!r} is {kind}" if kind else None
            if problem is not None:
                why = problem if col == "log" else f"its {col}: {problem}"
                break
            resolved[col] = p
        if why is not None:
            r = Refused(_abs(base / log), why, machine, where)
            if refused is None:
                raise CmcanError(f"{where}: {why}", Kind.NO_PERMISSION)
            refused.append(r)
            continue
        jobs.append(LogJob(machine, str(resolved["log"]), resolved["config"], resolved["model"], origin=where))
    return jobs


def manifest_logs(path: Path) -> set[str]:
    """The logs a manifest names (absolute paths, not checked), for telling a folder's logs apart."""
    try:
        rows = _read_rows(path)
    except CmcanError:
        return set()
    return {os.path.normpath(os.path.join(os.path.abspath(path.parent), (r.get("log") or "").strip())) for r in rows}


# -- folders and globs ----------------------------------------------------------------------------------


def _walk(top: Path, follow: bool, refused: list[Refused]) -> list[Path]:
    """Log files below ``top``: symbolic links to outside it refused unless ``follow``."""
    top_real = os.path.realpath(top)
    seen_dirs: set[str] = set()
    found = []
    for dirpath, dirnames, filenames in os.walk(top, followlinks=follow):
        real_dir = os.path.realpath(dirpath)
        if real_dir in seen_dirs:  # a link loop when following links
            dirnames[:] = []
            continue
        seen_dirs.add(real_dir)
        for d in sorted(dirnames):
            full = os.path.join(dirpath, d)
            if not follow and os.path.islink(full) and not _under(os.path.realpath(full), top_real):
                refused.append(
                    Refused(
                        full, f"a symbolic link to a folder outside {top}: not followed (--follow-symlinks follows it)"
                    )
                )
        dirnames.sort()
        for name in sorted(filenames):
            full = Path(dirpath) / name
            if not is_log(full):
                continue
            why = _outside(str(full), top_real, top, follow) or not_regular(full)
            if why is None and not full.exists():
                why = "a symbolic link to nothing: not read"
            if why is not None:
                refused.append(Refused(str(full), why, _machine_or_none(full, top)))
                continue
            found.append(full)
    return found


def _machine_or_none(path: Path, root: Path) -> str | None:
    try:
        return machine_of(path, root)
    except CmcanError:
        return None


def _glob_root(pattern: str) -> Path:
    parts = Path(pattern).parts
    keep = []
    for p in parts:
        if glob.has_magic(p):
            break
        keep.append(p)
    return Path(*keep) if keep else Path(".")


def _describe(j: LogJob) -> str:
    cfg = j.config or "the shipped configuration"
    mdl = j.model or "the configuration's model"
    return f"{j.origin or 'a source'} (machine {j.machine}, configuration {cfg}, model {mdl})"


# -- all sources ----------------------------------------------------------------------------------------


def find_logs(
    sources: list[str],
    config: str | None = None,
    model: str | None = None,
    follow_symlinks: bool = False,
    manifest_root: str | None = None,
) -> Sources:
    """Jobs for every log the sources name, each log once, in (machine, path) order, with what was
    refused and what the user should be told."""
    config = _abs(config) if config else None
    model = _abs(model) if model else None
    root = Path(_abs(manifest_root)) if manifest_root else None
    out = Sources([])
    jobs: list[tuple[int, int, LogJob]] = []  # (priority: 0 manifest, 1 other; source order; job)

    def manifest(p: Path, src_root: Path | None) -> None:
        for j in read_manifest(p, config, model, root or src_root, follow_symlinks, out.refused):
            jobs.append((0, len(jobs), j))

    for src in sources:
        p = Path(src)
        if p.is_file() and p.suffix.lower() == ".csv":
            manifest(p, None)
        elif p.is_dir():
            own = p / FOLDER_MANIFEST
            if own.is_file():
                out.notes.append(
                    f"{p}: read through its {FOLDER_MANIFEST} (machine, configuration and model of each log)"
                )
                manifest(own, None)
                named = manifest_logs(own)
                extra = [f for f in _walk(p, follow_symlinks, []) if os.path.normpath(_abs(f)) not in named]
                if extra:
                    out.notes.append(
                        f"{p}: {len(extra)} log(s) below it are not in its {FOLDER_MANIFEST} and are left out"
                    )
                continue
            for f in _walk(p, follow_symlinks, out.refused):
                jobs.append((1, len(jobs), LogJob(machine_of(f, p), _abs(f), config, model, origin=f"folder {p}")))
        elif glob.has_magic(src):
            groot = _glob_root(src)
            groot_real = os.path.realpath(groot)
            for f in sorted(Path(m) for m in glob.glob(src, recursive=True)):
                if f.is_dir():
                    continue
                why = _outside(str(f), groot_real, groot, follow_symlinks) or not_regular(f)
                if why is not None:
                    out.refused.append(Refused(str(f), why, _machine_or_none(f, groot), f"glob {src}"))
                    continue
                if f.is_file():
                    jobs.append(
                        (1, len(jobs), LogJob(machine_of(f, groot), _abs(f), config, model, origin=f"glob {src}"))
                    )
        elif os.path.lexists(p):
            why = not_regular(p) or ("a symbolic link to nothing" if not p.exists() else None)
            if why is not None:
                out.refused.append(Refused(str(p), why, _machine_or_none(p, p.parent)))
            else:
                jobs.append((1, len(jobs), LogJob(machine_of(p, p.parent), _abs(p), config, model, origin=str(p))))
        else:
            raise CmcanError(f"{src}: no such file, folder or matching glob", Kind.NO_INPUT)

    chosen: dict[str, tuple[int, LogJob]] = {}
    for prio, _order, j in sorted(jobs, key=lambda x: (x[0], x[1])):
        key = os.path.realpath(j.log)
        first = chosen.get(key)
        if first is None:
            chosen[key] = (prio, j)
        elif (first[1].machine, first[1].config, first[1].model) != (j.machine, j.config, j.model):
            out.notes.append(
                f"{j.log}: named by {_describe(first[1])} and by {_describe(j)}; replayed as the first "
                "(a manifest row before a folder or glob, else the first source given)"
            )
    if config is None:
        _refuse_when_a_manifest_names_them([j for prio, j in chosen.values() if prio == 1])
    out.jobs = sorted((j for _p, j in chosen.values()), key=lambda j: (j.machine, j.log))
    return out


def _refuse_when_a_manifest_names_them(jobs: list[LogJob]) -> None:
    """Logs found in folders, globs or by name that a ``manifest.csv`` of a folder above them names
    (with their own configuration): replaying them with the shipped one gives results that mean
    nothing, so the run stops and says what to give instead."""
    checked: dict[Path, set[str]] = {}
    hits: dict[Path, int] = {}
    for j in jobs:
        d = Path(j.log).parent
        for _ in range(MANIFEST_SEARCH_LEVELS + 1):
            m = d / FOLDER_MANIFEST
            if m not in checked:
                checked[m] = manifest_logs(m) if m.is_file() else set()
            if os.path.normpath(j.log) in checked[m]:
                hits[m] = hits.get(m, 0) + 1
                break
            if d.parent == d:
                break
            d = d.parent
    if hits:
        m, n = max(hits.items(), key=lambda kv: kv[1])
        raise CmcanError(
            f"{m} names {n} of these logs with their own configuration and model; replay {m} (or its folder "
            f"{m.parent}) instead, or give --config to replay them all with one configuration",
            Kind.USAGE,
        )


def discover(
    sources: list[str],
    config: str | None = None,
    model: str | None = None,
    follow_symlinks: bool = False,
    manifest_root: str | None = None,
) -> list[LogJob]:
    """The jobs of :func:`find_logs`; the first refused entry raises (no permission)."""
    found = find_logs(sources, config, model, follow_symlinks, manifest_root)
    if found.refused:
        r = found.refused[0]
        raise CmcanError(r.line(), Kind.NO_PERMISSION)
    return [replace(j) for j in found.jobs]
