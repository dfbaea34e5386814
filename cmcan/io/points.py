"""Operating-point tables: a CSV whose rows are already operating points (cycle means, test-rig
logs, spreadsheets), read into per-role arrays; and the CSV vocabulary it shares with run CSVs.

Such files name their columns their own way and often lack a sensor for a quantity the machine holds
constant (a pump on a constant-speed electric motor). A :class:`PointSpec` says which column holds
each role, which roles are constants, and which rows to keep (``pump_leak=0``). The reader is shared
by everything that takes operating points (training, scoring, the gap diagnosis).

What both CSV readers (this one and :mod:`cmcan.io.runcsv`) accept, defined once below: UTF-8 with or
without a byte-order mark, LF or CRLF, separator ``,``, ``;`` or tab (whichever the header line holds
most of), blank lines skipped, columns in any order, extra columns ignored. A cell is a number with
a ``.`` decimal point, or a missing value: blank or one of :data:`MISSING_CELLS` (any case). Anything
else in a column cmcan reads is an error naming the file, the line (the header is line 1, as an
editor or a spreadsheet numbers it), the column and the cell; a decimal comma gets a hint. A row with
fewer or more cells than the header has columns is an error; so is a column cmcan reads whose name
appears twice in the header (a duplicated name cmcan does not read is ignored).
"""

from __future__ import annotations

import csv
import math
import operator
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
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
        """Where the condition holds; a missing value (NaN) meets no condition, ``!=`` included."""
        values = np.asarray(values, dtype=np.float64)
        return np.asarray(_OPS[self.op](values, self.value), dtype=bool) & ~np.isnan(values)

    def __str__(self) -> str:
        return f"{self.column}{'=' if self.op == '==' else self.op}{self.value:g}"


@dataclass(frozen=True)
class PointSpec:
    """Which column holds each role, which roles are constants, which rows to keep."""

    columns: Mapping[str, str] = field(default_factory=dict)
    constants: Mapping[str, float] = field(default_factory=dict)
    where: tuple[Condition, ...] = ()
    source: str = "<points spec>"
    # where a role's column or constant, or a where-condition's column, was given when not in ``source``
    origin: Mapping[str, str] = field(default_factory=dict)

    def source_of(self, key: str) -> str:
        """Who gave the role (or the where-condition's column) ``key``: a file, or the command line."""
        return self.origin.get(key, self.source)

    def merged(self, other: PointSpec) -> PointSpec:
        """This spec with ``other``'s entries added (and taking precedence), e.g. command-line options."""
        cols = {k: v for k, v in self.columns.items() if k not in other.constants}
        consts = {k: v for k, v in self.constants.items() if k not in other.columns}
        origin = {k: self.source_of(k) for k in (*cols, *consts, *(c.column for c in self.where))}
        origin.update({k: other.source_of(k) for k in (*other.columns, *other.constants)})
        origin.update({c.column: other.source_of(c.column) for c in other.where})
        return PointSpec(
            {**cols, **other.columns},
            {**consts, **other.constants},
            (*self.where, *other.where),
            self.source,
            {k: v for k, v in origin.items() if v != self.source},
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
    A missing value (:data:`MISSING_CELLS`) in a role's column is an error, or NaN with
    ``missing_as_nan`` (for readers that judge each row on its own, such as scoring: one bad row must
    not lose the others). A cell that is neither a number nor a missing value is always an error."""
    p = Path(path)
    roles = tuple(roles)
    unmapped = [r for r in roles if r not in spec.columns and r not in spec.constants]
    if unmapped:
        raise PointsError(
            f"{p}: no column or constant for {', '.join(unmapped)} (give columns.ROLE: COLUMN or "
            f"constants.ROLE: VALUE in the points spec {spec.source}, or --column / --constant)",
            "spec",
        )
    try:
        table = read_csv_table(p)
        names = table.names
        wanted = {spec.columns[r] for r in roles if r in spec.columns} | {c.column for c in spec.where}
        missing = sorted(c for c in wanted if c not in names)
        if missing:
            given = [r for r in roles if spec.columns.get(r) == missing[0]]
            what, by = (f"columns.{given[0]}", given[0]) if given else ("where", missing[0])
            alike = [n for n in names if n.strip().lower() == missing[0].strip().lower()]
            hint = f" (did you mean {alike[0]!r}? names are case-sensitive)" if alike else ""
            raise PointsError(
                f"{p}: no column {missing[0]!r} ({what} in {spec.source_of(by)}){hint}; "
                f"the file has {', '.join(names)}",
                "data",
            )
        index = {c: column_index(p, names, c) for c in sorted(wanted)}
        keep = np.ones(len(table.rows), dtype=bool)
        for cond in spec.where:  # filter first: a row left out may hold anything in the other columns
            keep &= cond.holds(table.numbers(index[cond.column], keep))
        kept = np.flatnonzero(keep)
        values: dict[str, NDArray[np.float64]] = {}
        for r in roles:
            if r in spec.columns:
                col = index[spec.columns[r]]
                v = table.numbers(col, keep)[kept]
                bad = np.flatnonzero(np.isnan(v))
                if len(bad) and not missing_as_nan:
                    k = int(kept[bad[0]])
                    cell = table.rows[k][col].strip()
                    what = f"holds no value ({cell!r})" if cell else "is empty"
                    raise PointsError(f"{p}: line {table.lines[k]}: column {spec.columns[r]!r} ({r}) {what}", "data")
                values[r] = v
            else:
                values[r] = np.full(len(kept), float(spec.constants[r]))
    except CsvError as exc:
        raise PointsError(str(exc), "noinput" if exc.kind is Kind.NO_INPUT else "data") from None
    if len(kept) < min_rows:
        cond = " and ".join(str(c) for c in spec.where) or "no filter"
        raise PointsError(f"{p}: {len(kept)} of {len(table.rows)} rows kept ({cond}); need at least {min_rows}", "data")
    measured = frozenset(r for r in roles if r in spec.columns)
    cells = tuple(tuple(c.strip() for c in table.rows[i]) for i in kept)
    return Points(str(p), values, measured, kept.astype(np.int64) + 1, len(table.rows), spec, names, cells)


# -- CSV files: one vocabulary for operating-point tables and run CSVs -----------------------------

SEPARATORS = (",", ";", "\t")
# Spellings of a missing value (compared in lower case): blank, and what spreadsheets, pandas and
# loggers write for one. "-" and "?" are left out: too often a placeholder for something else.
MISSING_CELLS = frozenset({"", "nan", "na", "n/a", "#n/a", "null", "none"})
# A number as numpy's loadtxt (the run CSV's fast path) reads one: ASCII digits, '.' decimals.
_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_DECIMAL_COMMA = re.compile(r"[+-]?[0-9]*,[0-9]+(?:[eE][+-]?[0-9]+)?")


class CsvError(CmcanError, ValueError):
    """A CSV file cannot be read as cmcan reads CSV files; ``str()`` names the file, line and column."""

    kind = Kind.DATA


def cell_value(cell: str) -> float | None:
    """The number a cell holds, None for a missing value; ValueError (saying why) for anything else."""
    text = cell.strip()
    if text.lower() in MISSING_CELLS:
        return None
    if not _NUMBER.fullmatch(text):
        hint = " (decimal comma? cmcan reads '.' decimals)" if _DECIMAL_COMMA.fullmatch(text) else ""
        raise ValueError(f"is not a number{hint}")
    value = float(text)
    if not math.isfinite(value):  # only an exponent beyond float range gets here
        raise ValueError("is not a finite number")
    return value


@dataclass(frozen=True)
class CsvTable:
    """A CSV's header and its non-blank data rows, each with a cell for every column."""

    path: Path
    names: tuple[str, ...]
    rows: list[list[str]]
    lines: list[int]  # each row's line in the file (the header is line 1)

    def numbers(self, col: int, where: NDArray[np.bool_] | None = None) -> NDArray[np.float64]:
        """Column ``col`` as numbers, NaN for a missing value (and for the rows ``where`` leaves out)."""
        out = np.full(len(self.rows), np.nan)
        for k, row in enumerate(self.rows):
            if where is not None and not where[k]:
                continue
            try:
                value = cell_value(row[col])
            except ValueError as exc:
                raise CsvError(
                    f"{self.path}: line {self.lines[k]}: column {self.names[col]!r}: {row[col].strip()!r} {exc}"
                ) from None
            if value is not None:
                out[k] = value
        return out


def column_index(path: Path, names: Sequence[str], name: str) -> int:
    """The position of the column ``name`` (which must be there); a name given twice is an error."""
    at = [i for i, n in enumerate(names) if n == name]
    if len(at) > 1:
        times = "twice" if len(at) == 2 else f"{len(at)} times"
        where = ", ".join(str(i + 1) for i in at[:-1]) + f" and {at[-1] + 1}"
        raise CsvError(f"{path}: column {name!r} appears {times} (columns {where}); rename all but one")
    return at[0]


def csv_header(path: str | Path) -> tuple[tuple[str, ...], str]:
    """The column names (stripped) and the separator of the CSV ``path``."""
    names, sep, _ = _read_csv(Path(path), header_only=True)
    return names, sep


def read_csv_table(path: str | Path) -> CsvTable:
    """The whole CSV ``path``: header, rows (blank lines skipped) and each row's line."""
    p = Path(path)
    names, _, (rows, lines) = _read_csv(p, header_only=False)
    return CsvTable(p, names, rows, lines)


def _read_csv(p: Path, header_only: bool) -> tuple[tuple[str, ...], str, tuple[list[list[str]], list[int]]]:
    if not p.exists():
        raise CsvError(f"{p}: file not found", Kind.NO_INPUT)
    if p.is_dir():
        raise CsvError(f"{p}: is a folder, expected a CSV file", Kind.NO_INPUT)
    rows: list[list[str]] = []
    lines: list[int] = []
    try:
        with open(p, encoding="utf-8-sig", newline="") as f:
            first = f.readline()
            sep = max(SEPARATORS, key=first.count)
            f.seek(0)
            reader = csv.reader(f, delimiter=sep)
            header = next(reader, None)
            if not header or not any(h.strip() for h in header):
                raise CsvError(f"{p}: empty file, expected a header line with column names")
            names = tuple(h.strip() for h in header)
            if not header_only:
                for row in reader:
                    if not any(cell.strip() for cell in row):
                        continue
                    if len(row) != len(names):
                        raise CsvError(
                            f"{p}: line {reader.line_num}: {len(row)} cells, but the header (line 1) has "
                            f"{len(names)} columns ({sep!r} separated)"
                        )
                    rows.append(row)
                    lines.append(reader.line_num)
    except UnicodeDecodeError:
        raise CsvError(f"{p}: not a text CSV file (not UTF-8)") from None
    except csv.Error as exc:
        raise CsvError(f"{p}: cannot read as CSV: {exc}") from None
    except OSError as exc:
        raise CsvError(f"{p}: cannot read: {exc.strerror or exc}", Kind.NO_INPUT) from None
    return names, sep, (rows, lines)
