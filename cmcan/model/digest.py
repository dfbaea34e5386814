"""A cmcan model file's own checksum: SHA-256 of the file's bytes without the metadata entry holding it.

ONNX has no checksum: a flipped bit in a weight gives a model that loads, runs and predicts plausibly
wrong values. The digest covers every byte of the file (the graph with its weights and node
attributes, the opsets, and the metadata the runtime uses: envelope, oil, V_M) except the one
``metadata_props`` entry ``cmcan.content_sha256`` that records it. It is taken over the bytes as
stored, not over a re-serialization, so it needs neither the ``onnx`` package at run time nor a
canonical encoding: only the top level of the protobuf wire format is walked (tag, length; the graph
is skipped over, not parsed). The writer appends the entry at the end of the serialized model: a
parser merges a repeated field's entries wherever they stand, so the file reads as one more entry
of ``metadata_props``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from dataclasses import dataclass

KEY = "cmcan.content_sha256"
_KEY_BYTES = KEY.encode()
_METADATA_PROPS = 14  # ModelProto.metadata_props (onnx.proto), entries StringStringEntryProto
_ENTRY_KEY, _ENTRY_VALUE = 1, 2
_VARINT, _I64, _LEN, _I32 = 0, 1, 2, 5


class MalformedError(ValueError):
    """The bytes are not a protobuf message (at the top level)."""


def _varint(b: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if i >= len(b) or shift > 63:
            raise MalformedError(f"varint cut short or too long at byte {i}")
        c = b[i]
        i += 1
        value |= (c & 0x7F) << shift
        if c < 0x80:
            return value, i
        shift += 7


def _varint_bytes(n: int) -> bytes:
    out = bytearray()
    while n >= 0x80:
        out.append(n & 0x7F | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _fields(b: bytes | memoryview) -> Iterator[tuple[int, int, int, int]]:
    """(field number, start of the record, start of a length-delimited payload or -1, end) of each
    top-level field of message ``b``, in file order."""
    i = 0
    while i < len(b):
        start = i
        tag, i = _varint(b, i)
        number, wire = tag >> 3, tag & 7
        if number == 0:
            raise MalformedError(f"field number 0 at byte {start}")
        payload = -1
        if wire == _VARINT:
            _, i = _varint(b, i)
        elif wire == _I64:
            i += 8
        elif wire == _I32:
            i += 4
        elif wire == _LEN:
            n, payload = _varint(b, i)
            i = payload + n
        else:  # groups (3, 4) are not in onnx.proto; 6, 7 do not exist
            raise MalformedError(f"wire type {wire} at byte {start}")
        if i > len(b):
            raise MalformedError(f"field {number} at byte {start} runs past the end")
        yield number, start, payload, i


def _digest_records(blob: bytes) -> list[tuple[int, int, bytes]]:
    """(start, end, value) of each ``metadata_props`` entry whose key is :data:`KEY`."""
    found = []
    for number, start, payload, end in _fields(blob):
        if number != _METADATA_PROPS or payload < 0:
            continue
        entry = blob[payload:end]
        key = value = None
        for n, _s, p, e in _fields(entry):
            if p >= 0 and n == _ENTRY_KEY:
                key = entry[p:e]
            elif p >= 0 and n == _ENTRY_VALUE:
                value = entry[p:e]
        if key == _KEY_BYTES:
            found.append((start, end, value or b""))
    return found


def _without(blob: bytes, records: list[tuple[int, int, bytes]]) -> bytes:
    parts, at = [], 0
    for start, end, _ in records:
        parts.append(blob[at:start])
        at = end
    parts.append(blob[at:])
    return b"".join(parts)


def content_sha256(blob: bytes) -> str:
    """The digest of a serialized model: SHA-256 of its bytes with every digest entry cut out."""
    return hashlib.sha256(_without(blob, _digest_records(blob))).hexdigest()


def seal(blob: bytes) -> bytes:
    """A serialized ONNX model with its digest entry (any earlier one replaced) appended."""
    body = _without(blob, _digest_records(blob))
    value = json.dumps(hashlib.sha256(body).hexdigest()).encode()  # JSON, like every cmcan.* entry
    entry = _record(_ENTRY_KEY, _KEY_BYTES) + _record(_ENTRY_VALUE, value)
    return body + _record(_METADATA_PROPS, entry)


def _record(number: int, payload: bytes) -> bytes:
    """A length-delimited field (tag, length, payload)."""
    return _varint_bytes(number << 3 | _LEN) + _varint_bytes(len(payload)) + payload


def recorded_and_actual(blob: bytes) -> tuple[str | None, str]:
    """(the recorded digest or None when the file has none, the digest of its content).

    Raises :class:`MalformedError` for bytes that are not a protobuf message, and ``ValueError``
    for more than one digest entry or one that is not a JSON string."""
    records = _digest_records(blob)
    if len(records) > 1:
        raise ValueError(f"{len(records)} entries {KEY}, expected one")
    actual = hashlib.sha256(_without(blob, records)).hexdigest()
    if not records:
        return None, actual
    try:
        recorded = json.loads(records[0][2])
    except (UnicodeDecodeError, json.JSONDecodeError):
        recorded = None
    if not isinstance(recorded, str):
        raise ValueError(f"metadata {KEY} is not a JSON string")
    return recorded, actual


# -- what the graph holds, from the same walk ---------------------------------------------------------

_GRAPH, _TRAINING_INFO, _FUNCTIONS = 7, 20, 25  # ModelProto
_NODE = 1  # GraphProto
_OP_TYPE, _ATTRIBUTE, _DOMAIN = 4, 5, 7  # NodeProto
_ATTR_GRAPH, _ATTR_GRAPHS = 6, 11  # AttributeProto: a subgraph (the body of Loop, Scan, If), a list of them


@dataclass(frozen=True)
class GraphContent:
    """What a model file's graph holds, read from its bytes without the ``onnx`` package."""

    ops: tuple[tuple[str, str], ...]  # (domain, op type) of each node of the main graph, in file order
    subgraphs: int  # node attributes that hold a graph
    functions: int  # model-local function definitions (operators the file defines itself)
    training_info: int  # training graphs (ONNX training_info)


def metadata_props(blob: bytes) -> dict[str, str] | None:
    """The file's ``metadata_props`` as a parser reads them (the last entry of a key wins), or None
    when an entry is not UTF-8 (then onnxruntime names it). Raises :class:`MalformedError`."""
    view = memoryview(blob)
    props: dict[str, str] = {}
    for entry in _submessages(view, _METADATA_PROPS):
        try:
            props[bytes(_last(entry, _ENTRY_KEY)).decode()] = bytes(_last(entry, _ENTRY_VALUE)).decode()
        except UnicodeDecodeError:
            return None
    return props


def _last(b: memoryview, number: int) -> memoryview:
    value = memoryview(b"")
    for v in _submessages(b, number):  # a parser keeps the last of a repeated scalar field
        value = v
    return value


def _submessages(b: memoryview, number: int) -> Iterator[memoryview]:
    for n, _start, payload, end in _fields(b):
        if n == number and payload >= 0:
            yield b[payload:end]


def _last_string(b: memoryview, number: int) -> str:
    return bytes(_last(b, number)).decode("utf-8", errors="replace")


def graph_content(blob: bytes) -> GraphContent:
    """The operators of the graph (every ``graph`` entry of the file: a parser merges them), and
    whether it holds subgraphs, local functions or training graphs: a walk of the protobuf wire
    format over the graph and its nodes, the weights skipped by their length. Raises
    :class:`MalformedError` for bytes that are not protobuf messages down to the nodes' fields."""
    view = memoryview(blob)
    ops: list[tuple[str, str]] = []
    subgraphs = functions = training = 0
    for number, _start, payload, end in _fields(view):
        if payload < 0:
            continue
        if number == _FUNCTIONS:
            functions += 1
        elif number == _TRAINING_INFO:
            training += 1
        elif number == _GRAPH:
            for node in _submessages(view[payload:end], _NODE):
                ops.append((_last_string(node, _DOMAIN), _last_string(node, _OP_TYPE)))
                for attr in _submessages(node, _ATTRIBUTE):
                    subgraphs += sum(1 for n, *_ in _fields(attr) if n in (_ATTR_GRAPH, _ATTR_GRAPHS))
    return GraphContent(tuple(ops), subgraphs, functions, training)
