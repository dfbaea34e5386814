"""Loading the signal database (DBC) with strict checking, and finding the one cmcan ships."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

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
