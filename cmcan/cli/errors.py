"""The command line's exit codes: one table from an error's kind to its sysexits(3) code."""

from __future__ import annotations

from pathlib import Path

from cmcan.errors import CmcanError, Kind

EX_OK = 0
EX_USAGE = 64
EX_DATAERR = 65
EX_NOINPUT = 66
EX_UNAVAILABLE = 69
EX_SOFTWARE = 70
EX_OSERR = 71
EX_CANTCREAT = 73
EX_IOERR = 74
EX_TEMPFAIL = 75
EX_NOPERM = 77
EX_CONFIG = 78

EXIT_CODES: dict[Kind, int] = {
    Kind.USAGE: EX_USAGE,
    Kind.DATA: EX_DATAERR,
    Kind.NO_INPUT: EX_NOINPUT,
    Kind.UNAVAILABLE: EX_UNAVAILABLE,
    Kind.CANT_CREATE: EX_CANTCREAT,
    Kind.IO_ERROR: EX_IOERR,
    Kind.NO_PERMISSION: EX_NOPERM,
    Kind.TEMPFAIL: EX_TEMPFAIL,
    Kind.CONFIG: EX_CONFIG,
    Kind.SOFTWARE: EX_SOFTWARE,
}


def exit_code(exc: CmcanError) -> int:
    return EXIT_CODES[exc.kind]


def ensure_writable(path: str | Path, force: bool) -> Path:
    """Refuse to overwrite what the user has unless asked to; the parent folder must exist."""
    p = Path(path)
    if p.is_dir():
        raise CmcanError(f"{p}: is a folder, expected a file name", Kind.CANT_CREATE)
    if p.exists() and not force:
        raise CmcanError(f"{p}: already exists; pass --force to overwrite it", Kind.CANT_CREATE)
    if not p.parent.is_dir():
        raise CmcanError(f"{p.parent}: folder does not exist (for {p.name})", Kind.CANT_CREATE)
    return p


def require_extra(extra: str, module: str) -> None:
    """An optional part of cmcan needs a package from an extra: say which, exit 69."""
    import importlib

    try:
        importlib.import_module(module)
    except ImportError:
        raise CmcanError(
            f"this needs the {extra!r} extra: pip install 'cmcan[{extra}]' ({module} is missing)", Kind.UNAVAILABLE
        ) from None
