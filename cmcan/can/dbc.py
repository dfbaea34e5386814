"""Loading the signal database (DBC), and finding the one cmcan ships.

A vendor's DBC describes hundreds of messages, and cmcan reads a handful: a problem in a message
cmcan does not read (overlapping signals, a value table for a signal the message lacks) must not
refuse the whole file. A DBC that loads under cantools' strict checks is taken as it is; one that
does not is loaded leniently, each message is then checked with cantools' own strict check
(``Message.refresh(strict=True)``: overlapping signals, signals beyond the message), and value
tables naming no signal are dropped. :func:`message_problems` says what was found, by message: the
configuration check refuses a problem in a message cmcan reads or sends and only warns about the
others.
"""

from __future__ import annotations

import hashlib
import logging
import re
import weakref
from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cmcan.errors import CmcanError, Kind

if TYPE_CHECKING:  # cantools is imported where a DBC is read: it imports python-can, asammdf, pandas
    from cantools.database.can import Database

log = logging.getLogger("cmcan.dbc")


class DbcError(CmcanError, ValueError):
    """A DBC file is missing or does not load; ``str()`` names the file and the cause."""

    kind = Kind.CONFIG


def default_dbc_path() -> Path:
    """The shipped ``dbc/cmcan.dbc``: inside the installed package, or at the top of a checkout."""
    package = Path(__file__).resolve().parents[1]  # cmcan/, beside which a checkout has dbc/
    for candidate in (package / "_data" / "dbc" / "cmcan.dbc", package.parent / "dbc" / "cmcan.dbc"):
        if candidate.exists():
            return candidate
    raise DbcError("the shipped dbc/cmcan.dbc was not found next to the cmcan package")


def load_dbc(path: str | Path | None = None) -> Database:
    return load_dbc_digest(path)[0]


def dbc_name(path: str | Path | None = None) -> str:
    """The name a DBC is loaded (and named in messages) by: resolved when the file exists."""
    p = Path(path) if path is not None else default_dbc_path()
    return str(p.resolve()) if p.exists() else str(p)


def file_sha256(name: str) -> str | None:
    """The SHA-256 of a file's bytes (hex); None when it cannot be read."""
    try:
        with open(name, "rb") as f:
            return hashlib.sha256(f.read()).hexdigest()
    except OSError:
        return None


def load_dbc_digest(path: str | Path | None = None) -> tuple[Database, str | None]:
    """:func:`load_dbc`'s database and the SHA-256 of the bytes it was parsed from (None when the
    file changed while it was parsed). Parsed once per process for each content of the file: an
    edited file is parsed again."""
    name = dbc_name(path)
    for _ in range(3):  # a file rewritten while it was parsed is parsed again
        before = file_sha256(name)
        db = _load(name, before)
        if before is not None and file_sha256(name) == before:
            return db, before
    return db, None


# problems found in a leniently loaded database, by message name (absent: none)
_PROBLEMS: weakref.WeakKeyDictionary[Database, dict[str, str]] = weakref.WeakKeyDictionary()


def message_problems(db: Database) -> Mapping[str, str]:
    """What cantools' strict checks found wrong with each message of a DBC loaded by
    :func:`load_dbc`, by message name (empty for a file that loads strictly); a compiled database
    (:mod:`cmcan.can.dbcmodel`) carries those of the file it was compiled from."""
    own = getattr(db, "problems", None)  # a CompiledDatabase's (cantools' Database has no such field)
    if isinstance(own, Mapping):
        return own
    return _PROBLEMS.get(db, {})


@lru_cache(maxsize=8)
def _load(path: str, sha256: str | None) -> Database:  # sha256: the cache's key (a new content is parsed)
    import cantools
    from cantools.database.can import Database

    p = Path(path)
    if not p.exists():
        raise DbcError(f"{p}: DBC file not found")
    try:
        db = cantools.database.load_file(str(p), strict=True)
    except Exception as strict_exc:  # cantools raises several parser/validation types
        db = _load_lenient(p, strict_exc)
    if not isinstance(db, Database):
        raise DbcError(f"{p}: not a CAN database")
    return db


# a value table statement for one signal (not VAL_TABLE_): VAL_ <frame id> <signal> <value "text">... ;
_VAL = re.compile(r"^[ \t]*VAL_[ \t]+(\d+)[ \t]+(\w+)\b[^;]*;[ \t]*\r?\n?", re.M)
_BO = re.compile(r"^[ \t]*BO_[ \t]+(\d+)[ \t]+(\w+)[ \t]*:", re.M)
_SG = re.compile(r"^[ \t]*SG_[ \t]+(\w+)", re.M)


def _load_lenient(p: Path, strict_exc: Exception) -> Database:
    """A DBC that failed cantools' strict load, loaded without it, with its messages checked one by
    one; DbcError with the strict load's reason when it does not load at all."""
    import cantools
    from cantools.database.can import Database

    if p.suffix.lower() != ".dbc":
        raise DbcError(f"{p}: not a valid DBC: {strict_exc}") from None
    try:
        text = p.read_text(encoding="cp1252")  # cantools' own default for DBC files
        text, dropped = _drop_orphan_value_tables(text)
        db = cantools.database.load_string(text, "dbc", strict=False)
    except Exception as exc:
        raise DbcError(f"{p}: not a valid DBC: {strict_exc if str(exc) == str(strict_exc) else exc}") from None
    if not isinstance(db, Database):
        raise DbcError(f"{p}: not a CAN database")
    problems: dict[str, str] = {}
    for msg in db.messages:
        try:
            msg.refresh(strict=True)
        except Exception as exc:
            problems[msg.name] = str(exc)
        finally:
            msg.refresh(strict=False)
    for name, signals in dropped.items():
        note = f"value tables (VAL_) for signals it does not have: {', '.join(signals)}"
        problems[name] = f"{problems[name]}; {note}" if name in problems else note
    _PROBLEMS[db] = problems
    for name, why in sorted(problems.items()):
        log.info("%s: message %s does not pass cantools' strict check: %s", p, name, why)
    return db


def _drop_orphan_value_tables(text: str) -> tuple[str, dict[str, list[str]]]:
    """The DBC text without the ``VAL_`` statements that name a signal its message does not have (or
    a message the file does not have), which cantools refuses at any strictness; and those dropped,
    by message name (or frame id)."""
    signals: dict[int, set[str]] = {}
    names: dict[int, str] = {}
    bos = list(_BO.finditer(text))
    for i, bo in enumerate(bos):
        end = bos[i + 1].start() if i + 1 < len(bos) else len(text)
        block = text[bo.end() : end]
        # a message's signals are the SG_ lines right after its BO_ line, up to the first other line
        sg = []
        for line in block.splitlines()[1:]:
            m = _SG.match(line)
            if m is None:
                if line.strip():
                    break
                continue
            sg.append(m.group(1))
        fid = int(bo.group(1))
        signals[fid] = set(sg)
        names[fid] = bo.group(2)
    dropped: dict[str, list[str]] = {}

    def keep(m: re.Match[str]) -> str:
        fid, sig = int(m.group(1)), m.group(2)
        if sig in signals.get(fid, ()):
            return m.group(0)
        dropped.setdefault(names.get(fid, f"frame id {fid}"), []).append(sig)
        return ""

    return _VAL.sub(keep, text), dropped


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
