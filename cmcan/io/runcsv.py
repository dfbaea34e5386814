"""Run CSVs: one column per quantity with its unit in the name, one row per sample."""

from __future__ import annotations

import io
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cmcan.errors import CmcanError, Kind

# Decimals written per column: finer than any sensor resolution, coarse enough to keep files small.
_DECIMALS = {"time_s": 4, "operating_h": 7, "true_failed": 0, "true_misposition_pct": 4}
_DEFAULT_DECIMALS = 4


class RunCsvError(CmcanError, ValueError):
    """A run CSV cannot be read; ``str()`` names the file and what is wrong."""

    kind = Kind.DATA


def write_run_csv(path: str | Path, columns: dict[str, NDArray[np.float64]]) -> None:
    """Write atomically (temporary file, then rename): an earlier file is replaced only when complete."""
    p = Path(path)
    names = list(columns)
    data = np.column_stack([np.asarray(columns[k], dtype=float) for k in names]) if names else np.empty((0, 0))
    fmt = [f"%.{_DECIMALS.get(k, _DEFAULT_DECIMALS)}f" for k in names]
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "w", encoding="ascii", newline="\n") as f:
        f.write(",".join(names) + "\n")
        buf = io.StringIO()
        np.savetxt(buf, data, fmt=fmt, delimiter=",")
        f.write(buf.getvalue())
    tmp.replace(p)


def read_run_csv(path: str | Path, required: Iterable[str] = ()) -> dict[str, NDArray[np.float64]]:
    p = Path(path)
    if not p.exists():
        raise RunCsvError(f"{p}: file not found", Kind.NO_INPUT)
    try:
        with open(p, encoding="utf-8") as f:
            header = f.readline().strip()
    except UnicodeDecodeError:
        raise RunCsvError(f"{p}: not a text CSV file (not UTF-8)") from None
    except IsADirectoryError:
        raise RunCsvError(f"{p}: is a folder, expected a CSV file", Kind.NO_INPUT) from None
    if not header:
        raise RunCsvError(f"{p}: empty file, expected a header line with column names")
    names = [h.strip() for h in header.split(",")]
    missing = [k for k in required if k not in names]
    if missing:
        raise RunCsvError(f"{p}: missing column(s) {', '.join(missing)}; the file has {', '.join(names)}")
    try:
        data = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
    except (ValueError, UnicodeDecodeError) as exc:
        raise RunCsvError(f"{p}: not numeric CSV below the header: {exc}") from None
    if data.size == 0:
        return {k: np.empty(0) for k in names}
    if data.shape[1] != len(names):
        raise RunCsvError(f"{p}: rows have {data.shape[1]} values, the header names {len(names)} columns")
    return {k: data[:, i] for i, k in enumerate(names)}
