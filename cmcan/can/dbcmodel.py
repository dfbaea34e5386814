"""What cmcan reads of a DBC, as plain objects that need no cantools: a compiled database.

cantools parses a DBC in some 0.1 s and importing it takes 0.1-0.2 s more (it imports python-can):
most of a short command's start. The monitor, the replay, the check and the simulator read a
handful of facts per message (identifier and format, length, cycle time, multiplexing) and per
signal (bit position, byte order, sign, scale and offset, range, unit, multiplexing), and
:mod:`cmcan.can.codec` compiles its bit layouts from those. :class:`CompiledDatabase` holds exactly
those, under cantools' own attribute names, so that the code reading a cantools ``Database`` reads
this one unchanged; :mod:`cmcan.can.dbccache` keeps it on disk keyed by the DBC's bytes.

What only a full cantools database does (decoding a frame into named values with value tables,
``decode_message``) is handed to cantools itself, loaded on first use from the same file: tests and
the demo's analysis use it, never a running monitor.

:func:`to_doc` and :func:`from_doc` turn a compiled database into JSON-ready data and back;
:func:`from_doc` checks every field's type and range and raises :class:`BadDoc` on anything else,
so a damaged or hostile cache file is refused, never half-read.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # hints only: importing cantools pulls in python-can (issue 42)
    from cantools.database.can import Database, Message

# Bounds a well-formed compiled database stays within (DBC's own, with room): a document beyond
# them is damaged or hostile, not a DBC.
MAX_MESSAGES = 1 << 16
MAX_SIGNALS = 1 << 12  # per message
MAX_NAME_CHARS = 1 << 10
MAX_TEXT_CHARS = 1 << 16  # a problem's description, a unit
MAX_FRAME_BYTES = 64  # CAN FD
MAX_SIGNAL_BITS = 64
MAX_FRAME_ID = (1 << 29) - 1
BYTE_ORDERS = ("little_endian", "big_endian")


class BadDoc(ValueError):
    """A compiled-database document that is not one: ``str()`` says which field and why."""


class CompiledSignal:
    """A DBC signal as cmcan reads it (cantools' attribute names and value types)."""

    __slots__ = (
        "byte_order",
        "is_float",
        "is_multiplexer",
        "is_signed",
        "length",
        "maximum",
        "minimum",
        "multiplexer_ids",
        "multiplexer_signal",
        "name",
        "offset",
        "scale",
        "start",
        "unit",
    )

    def __init__(
        self,
        name: str,
        start: int,
        length: int,
        byte_order: str,
        is_signed: bool,
        is_float: bool,
        scale: int | float,
        offset: int | float,
        minimum: int | float | None,
        maximum: int | float | None,
        unit: str | None,
        is_multiplexer: bool,
        multiplexer_ids: list[int] | None,
        multiplexer_signal: str | None,
    ) -> None:
        self.name = name
        self.start = start
        self.length = length
        self.byte_order = byte_order
        self.is_signed = is_signed
        self.is_float = is_float
        self.scale = scale
        self.offset = offset
        self.minimum = minimum
        self.maximum = maximum
        self.unit = unit
        self.is_multiplexer = is_multiplexer
        self.multiplexer_ids = multiplexer_ids
        self.multiplexer_signal = multiplexer_signal

    def __repr__(self) -> str:
        return f"CompiledSignal({self.name!r}, start={self.start}, length={self.length})"


class CompiledMessage:
    """A DBC message as cmcan reads it; :meth:`decode` and :meth:`encode` are cantools' own (loaded
    on first use)."""

    __slots__ = (
        "cycle_time",
        "database",
        "frame_id",
        "is_extended_frame",
        "is_fd",
        "length",
        "multiplexed",
        "name",
        "signal_by_name",
        "signals",
    )

    def __init__(
        self,
        name: str,
        frame_id: int,
        is_extended_frame: bool,
        is_fd: bool,
        length: int,
        cycle_time: int | None,
        multiplexed: bool,
        signals: list[CompiledSignal],
    ) -> None:
        self.name = name
        self.frame_id = frame_id
        self.is_extended_frame = is_extended_frame
        self.is_fd = is_fd
        self.length = length
        self.cycle_time = cycle_time
        self.multiplexed = multiplexed
        self.signals = signals
        self.signal_by_name = {s.name: s for s in signals}  # as cantools: the last of a name wins
        self.database: CompiledDatabase | None = None  # set by the database that holds it

    def get_signal_by_name(self, name: str) -> CompiledSignal:
        return self.signal_by_name[name]  # KeyError, as cantools

    def is_multiplexed(self) -> bool:
        return self.multiplexed

    def cantools_message(self) -> Message:
        """This message in the full cantools database of the same file (parsed on first use)."""
        if self.database is None:
            raise RuntimeError(f"message {self.name} belongs to no compiled database")
        return self.database.cantools_database().get_message_by_name(self.name)

    def decode(self, data: bytes, *args: Any, **kwargs: Any) -> Any:
        """cantools' ``Message.decode``: value tables, every option (not the monitor's path)."""
        return self.cantools_message().decode(data, *args, **kwargs)

    def encode(self, data: Any, *args: Any, **kwargs: Any) -> bytes:
        """cantools' ``Message.encode`` (not the monitor's path: that is :mod:`cmcan.can.codec`)."""
        return self.cantools_message().encode(data, *args, **kwargs)

    def __repr__(self) -> str:
        return f"CompiledMessage({self.name!r}, frame_id=0x{self.frame_id:X}, length={self.length})"


class CompiledDatabase:
    """A DBC as cmcan reads it: its messages in the file's order, and the problems cantools' strict
    checks found in them by message name (:func:`cmcan.can.dbc.message_problems` reads them here).
    ``path`` is the file it was compiled from (for cantools' full database when one is asked for)."""

    __slots__ = ("_full", "message_by_name", "messages", "path", "problems", "sha256")

    def __init__(self, path: str, sha256: str, messages: list[CompiledMessage], problems: Mapping[str, str]) -> None:
        self.path = path
        self.sha256 = sha256
        self.messages = messages
        self.problems = dict(problems)
        self.message_by_name = {m.name: m for m in messages}  # as cantools: the last of a name wins
        self._full: Database | None = None
        for m in messages:
            m.database = self

    def get_message_by_name(self, name: str) -> CompiledMessage:
        return self.message_by_name[name]  # KeyError, as cantools

    def cantools_database(self) -> Database:
        """The full cantools database of the same bytes, parsed on first use and kept here: a decode
        per frame reads no file (DbcError when the file has changed since it was compiled)."""
        if self._full is None:
            from cmcan.can.dbc import DbcError, load_dbc_digest

            db, sha256 = load_dbc_digest(self.path)
            if sha256 != self.sha256:
                raise DbcError(f"{self.path}: changed since it was read; run the command again")
            self._full = db
        return self._full

    def decode_message(self, *args: Any, **kwargs: Any) -> Any:
        """cantools' ``Database.decode_message`` (tests and analysis, not the monitor's path)."""
        return self.cantools_database().decode_message(*args, **kwargs)

    def get_message_by_frame_id(self, frame_id: int) -> Message:
        return self.cantools_database().get_message_by_frame_id(frame_id)

    def __repr__(self) -> str:
        return f"CompiledDatabase({self.path!r}, {len(self.messages)} messages)"


# -- from cantools ------------------------------------------------------------------------------------


def compile_database(db: Database, path: str, sha256: str, problems: Mapping[str, str]) -> CompiledDatabase:
    """What cmcan reads of a cantools database, with the problems its loader found."""
    messages = []
    for m in db.messages:
        signals = [
            CompiledSignal(
                s.name,
                s.start,
                s.length,
                s.byte_order,
                bool(s.is_signed),
                bool(s.is_float),
                s.scale,
                s.offset,
                s.minimum,
                s.maximum,
                s.unit,
                bool(s.is_multiplexer),
                list(s.multiplexer_ids) if s.multiplexer_ids is not None else None,
                s.multiplexer_signal,
            )
            for s in m.signals
        ]
        messages.append(
            CompiledMessage(
                m.name,
                m.frame_id,
                bool(m.is_extended_frame),
                bool(m.is_fd),
                m.length,
                m.cycle_time,
                bool(m.is_multiplexed()),
                signals,
            )
        )
    return CompiledDatabase(path, sha256, messages, problems)


# -- to and from JSON-ready data ----------------------------------------------------------------------


def to_doc(db: CompiledDatabase) -> dict[str, Any]:
    """The database as JSON-ready data (without its path and hash: the cache keys on those)."""
    return {
        "messages": [
            {
                "name": m.name,
                "frame_id": m.frame_id,
                "extended": m.is_extended_frame,
                "fd": m.is_fd,
                "length": m.length,
                "cycle_time_ms": m.cycle_time,
                "multiplexed": m.multiplexed,
                "signals": [
                    {
                        "name": s.name,
                        "start": s.start,
                        "length": s.length,
                        "byte_order": s.byte_order,
                        "signed": s.is_signed,
                        "float": s.is_float,
                        "scale": s.scale,
                        "offset": s.offset,
                        "minimum": s.minimum,
                        "maximum": s.maximum,
                        "unit": s.unit,
                        "multiplexer": s.is_multiplexer,
                        "multiplexer_ids": s.multiplexer_ids,
                        "multiplexer_signal": s.multiplexer_signal,
                    }
                    for s in m.signals
                ],
            }
            for m in db.messages
        ],
        "problems": dict(db.problems),
    }


def from_doc(doc: Any, path: str, sha256: str) -> CompiledDatabase:
    """A compiled database from :func:`to_doc`'s data; BadDoc on any field of a wrong type or out of
    range (so a damaged or hostile file can neither crash a reader nor decode wrongly)."""
    d = _fields(doc, "database", {"messages": list, "problems": dict})
    if len(d["messages"]) > MAX_MESSAGES:
        raise BadDoc(f"{len(d['messages'])} messages")
    problems = {}
    for k, v in d["problems"].items():
        problems[_name(k, "problems")] = _text(v, f"problems.{k}")
    return CompiledDatabase(path, sha256, [_message(m, i) for i, m in enumerate(d["messages"])], problems)


_MESSAGE_FIELDS = {
    "name": str,
    "frame_id": int,
    "extended": bool,
    "fd": bool,
    "length": int,
    "cycle_time_ms": (int, type(None)),
    "multiplexed": bool,
    "signals": list,
}
_SIGNAL_FIELDS = {
    "name": str,
    "start": int,
    "length": int,
    "byte_order": str,
    "signed": bool,
    "float": bool,
    "scale": (int, float),
    "offset": (int, float),
    "minimum": (int, float, type(None)),
    "maximum": (int, float, type(None)),
    "unit": (str, type(None)),
    "multiplexer": bool,
    "multiplexer_ids": (list, type(None)),
    "multiplexer_signal": (str, type(None)),
}


def _message(doc: Any, i: int) -> CompiledMessage:
    where = f"messages[{i}]"
    m = _fields(doc, where, _MESSAGE_FIELDS)
    _name(m["name"], f"{where}.name")
    _bounded(m["frame_id"], 0, MAX_FRAME_ID, f"{where}.frame_id")
    _bounded(m["length"], 0, MAX_FRAME_BYTES, f"{where}.length")
    if m["cycle_time_ms"] is not None:
        _bounded(m["cycle_time_ms"], 0, 1 << 32, f"{where}.cycle_time_ms")
    if len(m["signals"]) > MAX_SIGNALS:
        raise BadDoc(f"{where}: {len(m['signals'])} signals")
    signals = [_signal(s, f"{where}.signals[{j}]", m["length"]) for j, s in enumerate(m["signals"])]
    return CompiledMessage(
        m["name"], m["frame_id"], m["extended"], m["fd"], m["length"], m["cycle_time_ms"], m["multiplexed"], signals
    )


def _signal(doc: Any, where: str, frame_bytes: int) -> CompiledSignal:
    s = _fields(doc, where, _SIGNAL_FIELDS)
    _name(s["name"], f"{where}.name")
    if s["byte_order"] not in BYTE_ORDERS:
        raise BadDoc(f"{where}.byte_order: {s['byte_order']!r}")
    _bounded(s["length"], 1, MAX_SIGNAL_BITS, f"{where}.length")
    # a signal's bits lie in the frame read as max(8, length) bytes, as cmcan.can.codec reads it
    _bounded(s["start"], 0, 8 * max(8, frame_bytes) - 1, f"{where}.start")
    for k in ("scale", "offset"):
        _finite(s[k], f"{where}.{k}")
    for k in ("minimum", "maximum"):
        if s[k] is not None:
            _finite(s[k], f"{where}.{k}")
    if s["unit"] is not None:
        _text(s["unit"], f"{where}.unit")
    ids = s["multiplexer_ids"]
    if ids is not None:
        if len(ids) > MAX_SIGNALS:
            raise BadDoc(f"{where}.multiplexer_ids: {len(ids)} values")
        for v in ids:
            _bounded(v, 0, (1 << 64) - 1, f"{where}.multiplexer_ids")
    if s["multiplexer_signal"] is not None:
        _name(s["multiplexer_signal"], f"{where}.multiplexer_signal")
    return CompiledSignal(
        s["name"],
        s["start"],
        s["length"],
        s["byte_order"],
        s["signed"],
        s["float"],
        s["scale"],
        s["offset"],
        s["minimum"],
        s["maximum"],
        s["unit"],
        s["multiplexer"],
        list(ids) if ids is not None else None,
        s["multiplexer_signal"],
    )


def _fields(doc: Any, where: str, types: Mapping[str, Any]) -> dict[str, Any]:
    """``doc`` as a dict with exactly these keys, each of its type (a bool is no int here)."""
    if not isinstance(doc, dict):
        raise BadDoc(f"{where}: {type(doc).__name__}, not an object")
    if set(doc) != set(types):
        raise BadDoc(f"{where}: fields {sorted(map(str, doc))}, expected {sorted(types)}")
    for k, t in types.items():
        v = doc[k]
        allowed = t if isinstance(t, tuple) else (t,)
        if isinstance(v, bool) and bool not in allowed:
            raise BadDoc(f"{where}.{k}: a boolean")
        if not isinstance(v, allowed):
            raise BadDoc(f"{where}.{k}: {type(v).__name__}")
    return doc


def _bounded(v: Any, lo: int, hi: int, where: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise BadDoc(f"{where}: {v!r}, expected an integer in [{lo}, {hi}]")
    return v


def _finite(v: Any, where: str) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise BadDoc(f"{where}: {v!r}, expected a finite number")


def _name(v: Any, where: str) -> str:
    if not isinstance(v, str) or not 0 < len(v) <= MAX_NAME_CHARS:
        raise BadDoc(f"{where}: not a name")
    return v


def _text(v: Any, where: str) -> str:
    if not isinstance(v, str) or len(v) > MAX_TEXT_CHARS:
        raise BadDoc(f"{where}: not a text")
    return v
