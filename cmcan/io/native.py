"""The C helpers, when the install built them (``_native.so`` from ``_candump_fast.c``,
``_textcols_fast.c`` and ``cmcan/sim/_drive_fast.c``): the parser of common ``candump -l`` lines and
the row formatter of the timeline and the emitted log, and the simulator's time integration (called
by :mod:`cmcan.sim.drive`, which has the Python loop it transcribes).

Loaded with ctypes, which releases the GIL for each call: the read-ahead thread parses the next
chunk and the writer thread formats the last one on the second core without taking the GIL from
the replay engine, which numpy's many short calls cannot avoid. Building them needs a C compiler
at install time (``hatch_build.py``); without one, or with ``CMCAN_NATIVE=0`` in the environment,
the numpy code of :mod:`cmcan.io.candump_columns` and :mod:`cmcan.io.textcols` does the same work
(tests check they agree, and agree with python-can's reader and Python's own formatting).
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

LIB_NAME = "_native.so"
_NAME_SLOT = 32  # NAME_MAX_LEN + 1 in the C source
_MAX_NAMES = 64  # channel names per chunk; lines beyond go to the line reader


def _load() -> ctypes.CDLL | None:
    if os.environ.get("CMCAN_NATIVE", "1") == "0":
        return None
    path = Path(__file__).with_name(LIB_NAME)
    if not path.is_file():
        return None
    try:
        lib = ctypes.CDLL(str(path))
    except OSError:  # built for another machine: the numpy reader
        return None
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32
    lib.cmcan_count_lines.argtypes = [ctypes.c_char_p, i64]
    lib.cmcan_count_lines.restype = i64
    lib.cmcan_parse_candump.argtypes = [ctypes.c_char_p, i64, i64, p, p, p, p, p, p, p, p, p, i32, p]
    lib.cmcan_parse_candump.restype = i64
    lib.cmcan_format_rows.argtypes = [i64, i32, p, p, p, p, p, p, p, ctypes.c_char_p, i32, p, i64]
    lib.cmcan_format_rows.restype = i64
    if hasattr(lib, "cmcan_drive_integrate"):  # not in a library built before the integrator
        d = ctypes.c_double
        lib.cmcan_drive_constants.argtypes = []
        lib.cmcan_drive_constants.restype = i32
        lib.cmcan_drive_integrate.argtypes = [i64, p, d, p, p, p, p, p, p, p, p, p, p, p, p, p, p]
        lib.cmcan_drive_integrate.restype = i64
    return lib


LIB = _load()


@dataclass
class Parsed:
    """Line i of the text is row i; ``fast[i]``: parsed (else for the line reader, all zero);
    ``chan`` indexes ``names``."""

    n_lines: int
    fast: NDArray[np.bool_]
    timestamp_s: NDArray[np.float64]
    chan: NDArray[np.int16]
    arbitration_id: NDArray[np.uint32]
    extended: NDArray[np.bool_]
    dlc: NDArray[np.int16]
    data: NDArray[np.uint8]
    names: list[bytes]


def parse(text: bytes, size: int | None = None) -> Parsed:
    """Parse the complete lines of ``text[:size]`` (which ends with a newline) with the C parser;
    ``LIB`` must be loaded."""
    assert LIB is not None
    size = len(text) if size is None else min(size, len(text))
    n = int(LIB.cmcan_count_lines(text, size))
    fast = np.empty(n, dtype=np.bool_)
    t = np.empty(n, dtype=np.float64)
    chan = np.empty(n, dtype=np.int16)
    cid = np.empty(n, dtype=np.uint32)
    ext = np.empty(n, dtype=np.bool_)
    dlc = np.empty(n, dtype=np.int16)
    data = np.empty((n, 8), dtype=np.uint8)
    names = np.zeros((_MAX_NAMES, _NAME_SLOT), dtype=np.uint8)
    name_len = np.zeros(_MAX_NAMES, dtype=np.int32)
    n_names = np.zeros(1, dtype=np.int32)
    ptr = lambda a: a.ctypes.data  # noqa: E731
    got = LIB.cmcan_parse_candump(
        text,
        size,
        n,
        ptr(t),
        ptr(chan),
        ptr(cid),
        ptr(ext),
        ptr(dlc),
        ptr(data),
        ptr(fast),
        ptr(names),
        ptr(name_len),
        _MAX_NAMES,
        ptr(n_names),
    )
    assert got == n, (got, n)
    found = [names[k, : name_len[k]].tobytes() for k in range(int(n_names[0]))]
    return Parsed(n, fast, t, chan, cid, ext, dlc, data, found)


# -- rows of text ------------------------------------------------------------------------------------

FIXED, INT, NAME, HEX_ID, HEX_DATA = range(5)  # the column kinds of _textcols_fast.c


@dataclass
class TextColumn:
    """One column of :func:`format_rows`: its kind, written after ``prefix``.
    FIXED: ``values`` float64 with ``decimals``; INT: int64; NAME: int64 indexes into ``names``;
    HEX_ID: uint32 with ``widths`` the extended flags (8 digits, else 3); HEX_DATA: (n, 8) uint8
    with ``widths`` the lengths in bytes."""

    kind: int
    values: NDArray[np.generic]
    prefix: bytes = b""
    decimals: int = 0
    widths: NDArray[np.generic] | None = None
    names: Sequence[bytes] = ()


_WIDTH = {FIXED: 23, INT: 21, HEX_ID: 8, HEX_DATA: 16}
_DTYPES = {FIXED: np.float64, INT: np.int64, NAME: np.int64, HEX_ID: np.uint32, HEX_DATA: np.uint8}


def format_rows(n: int, columns: Sequence[TextColumn], end: bytes) -> bytes | None:
    """``n`` rows of the columns side by side, each row closed by ``end``; None when a value does not
    fit the usual widths (a number beyond 2^52 written out in full): the caller formats those rows
    otherwise. ``LIB`` must be loaded."""
    assert LIB is not None
    k = len(columns)
    keep: list[object] = []  # every buffer the call reads, alive until it returns
    kinds = np.array([c.kind for c in columns], dtype=np.int32)
    args = np.array([c.decimals for c in columns], dtype=np.int32)
    a, b, t = (ctypes.c_void_p * k)(), (ctypes.c_void_p * k)(), (ctypes.c_char_p * k)()
    prefix = (ctypes.c_char_p * k)(*[c.prefix for c in columns])
    prefix_len = np.array([len(c.prefix) for c in columns], dtype=np.int32)
    width = sum(len(c.prefix) for c in columns) + len(end)
    for j, c in enumerate(columns):
        if c.kind == FIXED and not 0 <= c.decimals <= 9:
            raise ValueError(f"decimals {c.decimals}: 0..9")
        v = np.ascontiguousarray(c.values, dtype=_DTYPES[c.kind])
        if len(v) != n:
            raise ValueError(f"column {j}: {len(v)} values for {n} rows")
        keep.append(v)
        a[j] = v.ctypes.data
        if c.kind == NAME:
            if n and not (int(v.min()) >= 0 and int(v.max()) < len(c.names)):
                raise IndexError(f"column {j}: a name index outside 0..{len(c.names) - 1}")
            off = np.cumsum([0, *(len(x) for x in c.names)]).astype(np.int32)
            text = b"".join(c.names)
            keep += [off, text]
            b[j], t[j] = off.ctypes.data, text
            width += max((len(x) for x in c.names), default=0)
        else:
            width += _WIDTH[c.kind] + c.decimals
            if c.kind in (HEX_ID, HEX_DATA):
                assert c.widths is not None
                w = np.ascontiguousarray(c.widths, dtype=np.uint8 if c.kind == HEX_ID else np.int16)
                keep.append(w)
                b[j] = w.ctypes.data
    out = np.empty(max(1, n * width), dtype=np.uint8)
    got = LIB.cmcan_format_rows(
        n,
        k,
        kinds.ctypes.data,
        args.ctypes.data,
        a,
        b,
        t,
        prefix,
        prefix_len.ctypes.data,
        end,
        len(end),
        out.ctypes.data,
        len(out),
    )
    return None if got < 0 else out[:got].tobytes()
