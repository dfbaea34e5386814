"""Loading the signal database (DBC) with strict checking, and finding the one cmcan ships."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

import cantools
from cantools.database.can import Database

from cmcan.errors import CmcanError, Kind


class DbcError(CmcanError, ValueError):
    """A DBC file is missing or does not load; ``str()`` names the file and the cause."""

    kind = Kind.CONFIG


def default_dbc_path() -> Path:
    """The shipped ``dbc/cmcan.dbc``: inside the installed package, or at the top of a checkout."""
    here = Path(__file__).resolve().parent
    for candidate in (here / "_data" / "dbc" / "cmcan.dbc", here.parent / "dbc" / "cmcan.dbc"):
        if candidate.exists():
            return candidate
    raise DbcError("the shipped dbc/cmcan.dbc was not found next to the cmcan package")


def load_dbc(path: str | Path | None = None) -> Database:
    p = Path(path) if path is not None else default_dbc_path()
    return _load(str(p.resolve()) if p.exists() else str(p))


@lru_cache(maxsize=8)
def _load(path: str) -> Database:
    p = Path(path)
    if not p.exists():
        raise DbcError(f"{p}: DBC file not found")
    try:
        db = cantools.database.load_file(str(p), strict=True)
    except Exception as exc:  # cantools raises several parser/validation types
        raise DbcError(f"{p}: not a valid DBC: {exc}") from None
    if not isinstance(db, Database):
        raise DbcError(f"{p}: not a CAN database")
    return db


def raw_range(signal: Any) -> tuple[int, int]:
    """The raw integers a signal's bits hold: two's complement when signed."""
    n = int(signal.length)
    return (-(1 << (n - 1)), (1 << (n - 1)) - 1) if signal.is_signed else (0, (1 << n) - 1)


def physical_range(signal: Any) -> tuple[float, float]:
    """The physical values a (cantools) signal carries: its raw range through scale and offset, within
    its minimum and maximum where the DBC gives them (cmcan's encoder saturates at those). An empty
    range (the DBC's minimum above what the bits hold, say) comes back with lo > hi."""
    r_lo, r_hi = raw_range(signal)
    scale, offset = float(signal.scale), float(signal.offset)
    a, b = r_lo * scale + offset, r_hi * scale + offset
    lo, hi = min(a, b), max(a, b)
    if signal.minimum is not None:
        lo = max(lo, float(signal.minimum))
    if signal.maximum is not None:
        hi = min(hi, float(signal.maximum))
    return lo, hi


def describe_signal(signal: Any) -> str:
    """A signal's coding for people: ``8-bit unsigned, scale 0.01, offset 0, [0|2.55] %``."""
    sign = "signed" if signal.is_signed else "unsigned"
    given = (
        f", range [{signal.minimum:g}|{signal.maximum:g}]"
        if signal.minimum is not None and signal.maximum is not None
        else f", minimum {signal.minimum:g}"
        if signal.minimum is not None
        else f", maximum {signal.maximum:g}"
        if signal.maximum is not None
        else ", no range given"
    )
    return f"{signal.length}-bit {sign}, scale {float(signal.scale):g}, offset {float(signal.offset):g}{given}"


def covers(carried: tuple[float, float], needed: tuple[float, float], resolution: float) -> bool:
    """Whether a signal carrying ``carried`` holds every value of ``needed``; a range short by less
    than one step of the signal's ``resolution`` is a matter of resolution (the value rounds), not of
    range."""
    lo, hi = carried
    tol = abs(resolution) + 1e-9 * max(1.0, abs(needed[0]), abs(needed[1]))
    return lo <= needed[0] + tol and hi >= needed[1] - tol
