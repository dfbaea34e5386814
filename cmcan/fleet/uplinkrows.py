"""What the ingest makes of one MQTT message of a gateway's uplink: pure code over bytes, no I/O.

``parse`` turns a topic and a payload into a :class:`Message` (its table, machine, day, dedup key and
row) or a :class:`Refusal` (the reason, and what of the message can be named safely). ``Seen`` is
the index of what is committed (by the payload's ``id``: ``<stream>-<seq>``, kept per stream as
ranges of ``seq``, so it stays small however many entries arrive in order), ``Batch`` sorts the
messages of one batch into rows, duplicates and quarantine rows. The payloads are those of
``docs/uplink.md`` (schema :data:`cmcan.uplink.records.SCHEMA_VERSION`), whose vocabulary is
imported, not copied.
"""

from __future__ import annotations

import bisect
import datetime as dt
import hashlib
import json
import math
import re
import sys
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from cmcan.fleet.dataset import MACHINE_RE, day_of
from cmcan.uplink.records import DROPPED, ENVELOPE_KEYS, EVENT, LEVELS, SCHEMA_VERSION, SUMMARY, dumps

STATUS = "status"
INGEST_KINDS = (EVENT, SUMMARY, DROPPED, STATUS)  # the topics subscribed to (not health: not data)
TABLE_OF_KIND = {
    EVENT: "uplink_events",
    SUMMARY: "uplink_summaries",
    DROPPED: "uplink_dropped",
    STATUS: "uplink_status",
}
UPLINK_TABLES = tuple(TABLE_OF_KIND.values())
UPLINK_QUARANTINE = "uplink_quarantine"
UPLINK_COMMITS = "uplink_commits"  # one record per committed batch or fold: its files and the ids in them
MAX_PAYLOAD_BYTES = 256 * 1024  # a summary is some 2 KiB; anything near this is not a gateway's
MAX_SHOWN = 120  # characters of a hostile topic or id kept in a quarantine row
# <stream>-<seq>: the outbox's random stream id (hex) and the entry's number in it
ID_RE = re.compile(r"([0-9a-f]{1,64})-([0-9]{1,18})")
STATUS_STATES = ("online", "offline")
T_MIN_S, T_MAX_S = 0.0, 253402300799.0  # what a day partition can name (year 1970 to 9999)


@dataclass(frozen=True)
class Message:
    """A payload that parsed: where its row goes and how copies of it are recognised."""

    kind: str
    table: str
    machine: str
    day: str
    dedup: tuple[str, int] | str  # ("<machine>/<stream>", seq) of an entry; a content key for a status
    id: str  # "<machine>/<id>": a cloned gateway (the same outbox, so stream) is still another machine
    topic: str
    digest: str  # of the content copies share (all but ``late``)
    row: dict[str, Any]


@dataclass(frozen=True)
class Refusal:
    """A message that goes to the quarantine, with why; the topic and id only as far as they are safe
    to show, the payload by size and hash (never its content)."""

    reason: str
    topic: str
    machine: str | None
    id: str | None
    payload_bytes: int
    payload_sha256: str

    @property
    def key(self) -> str:
        """The same bad message redelivered is quarantined once."""
        return "q:" + hashlib.sha256(f"{self.topic}\0{self.payload_sha256}\0{self.reason}".encode()).hexdigest()[:32]


def shown(text: str) -> str:
    """A hostile string as one safe line: escaped, cut to :data:`MAX_SHOWN` characters."""
    s = text.encode("unicode_escape", "backslashreplace").decode("ascii")
    return s if len(s) <= MAX_SHOWN else s[: MAX_SHOWN - 3] + "..."


class _Bad(Exception):
    pass


def _no_constant(name: str) -> Any:
    raise _Bad(f"payload holds {name}, which JSON does not allow")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out = dict(pairs)  # (in C; a key is looked for only when one repeats)
    if len(out) != len(pairs):
        seen: set[str] = set()
        for k, _v in pairs:
            if k in seen:
                raise _Bad(f"payload repeats the key {shown(k)!r}")
            seen.add(k)
    return out


def _decode(payload: bytes) -> dict[str, Any]:
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise _Bad(f"payload of {len(payload)} bytes, more than {MAX_PAYLOAD_BYTES}")
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _Bad(f"payload is not UTF-8 (byte {exc.start})") from None
    try:
        obj = json.loads(text, parse_constant=_no_constant, object_pairs_hook=_unique_keys)
    except RecursionError:
        raise _Bad("payload nested too deep") from None
    except ValueError as exc:
        raise _Bad(f"payload is not JSON ({str(exc).splitlines()[0][:80]})") from None
    if not isinstance(obj, dict):
        raise _Bad(f"payload is a JSON {type(obj).__name__}, expected an object")
    return obj


def _field(p: dict[str, Any], name: str, types: tuple[type, ...], required: bool = True) -> Any:
    v = p.get(name)
    if v is None and not required:
        return None
    if v is None or isinstance(v, bool) != (bool in types) or not isinstance(v, types):
        want = "/".join(t.__name__ for t in types)
        got = "missing" if name not in p else type(v).__name__
        raise _Bad(f"field {name!r}: expected {want}, got {got}")
    if isinstance(v, float) and not math.isfinite(v):
        raise _Bad(f"field {name!r}: not a finite number")
    return v


_NUM = (int, float)
_FLOAT_MAX = sys.float_info.max
INT64 = (-(2**63), 2**63 - 1)  # what an integer column holds


def _finite(v: Any) -> float | None:
    """A JSON number as a finite float, else None (a bool, NaN, infinity, an integer too large for a
    float: ``float()`` of one raises, which made one such field of one message stop the ingest)."""
    t = type(v)
    if t is float:
        return v if math.isfinite(v) else None
    if t is int:
        return float(v) if -_FLOAT_MAX <= v <= _FLOAT_MAX else None
    return None


def _int64(p: dict[str, Any], name: str) -> int:
    v = _field(p, name, (int,))
    if not INT64[0] <= v <= INT64[1]:
        raise _Bad(f"field {name!r}: an integer beyond 64 bits")
    return v


def _opt_num(d: Any, name: str) -> float | None:
    """A number of an optional part of the payload (None when absent, null, "never" or not a number)."""
    return _finite(d.get(name)) if isinstance(d, dict) else None


def _opt_str(d: Any, name: str) -> str | None:
    v = d.get(name) if isinstance(d, dict) else None
    return shown(v) if isinstance(v, str) else None


def _hours(v: Any) -> float | None:
    """An hours field of the prognosis: a number, ``"never"`` (infinity), or None."""
    if v == "never":
        return math.inf
    return _finite(v)


def _total_h(levels: Any) -> float | None:
    """Time in any level since commissioning (the summary's ``time_in_level_total_s``), in hours."""
    if not isinstance(levels, dict):
        return None
    parts = [_opt_num(levels, lv) for lv in LEVELS]
    return sum(x for x in parts if x is not None) / 3600.0 if any(x is not None for x in parts) else None


def split_topic(topic: str, prefix: str) -> tuple[str, str]:
    """``<prefix>/<machine>/<kind>`` -> (machine, kind), both checked."""
    head = prefix + "/"
    rest = topic[len(head) :].split("/") if topic.startswith(head) else []
    if len(rest) != 2:
        raise _Bad(f"topic is not {prefix}/<machine>/<kind>")
    machine, kind = rest
    if kind not in INGEST_KINDS:
        raise _Bad(f"topic kind {shown(kind)!r} is none of {', '.join(INGEST_KINDS)}")
    if not MACHINE_RE.fullmatch(machine):
        raise _Bad(f"machine id {shown(machine)!r} of the topic is not a safe name (letters, digits, '.', '_', '-')")
    return machine, kind


def _envelope(p: dict[str, Any], machine: str, kind: str) -> None:
    schema = _field(p, "schema", (int,))
    if schema > SCHEMA_VERSION:
        raise _Bad(f"schema {schema} is newer than this ingest reads ({SCHEMA_VERSION}): update cmcan")
    if schema != SCHEMA_VERSION:
        raise _Bad(f"schema {schema} is unknown (this ingest reads {SCHEMA_VERSION})")
    if _field(p, "kind", (str,)) != kind:
        raise _Bad(f"field 'kind' {shown(p['kind'])!r} differs from the topic's {kind!r}")
    if _field(p, "machine_id", (str,)) != machine:
        raise _Bad(f"field 'machine_id' {shown(p['machine_id'])!r} differs from the topic's {machine!r}")


def _time(p: dict[str, Any]) -> float:
    t = _field(p, "t_s", _NUM)
    if not T_MIN_S <= t <= T_MAX_S:  # (compared as it came: a huge integer is no float)
        raise _Bad(f"field 't_s': {shown(str(t))} is not a time between 1970 and 9999")
    return float(t)


def _entry_row(p: dict[str, Any], kind: str) -> dict[str, Any]:
    """The columns of an event, summary or dropped row (the whole payload is kept beside them)."""
    if kind == EVENT:
        return {
            "type": shown(_field(p, "type", (str,))),
            "from_level": _opt_str(p, "from"),
            "to_level": _opt_str(p, "to"),
            "reason": _opt_str(p, "reason"),
            "ratio_filt_pct": _opt_num(p, "ratio_filt_pct"),
            "extra_leak_lpm": _opt_num(p, "extra_leak_lpm"),
        }
    if kind == DROPPED:
        return {
            "reason": shown(_field(p, "reason", (str,))),
            "entries": _int64(p, "entries"),
            "first_seq": _opt_num(p, "first_seq"),
            "last_seq": _opt_num(p, "last_seq"),
        }
    level = _field(p, "level", (str,))
    if level not in LEVELS:
        raise _Bad(f"field 'level': {shown(level)!r} is none of {', '.join(LEVELS)}")
    window = p.get("window")
    b, g = p.get("baseline"), p.get("prognosis")
    eol = g.get("to_eol_h") if isinstance(g, dict) else None
    eol = eol if isinstance(eol, list) and len(eol) == 3 else [None, None, None]
    return {
        "level": level,
        "reason": _opt_str(p, "reason"),
        "ratio_filt_pct": _opt_num(p, "ratio_filt_pct"),
        "extra_leak_lpm": _opt_num(p, "extra_leak_lpm"),
        "window_start_s": _opt_num(window, "start_s"),
        "window_every_s": _opt_num(window, "every_s"),
        "evaluated_s": _opt_num(p, "evaluated_s"),
        "evaluated_total_h": _opt_num(p, "evaluated_total_h"),
        "operating_total_h": _total_h(p.get("time_in_level_total_s")),
        "warning_count": _opt_num(p, "warning_count"),
        "fault_count": _opt_num(p, "fault_count"),
        "baseline_state": _opt_str(b, "state"),
        "baseline_learned_h": _opt_num(b, "learned_h"),
        "baseline_distance_lpm": _opt_num(b, "distance_lpm"),
        "prognosis_state": _opt_str(g, "state"),
        "prognosis_direction": _opt_str(g, "direction"),
        "prognosis_to_warning_h": _hours(g.get("to_warning_h")) if isinstance(g, dict) else None,
        **{f"prognosis_to_eol_{q}_h": _hours(v) for q, v in zip(("p10", "p50", "p90"), eol, strict=True)},
    }


_HEAD_KEYS = ("schema", "kind", "machine_id", "id", "seq", "t", "t_s")  # the envelope before its `late`


def digest_of(p: dict[str, Any], payload: bytes | None = None) -> str:
    """What copies of one entry share: everything but ``late`` (docs/uplink.md). A payload laid out as
    the uplink writes it (:func:`cmcan.uplink.records.envelope`: these keys first, then ``late``) is
    hashed as its bytes with ``late`` false (the copies the uplink sends differ in that value alone),
    a tenth of the cost of writing the content out again; any other payload by its content without
    ``late``. (So a copy re-serialised by something between, its bytes but not its content other, is
    quarantined as other content: never dropped unseen.)"""
    late = p.get("late")
    if payload is not None and isinstance(late, bool):
        try:
            head = dumps({k: p[k] for k in _HEAD_KEYS})[:-1].encode() + b',"late":'
        except (KeyError, TypeError, ValueError):
            head = b""
        value = b"true" if late else b"false"
        if head and payload.startswith(head) and payload.startswith(value, len(head)):
            # the top-level key at that place (the head is whole keys and values; no key repeats)
            return hashlib.sha256(b"%sfalse%s" % (head, payload[len(head) + len(value) :])).hexdigest()[:32]
    return hashlib.sha256(dumps({k: v for k, v in p.items() if k != "late"}).encode()).hexdigest()[:32]


def parse(topic: str, payload: bytes, prefix: str, received_s: float) -> Message | Refusal:
    """One MQTT message as a row of the data set, or why not. Never raises on what arrives."""
    sha = hashlib.sha256(payload).hexdigest()
    machine: str | None = None
    ident: str | None = None
    try:
        machine, kind = split_topic(topic, prefix)
        p = _decode(payload)
        _envelope(p, machine, kind)
        if kind == STATUS:
            state = _field(p, "state", (str,))
            if state not in STATUS_STATES:
                raise _Bad(f"field 'state': {shown(state)!r} is none of {', '.join(STATUS_STATES)}")
            key = "s:" + hashlib.sha256(f"{topic}\0{sha}".encode()).hexdigest()[:32]
            row = {
                "time_s": float(received_s),
                "state": state,
                "reason": _opt_str(p, "reason"),
                "client_id": _opt_str(p, "client_id"),
                "version": _opt_str(p, "version"),
                "uplink_time_utc": _opt_str(p, "uplink_time_utc"),
            }
            return Message(kind, TABLE_OF_KIND[kind], machine, day_of(received_s), key, key, topic, sha[:32], row)
        ident = _field(p, "id", (str,))
        m = ID_RE.fullmatch(ident)
        if m is None:
            ident = None
            raise _Bad(f"field 'id' {shown(p['id'])!r} is not <stream>-<seq>")
        seq = _field(p, "seq", (int,))
        if int(m.group(2)) != seq:
            raise _Bad(f"field 'id' {ident!r} does not end in its seq {seq}")
        t_s = _time(p)
        late = _field(p, "late", (bool,))
        row = {
            "id": ident,
            "stream": m.group(1),
            "seq": seq,
            "time_s": t_s,
            "late": late,
            **_entry_row(p, kind),
            "payload": payload.decode("utf-8"),  # as it arrived (it parsed: UTF-8 JSON of one object)
            "received_s": float(received_s),
        }
        dedup = (f"{machine}/{m.group(1)}", seq)
        return Message(
            kind,
            TABLE_OF_KIND[kind],
            machine,
            day_of(t_s),
            dedup,
            f"{machine}/{ident}",
            topic,
            digest_of(p, payload),
            row,
        )
    except _Bad as exc:
        return Refusal(str(exc), shown(topic), machine, ident, len(payload), sha)


def quarantine_row(r: Refusal, received_s: float) -> dict[str, Any]:
    return {
        "received_s": float(received_s),
        "received_at": dt.datetime.fromtimestamp(received_s, dt.UTC).isoformat(timespec="milliseconds"),
        "topic": r.topic,
        "machine": r.machine,
        "id": r.id,
        "reason": r.reason,
        "payload_bytes": r.payload_bytes,
        "payload_sha256": r.payload_sha256,
    }


# -- what is committed ----------------------------------------------------------------------------------


@dataclass
class Seen:
    """The ids committed: per machine and stream (``"<machine>/<stream>"``), disjoint ranges
    ``[lo, hi]`` of seq (sorted); other keys (a status, a quarantined message) as a set. ``recent``
    keeps the content digests of the latest ids (bounded), so a copy with other content is told from
    a plain duplicate."""

    ranges: dict[str, list[list[int]]] = field(default_factory=dict)
    keys: set[str] = field(default_factory=set)
    recent: OrderedDict[str, str] = field(default_factory=OrderedDict)
    recent_max: int = 1 << 16

    def __contains__(self, dedup: tuple[str, int] | str) -> bool:
        if isinstance(dedup, str):
            return dedup in self.keys
        stream, seq = dedup
        rs = self.ranges.get(stream)
        if not rs:
            return False
        i = bisect.bisect_right(rs, [seq, math.inf]) - 1
        return i >= 0 and rs[i][0] <= seq <= rs[i][1]

    def add(self, dedup: tuple[str, int] | str) -> None:
        if isinstance(dedup, str):
            self.keys.add(dedup)
            return
        stream, seq = dedup
        if dedup in self:
            return
        rs = self.ranges.setdefault(stream, [])
        i = bisect.bisect_right(rs, [seq, math.inf])
        rs.insert(i, [seq, seq])
        if i + 1 < len(rs) and rs[i + 1][0] == seq + 1:  # joins the next range
            rs[i][1] = rs.pop(i + 1)[1]
        if i > 0 and rs[i - 1][1] == seq - 1:  # joins the previous one
            rs[i - 1][1] = rs.pop(i)[1]

    def remember(self, ident: str, digest: str) -> None:
        self.recent[ident] = digest
        self.recent.move_to_end(ident)
        while len(self.recent) > self.recent_max:
            self.recent.popitem(last=False)

    def merge(self, record: dict[str, Any]) -> None:
        """The ids of a commit record (:func:`ids_record`)."""
        for stream, rs in record.get("ranges", {}).items():
            for lo, hi in rs:
                self._add_range(stream, int(lo), int(hi))
        self.keys.update(record.get("keys", ()))

    def _add_range(self, stream: str, lo: int, hi: int) -> None:
        rs = self.ranges.setdefault(stream, [])
        merged = [r for r in rs if r[1] < lo - 1 or r[0] > hi + 1]
        for r in rs:
            if not (r[1] < lo - 1 or r[0] > hi + 1):
                lo, hi = min(lo, r[0]), max(hi, r[1])
        merged.append([lo, hi])
        merged.sort()
        self.ranges[stream] = merged


def ids_record(dedups: list[tuple[str, int] | str]) -> dict[str, Any]:
    """The ids of a batch as its commit record lists them: ranges per stream, other keys."""
    s = Seen()
    for d in dedups:
        s.add(d)
    return {"ranges": s.ranges, "keys": sorted(s.keys)}


# -- one batch ------------------------------------------------------------------------------------------


@dataclass
class Batch:
    """The messages received since the last commit, sorted: new rows per (table, machine, day),
    quarantine rows, and the acknowledgements owed once the batch is committed."""

    rows: dict[tuple[str, str, str], list[dict[str, Any]]] = field(default_factory=dict)
    quarantine: list[dict[str, Any]] = field(default_factory=list)
    dedups: list[tuple[str, int] | str] = field(default_factory=list)
    digests: dict[str, str] = field(default_factory=dict)  # id -> digest, of this batch's new rows
    keys: set[str] = field(default_factory=set)  # the quarantined messages' keys (as in dedups)
    acks: list[tuple[int, int]] = field(default_factory=list)  # (mid, qos)
    duplicates: int = 0
    messages: int = 0

    def __len__(self) -> int:
        return self.messages

    def add(self, parsed: Message | Refusal, seen: Seen, received_s: float, ack: tuple[int, int] | None) -> str:
        """Sort one message in; returns what it was: 'new', 'duplicate' or 'quarantined'."""
        self.messages += 1
        if ack is not None:
            self.acks.append(ack)
        if isinstance(parsed, Message):
            if parsed.dedup in seen or parsed.id in self.digests:
                before = self.digests.get(parsed.id) or seen.recent.get(parsed.id)
                if before is None or before == parsed.digest:
                    self.duplicates += 1
                    return "duplicate"
                ident = parsed.id.split("/", 1)[1]
                parsed = Refusal(
                    f"id {ident} arrived before with other content (a copy may differ only in 'late')",
                    shown(parsed.topic),
                    parsed.machine,
                    ident,
                    len(parsed.row.get("payload", "")),
                    parsed.digest,
                )
            else:
                self.rows.setdefault((parsed.table, parsed.machine, parsed.day), []).append(parsed.row)
                self.dedups.append(parsed.dedup)
                self.digests[parsed.id] = parsed.digest
                return "new"
        if parsed.key in seen or parsed.key in self.keys:
            self.duplicates += 1
            return "duplicate"
        self.dedups.append(parsed.key)
        self.keys.add(parsed.key)
        self.quarantine.append(quarantine_row(parsed, received_s))
        return "quarantined"

    def committed_into(self, seen: Seen) -> None:
        """After the commit: its ids are seen."""
        for d in self.dedups:
            seen.add(d)
        for ident, digest in self.digests.items():
            seen.remember(ident, digest)


__all__ = [
    "ENVELOPE_KEYS",
    "INGEST_KINDS",
    "UPLINK_COMMITS",
    "UPLINK_QUARANTINE",
    "UPLINK_TABLES",
    "Batch",
    "Message",
    "Refusal",
    "Seen",
    "ids_record",
    "parse",
]


# Column types of each table (Arrow aliases): a column that is null in every row of a file keeps its
# type, so the files of a table union by name.
_ENTRY = {"id": "string", "stream": "string", "seq": "int64", "time_s": "double", "late": "bool"}
_TAIL = {"payload": "string", "received_s": "double"}
COLUMNS: dict[str, dict[str, str]] = {
    "uplink_events": {
        **_ENTRY,
        "type": "string",
        "from_level": "string",
        "to_level": "string",
        "reason": "string",
        "ratio_filt_pct": "double",
        "extra_leak_lpm": "double",
        **_TAIL,
    },
    "uplink_summaries": {
        **_ENTRY,
        "level": "string",
        "reason": "string",
        "ratio_filt_pct": "double",
        "extra_leak_lpm": "double",
        "window_start_s": "double",
        "window_every_s": "double",
        "evaluated_s": "double",
        "evaluated_total_h": "double",
        "operating_total_h": "double",
        "warning_count": "double",
        "fault_count": "double",
        "baseline_state": "string",
        "baseline_learned_h": "double",
        "baseline_distance_lpm": "double",
        "prognosis_state": "string",
        "prognosis_direction": "string",
        "prognosis_to_warning_h": "double",
        "prognosis_to_eol_p10_h": "double",
        "prognosis_to_eol_p50_h": "double",
        "prognosis_to_eol_p90_h": "double",
        **_TAIL,
    },
    "uplink_dropped": {
        **_ENTRY,
        "reason": "string",
        "entries": "int64",
        "first_seq": "double",
        "last_seq": "double",
        **_TAIL,
    },
    "uplink_status": {
        "time_s": "double",
        "state": "string",
        "reason": "string",
        "client_id": "string",
        "version": "string",
        "uplink_time_utc": "string",
    },
    UPLINK_QUARANTINE: {
        "received_s": "double",
        "received_at": "string",
        "topic": "string",
        "machine": "string",
        "id": "string",
        "reason": "string",
        "payload_bytes": "int64",
        "payload_sha256": "string",
    },
}
