"""Errors the CLI reports as one line and a sysexits(3) exit code."""

from __future__ import annotations

from pathlib import Path

EX_USAGE = 64
EX_DATAERR = 65
EX_NOINPUT = 66
EX_UNAVAILABLE = 69
EX_SOFTWARE = 70
EX_OSERR = 71
EX_CANTCREAT = 73
EX_IOERR = 74
EX_TEMPFAIL = 75
EX_CONFIG = 78


class CliError(Exception):
    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def ensure_writable(path: str | Path, force: bool) -> Path:
    """Refuse to overwrite what the user has unless asked to; the parent folder must exist."""
    p = Path(path)
    if p.exists() and not force:
        raise CliError(f"{p}: already exists; pass --force to overwrite it", EX_CANTCREAT)
    if not p.parent.exists():
        raise CliError(f"{p.parent}: folder does not exist", EX_CANTCREAT)
    if p.is_dir():
        raise CliError(f"{p}: is a folder, expected a file name", EX_CANTCREAT)
    return p
