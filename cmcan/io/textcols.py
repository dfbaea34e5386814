"""Text columns written with array operations, to the byte what Python's own formatting writes.

The replay writes a timeline row per evaluation tick and a candump line per emitted frame: tens of
thousands per million frames of log, where formatting each number with an f-string costs as much as
the rest of the columnar engine. Here a column of numbers becomes a matrix of ASCII digits at once.

Exactness: ``f"{x:.{d}f}"`` rounds the exact binary value of ``x`` to ``d`` decimals, half to even.
The array path scales by 10^d in floating point, which can move a value across a rounding boundary
only when it lies within a few ulps of one; such values (and infinities, numbers beyond 2^52) are
formatted by Python itself. Tests hold the two equal over random and adversarial values. NaN is an
empty cell: a value that is not there (a tick not evaluated has no prediction, as the fleet's NaN).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

_MAX_SCALED = float(2**52)
_DIGITS = np.frombuffer(b"0123456789", dtype=np.uint8)


class Column:
    """A column of text cells: right-aligned ASCII in ``chars`` (n, width), ``lengths`` per row."""

    __slots__ = ("chars", "lengths")

    def __init__(self, chars: NDArray[np.uint8], lengths: NDArray[np.int64]) -> None:
        self.chars = chars
        self.lengths = lengths

    @classmethod
    def of_strings(cls, cells: Sequence[str]) -> Column:
        enc = [c.encode("ascii") for c in cells]
        width = max((len(e) for e in enc), default=0)
        out = np.full((len(enc), width), 0x20, dtype=np.uint8)
        for i, e in enumerate(enc):
            if e:
                out[i, width - len(e) :] = np.frombuffer(e, dtype=np.uint8)
        return cls(out, np.fromiter((len(e) for e in enc), np.int64, len(enc)))

    @classmethod
    def of_names(cls, codes: NDArray[np.integer], names: dict[int, str]) -> Column:
        """Cells from a table of names (e.g. a gate code's name)."""
        keys = sorted(names)
        table = cls.of_strings([names[k] for k in keys])
        pos = np.searchsorted(np.asarray(keys), codes)
        return cls(table.chars[pos], table.lengths[pos])


_POW10 = np.array([10**k for k in range(1, 19)], dtype=np.int64)
# "00".."99": two digits per division
_PAIRS = np.frombuffer("".join(f"{i:02d}" for i in range(100)).encode("ascii"), dtype=np.uint16)


def name_indexes(codes: NDArray[np.integer], names: dict[int, str]) -> tuple[NDArray[np.int64], list[bytes]] | None:
    """Each code's place in the table of names (``Column.of_names`` order), and the names as bytes;
    None when a code is not in the table."""
    keys = np.asarray(sorted(names))
    pos = np.searchsorted(keys, codes)
    if len(pos) and not (pos.max() < len(keys) and (keys[pos] == codes).all()):
        return None
    return pos.astype(np.int64), [names[int(k)].encode("ascii") for k in keys]


def _uint_digits(v: NDArray[np.int64], min_digits: int) -> tuple[NDArray[np.uint8], NDArray[np.int64]]:
    """Decimal digits of non-negative integers, right-aligned and zero-padded to a common width, and
    each one's digit count (at least ``min_digits``)."""
    n = len(v)
    if not n:
        return np.zeros((0, max(1, min_digits)), dtype=np.uint8), np.zeros(0, np.int64)
    ndig = np.maximum(np.searchsorted(_POW10, v, side="right") + 1, min_digits)
    width = int(ndig.max())
    pairs = np.empty((n, (width + 1) // 2), dtype=np.uint16)  # two ASCII digits per element
    rest = v.copy()
    for col in range(pairs.shape[1] - 1, -1, -1):
        q = rest // 100
        pairs[:, col] = _PAIRS[rest - q * 100]
        rest = q
    out = pairs.view(np.uint8)
    return out[:, out.shape[1] - width :], ndig.astype(np.int64)


def fixed(x: NDArray[np.float64], decimals: int) -> Column:
    """``f"{v:.{decimals}f}"`` for every value of ``x``; an empty cell for NaN."""
    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    scale = 10**decimals
    with np.errstate(over="ignore", invalid="ignore"):
        # The integer part and the fraction are exact in float64; only the fraction is scaled, so the
        # rounding error is a few ulps of 10^d: values that close to a halfway point (true ties
        # among them), NaN, infinities and numbers beyond 2^52 are left to Python.
        ax = np.abs(x)
        slow = ~(ax < _MAX_SCALED)
        ax = np.where(slow, 0.0, ax)
        whole = np.floor(ax)
        scaled = (ax - whole) * float(scale)
        rounded = np.rint(scaled)
        slow |= np.abs(scaled - np.floor(scaled) - 0.5) <= 4.0 * np.spacing(np.maximum(scaled, 1.0))
    ip = whole.astype(np.int64)
    fp = rounded.astype(np.int64)
    if decimals:
        carry = fp >= scale
        ip += carry
        fp[carry] -= scale
    else:
        ip += fp
    idig, ilen = _uint_digits(ip, 1)
    neg = np.signbit(x)
    width = idig.shape[1] + 1 + (decimals + 1 if decimals else 0)
    out = np.full((n, width), 0x20, dtype=np.uint8)
    if decimals:
        fdig, _ = _uint_digits(fp, decimals)
        out[:, width - decimals :] = fdig[:, -decimals:]
        out[:, width - decimals - 1] = ord(".")
        int_end = width - decimals - 1
    else:
        int_end = width
    iw = idig.shape[1]
    out[:, int_end - iw : int_end] = idig
    # blank the leading zeros of the integer part, then put the sign in front
    col = np.arange(iw)[None, :]
    lead = col < (iw - ilen)[:, None]
    block = out[:, int_end - iw : int_end]
    block[lead] = 0x20
    lengths = ilen + (decimals + 1 if decimals else 0) + neg
    sign_col = int_end - ilen - 1
    rows = np.flatnonzero(neg)
    out[rows, sign_col[rows]] = ord("-")
    col_ = Column(out, lengths.astype(np.int64))
    if slow.any():
        idx = np.flatnonzero(slow)
        col_ = _patch(col_, idx, ["" if v != v else f"{v:.{decimals}f}" for v in x[idx].tolist()])
    return col_


def integers(v: NDArray[np.integer]) -> Column:
    """``str(int(v))`` for every value."""
    v = np.asarray(v, dtype=np.int64)
    neg = v < 0
    dig, ndig = _uint_digits(np.abs(v), 1)
    w = dig.shape[1] + 1
    out = np.full((len(v), w), 0x20, dtype=np.uint8)
    out[:, 1:] = dig
    col = np.arange(dig.shape[1])[None, :]
    out[:, 1:][col < (dig.shape[1] - ndig)[:, None]] = 0x20
    rows = np.flatnonzero(neg)
    out[rows, (w - ndig - 1)[rows]] = ord("-")
    return Column(out, ndig + neg)


def _patch(col: Column, idx: NDArray[np.int64], cells: list[str]) -> Column:
    """``col`` with the rows ``idx`` replaced by ``cells`` (widening the matrix if needed)."""
    need = max(len(c) for c in cells)
    chars, lengths = col.chars, col.lengths.copy()
    w = max(need, chars.shape[1])
    if w > chars.shape[1]:
        wider = np.full((len(chars), w), 0x20, dtype=np.uint8)
        wider[:, w - chars.shape[1] :] = chars
        chars = wider
    else:
        chars = chars.copy()
    block = "".join(c.rjust(w) for c in cells).encode("ascii")
    chars[idx] = np.frombuffer(block, dtype=np.uint8).reshape(len(cells), w)
    lengths[idx] = [len(c) for c in cells]
    return Column(chars, lengths)


def rows(fields: Sequence[Column | bytes], end: bytes = b"\n") -> bytes:
    """Lines made of the fields side by side (a ``bytes`` field is the same text on every row), each
    cell taken at its own length, the line closed by ``end``: one buffer for all rows."""
    n = next(len(f.lengths) for f in fields if isinstance(f, Column))
    mats: list[NDArray[np.uint8]] = []
    keeps: list[NDArray[np.bool_]] = []
    for f in (*fields, end):
        if isinstance(f, Column):
            w = f.chars.shape[1]
            if w:
                mats.append(f.chars)
                # a cell is right-aligned in its column: keep its own characters, drop the padding
                keeps.append(np.arange(w)[None, :] >= (w - f.lengths)[:, None])
        elif f:
            lit = np.frombuffer(f, dtype=np.uint8)
            mats.append(np.broadcast_to(lit, (n, len(lit))))
            keeps.append(np.ones((n, len(lit)), dtype=bool))
    # all cells side by side at full width, then the padding dropped row by row in one pass
    return np.hstack(mats)[np.hstack(keeps)].tobytes()
