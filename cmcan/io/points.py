"""Operating-point tables: a CSV whose rows are already operating points (cycle means, test-rig
logs, spreadsheets), read into per-role arrays.

Such files name their columns their own way and often lack a sensor for a quantity the machine holds
constant (a pump on a constant-speed electric motor). A :class:`PointSpec` says which column holds
each role, which roles are constants, and which rows to keep (``pump_leak=0``). The reader is shared
by everything that takes operating points (the gap diagnosis; training on real data later).
"""

from __future__ import annotations

import csv
import math
import operator
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cmcan.errors import CmcanError, Kind

_OPS: dict[str, Callable[[float, float], bool]] = {
    "==": operator.eq,
    "!=": operator.ne,
    "<=": operator.le,
    ">=": operator.ge,
    "<": operator.lt,
    ">": operator.gt,
    "=": operator.eq,
}
_CONDITION = re.compile(r"^\s*([^=!<>\s][^=!<>]*?)\s*(==|!=|<=|>=|=|<|>)\s*(.+?)\s*$")


class PointsError(CmcanError, ValueError):
    """An operating-point table or its spec cannot be used; ``str()`` names the file and field.

    ``problem`` says whose fault it is: ``"noinput"`` (the file is missing), ``"data"`` (the file does
    not hold what the spec asks for), ``"spec"`` (the spec itself is malformed: a configuration error,
    or a usage error when the spec came from the command line)."""

    def __init__(self, message: str, problem: str) -> None:
        super().__init__(message, {"noinput": Kind.NO_INPUT, "data": Kind.DATA}.get(problem, Kind.CONFIG))
        self.problem = problem


@dataclass(frozen=True)
class Condition:
    """A row filter: ``column op value`` with op one of = == != < <= > >=."""

    column: str
    op: str
    value: float

    @classmethod
    def parse(cls, text: str, where: str = "--where") -> Condition:
        m = _CONDITION.match(text)
        if not m:
            raise PointsError(f"{where}: {text!r} is not COLUMN=VALUE (or !=, <, <=, >, >=)", "spec")
        col, op, raw = m.groups()
        try:
            value = float(raw)
        except ValueError:
            raise PointsError(f"{where}: {text!r}: {raw!r} is not a number", "spec") from None
        return cls(col, "==" if op == "=" else op, value)

    def holds(self, values: NDArray[np.float64]) -> NDArray[np.bool_]:
        return np.asarray(_OPS[self.op](values, self.value), dtype=bool)

    def __str__(self) -> str:
        return f"{self.column}{'=' if self.op == '==' else self.op}{self.value:g}"


@dataclass(frozen=True)
class PointSpec:
    """Which column holds each role, which roles are constants, which rows to keep."""

    columns: Mapping[str, str] = field(default_factory=dict)
    constants: Mapping[str, float] = field(default_factory=dict)
    where: tuple[Condition, ...] = ()
    source: str = "<points spec>"

    def merged(self, other: PointSpec) -> PointSpec:
        """This spec with ``other``'s entries added (and taking precedence), e.g. command-line options."""
        cols = {k: v for k, v in self.columns.items() if k not in other.constants}
        consts = {k: v for k, v in self.constants.items() if k not in other.columns}
        return PointSpec(
            {**cols, **other.columns}, {**consts, **other.constants}, (*self.where, *other.where), self.source
        )

    @classmethod
    def from_dict(cls, raw: Any, source: str) -> PointSpec:
        """From a mapping ``{columns: {role: column}, constants: {role: value}, where: [text]}``."""
        if raw is None:
            raw = {}
        if not isinstance(raw, dict):
            raise PointsError(f"{source}: expected a mapping with columns, constants, where", "spec")
        unknown = sorted(set(raw) - {"columns", "constants", "where"})
        if unknown:
            raise PointsError(f"{source}: {unknown[0]}: unknown field (known: columns, constants, where)", "spec")
        cols = raw.get("columns") or {}
        consts = raw.get("constants") or {}
        where = raw.get("where") or []
        if not isinstance(cols, dict) or not all(isinstance(v, str) for v in cols.values()):
            raise PointsError(f"{source}: columns: expected a mapping of role to column name", "spec")
        if not isinstance(consts, dict):
            raise PointsError(f"{source}: constants: expected a mapping of role to number", "spec")
        for k, v in consts.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise PointsError(f"{source}: constants.{k}: expected a number, got {v!r}", "spec")
        both = sorted(set(cols) & set(consts))
        if both:
            raise PointsError(f"{source}: {both[0]}: given both as a column and as a constant", "spec")
        if isinstance(where, str):
            where = [where]
        if not isinstance(where, list):
            raise PointsError(f"{source}: where: expected a list of COLUMN=VALUE conditions", "spec")
        conds = tuple(Condition.parse(str(w), f"{source}: where[{i}]") for i, w in enumerate(where))
        return cls(dict(cols), {k: float(v) for k, v in consts.items()}, conds, source)

    @classmethod
    def load(cls, path: str | Path) -> PointSpec:
        from cmcan.schema import SchemaError, load_yaml

        p = Path(path)
        if not p.exists():
            raise PointsError(f"{p}: file not found", "noinput")
        try:
            raw = load_yaml(p)
        except SchemaError as exc:
            raise PointsError(str(exc), "spec") from None
        return cls.from_dict(raw, str(p))


@dataclass(frozen=True)
class Points:
    """Per-role values of the kept rows; constants repeated, so every role is an array."""

    source: str
    values: dict[str, NDArray[np.float64]]
    measured: frozenset[str]  # roles read from a column (the others are constants)
    rows: NDArray[np.int64]  # 1-based data row numbers (the header is row 0) of the kept rows
    total_rows: int
    spec: PointSpec
    # The file's column names and the kept rows' cells as written, for outputs that carry them on.
    header: tuple[str, ...] = ()
    cells: tuple[tuple[str, ...], ...] = ()

    def __len__(self) -> int:
        return len(self.rows)


def read_points(
    path: str | Path, spec: PointSpec, roles: Iterable[str], min_rows: int = 1, missing_as_nan: bool = False
) -> Points:
    """The roles ``roles`` from the CSV ``path`` as ``spec`` maps them; every one must be mapped.
    An empty or non-numeric cell of a role's column is an error, or NaN with ``missing_as_nan`` (for
    readers that judge each row on its own, such as scoring: one bad row must not lose the others)."""
    p = Path(path)
    roles = tuple(roles)
    unmapped = [r for r in roles if r not in spec.columns and r not in spec.constants]
    if unmapped:
        raise PointsError(
            f"{p}: no column or constant for {', '.join(unmapped)} (give columns.ROLE: COLUMN or "
            f"constants.ROLE: VALUE in the points spec {spec.source}, or --column / --constant)",
            "spec",
        )
    if not p.exists():
        raise PointsError(f"{p}: file not found", "noinput")
    try:
        with open(p, encoding="utf-8-sig", newline="") as f:
            sample = f.read(65536)
            f.seek(0)
            delim = _delimiter(sample)
            reader = csv.reader(f, delimiter=delim)
            header = next(reader, None)
            body = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise PointsError(f"{p}: cannot read as CSV: {exc}", "data") from None
    if not header:
        raise PointsError(f"{p}: empty file, expected a header line with column names", "data")
    names = [h.strip() for h in header]
    index = {n: i for i, n in enumerate(names)}
    wanted = {spec.columns[r] for r in roles if r in spec.columns} | {c.column for c in spec.where}
    missing = sorted(c for c in wanted if c not in index)
    if missing:
        fields = [f"columns.{r}" for r in roles if spec.columns.get(r) == missing[0]] or ["where"]
        raise PointsError(
            f"{p}: no column {missing[0]!r} ({fields[0]} in {spec.source}); the file has {', '.join(names)}", "data"
        )
    body = [row for row in body if any(cell.strip() for cell in row)]
    keep = np.ones(len(body), dtype=bool)
    for cond in spec.where:  # filter first: a row left out may hold anything in the other columns
        keep &= cond.holds(_numeric(p, body, index[cond.column], cond.column, keep))
    rows = np.flatnonzero(keep).astype(np.int64) + 1
    kept = [body[i] for i in np.flatnonzero(keep)]
    values: dict[str, NDArray[np.float64]] = {}
    for r in roles:
        if r in spec.columns:
            v = _numeric(p, kept, index[spec.columns[r]], spec.columns[r], None, rows, missing_as_nan)
            bad = np.flatnonzero(~np.isfinite(v))
            if len(bad) and not missing_as_nan:
                raise PointsError(f"{p}: row {rows[bad[0]]}: column {spec.columns[r]!r} ({r}) is empty", "data")
            values[r] = v
        else:
            values[r] = np.full(len(kept), float(spec.constants[r]))
    if len(kept) < min_rows:
        cond = " and ".join(str(c) for c in spec.where) or "no filter"
        raise PointsError(f"{p}: {len(kept)} of {len(body)} rows kept ({cond}); need at least {min_rows}", "data")
    measured = frozenset(r for r in roles if r in spec.columns)
    cells = tuple((*(c.strip() for c in row[: len(names)]), *("",) * (len(names) - len(row))) for row in kept)
    return Points(str(p), values, measured, rows, len(body), spec, tuple(names), cells)


def _delimiter(sample: str) -> str:
    first = sample.splitlines()[0] if sample else ""
    return max((",", ";", "\t"), key=first.count)


def _numeric(
    p: Path,
    body: list[list[str]],
    col: int,
    name: str,
    keep: NDArray[np.bool_] | None = None,
    rows: NDArray[np.int64] | None = None,
    lenient: bool = False,
) -> NDArray[np.float64]:
    """Column ``col`` as numbers (NaN where empty); only where ``keep`` (the rest NaN); errors name the
    file's data row (``rows`` maps positions to it)."""
    out = np.full(len(body), np.nan)
    for k, row in enumerate(body):
        if keep is not None and not keep[k]:
            continue
        cell = row[col].strip() if col < len(row) else ""
        if not cell:
            continue
        try:
            out[k] = float(cell)
        except ValueError:
            if lenient:
                continue
            at = int(rows[k]) if rows is not None else k + 1
            raise PointsError(f"{p}: row {at}: column {name!r}: {cell!r} is not a number", "data") from None
    return out
