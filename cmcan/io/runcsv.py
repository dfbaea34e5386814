"""Run CSVs: one column per quantity with its unit in the name, one row per sample.

Read with the CSV vocabulary of :mod:`cmcan.io.points` (separators, missing values, errors naming
the line and column), like operating-point tables."""

from __future__ import annotations

import contextlib
import io
import logging
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cmcan.errors import CmcanError, Kind
from cmcan.io import native
from cmcan.io.points import CsvError, CsvTable, column_index, csv_header, read_csv_table

# Decimals written per column: finer than any sensor resolution, coarse enough to keep files small.
_DECIMALS = {"time_s": 4, "operating_h": 7, "true_failed": 0, "true_misposition_pct": 4}
_DEFAULT_DECIMALS = 4
log = logging.getLogger("cmcan.io")


class RunCsvError(CmcanError, ValueError):
    """A run CSV cannot be read; ``str()`` names the file and what is wrong."""

    kind = Kind.DATA


def write_run_csv(path: str | Path, columns: dict[str, NDArray[np.float64]]) -> None:
    """Write atomically (temporary file, then rename): an earlier file is replaced only when complete."""
    p = Path(path)
    names = list(columns)
    data = np.column_stack([np.asarray(columns[k], dtype=float) for k in names]) if names else np.empty((0, 0))
    decimals = [_DECIMALS.get(k, _DEFAULT_DECIMALS) for k in names]
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "w", encoding="ascii", newline="\n") as f:
        f.write(",".join(names) + "\n")
        for a in range(0, len(data), _WRITE_ROWS):
            f.write(_rows(data[a : a + _WRITE_ROWS], decimals))
    tmp.replace(p)


_WRITE_ROWS = 200_000  # rows formatted at a time: a bounded buffer, whatever the run's length


def _rows(data: NDArray[np.float64], decimals: list[int]) -> str:
    """The rows as ``np.savetxt`` with ``%.<d>f`` writes them: by the C formatter where it is built
    and every value is finite (NaN and infinities are numpy's to spell), else by numpy."""
    if len(data) and native.LIB is not None and np.isfinite(data).all():
        cols = [native.TextColumn(native.FIXED, data[:, j], b"," if j else b"", d) for j, d in enumerate(decimals)]
        got = native.format_rows(len(data), cols, b"\n")
        if got is not None:
            return got.decode("ascii")
    buf = io.StringIO()
    np.savetxt(buf, data, fmt=[f"%.{d}f" for d in decimals], delimiter=",")
    return buf.getvalue()


class RunColumns(dict[str, NDArray[np.float64]]):
    """A run CSV's numeric columns by name; ``skipped_lines`` are the lines (the header is line 1) left
    out because a column cmcan reads had no value there; ``lines`` the line of each row kept."""

    skipped_lines: tuple[int, ...] = ()
    lines: Sequence[int] = ()


def read_run_csv(path: str | Path, required: Iterable[str] = ()) -> RunColumns:
    """The columns of the run CSV ``path`` (the CSV vocabulary of :mod:`cmcan.io.points`).

    Each ``required`` column must be there once and hold numbers; a row with a missing value in one of
    them is left out (a sample lost: the windows downstream take irregular samples). Any other column
    is returned when it holds only numbers and missing values (NaN), and ignored otherwise (an
    operator's name, a note), as is a column whose name appears twice."""
    p = Path(path)
    required = tuple(dict.fromkeys(required))
    try:
        names, sep = csv_header(p)
        missing = [k for k in required if k not in names]
        if missing:
            raise RunCsvError(f"{p}: missing column(s) {', '.join(missing)}; the file has {', '.join(names)}")
        for k in required:
            column_index(p, names, k)
        single = {k: i for i, k in enumerate(names) if k and names.count(k) == 1}
        data = _numeric_fast(p, sep, len(names))
        if data is not None and len(data) == _data_lines(p):  # no blank line skipped: lines 2, 3, ...
            out = RunColumns({k: data[:, i] for k, i in single.items()})
            out.lines = range(2, len(data) + 2)
            return out
        return _read_slow(read_csv_table(p), single, required)
    except CsvError as exc:
        raise RunCsvError(str(exc), exc.kind) from None


def _data_lines(p: Path) -> int:
    """The lines after the header, blank ones included (numpy skips those: the slow path then numbers
    the rows by their lines)."""
    text = p.read_bytes()
    return text.count(b"\n") + (0 if text.endswith(b"\n") or not text else 1) - 1


def _numeric_fast(p: Path, sep: str, width: int) -> NDArray[np.float64] | None:
    """The whole file parsed by numpy when every cell is a finite number and every row full, else None
    (the slow path then finds what is missing or wrong, and where)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": a header-only file
            data = np.loadtxt(p, delimiter=sep, skiprows=1, ndmin=2, comments=None, encoding="utf-8-sig")
    except (ValueError, UnicodeDecodeError):
        return None
    if data.size == 0:
        return np.empty((0, width))
    if data.shape[1] != width or not np.isfinite(data).all():
        return None
    return data


def _read_slow(table: CsvTable, single: dict[str, int], required: tuple[str, ...]) -> RunColumns:
    cols: dict[str, NDArray[np.float64]] = {}
    for k, i in single.items():
        if k in required:
            cols[k] = table.numbers(i)
        else:
            with contextlib.suppress(CsvError):  # a column cmcan does not need may hold text
                cols[k] = table.numbers(i)
    complete = np.ones(len(table.rows), dtype=bool)
    for k in required:
        complete &= ~np.isnan(cols[k])
    if len(table.rows) and not complete.any():
        worst = max(required, key=lambda k: int(np.isnan(cols[k]).sum()))
        raise RunCsvError(
            f"{table.path}: no row has a value in every column cmcan reads ({', '.join(required)}); "
            f"{worst!r} is missing in {int(np.isnan(cols[worst]).sum())} of {len(table.rows)} rows"
        )
    out = RunColumns({k: v[complete] for k, v in cols.items()})
    out.skipped_lines = tuple(table.lines[i] for i in np.flatnonzero(~complete))
    out.lines = tuple(table.lines[i] for i in np.flatnonzero(complete))
    if out.skipped_lines:  # said, not silent: those samples are lost to every command reading the file
        shown = ", ".join(map(str, out.skipped_lines[:5])) + (", ..." if len(out.skipped_lines) > 5 else "")
        log.warning(
            "%s: %d of %d rows left out: a value cmcan reads is missing (lines %s)",
            table.path,
            len(out.skipped_lines),
            len(table.rows),
            shown,
        )
    return out
