"""Message checksums a sender puts in a frame and a receiver checks: the algorithms cmcan knows.

- ``crc8_sae_j1850``: CRC-8/SAE-J1850 (polynomial 0x1D, initial value 0xFF, not reflected, final XOR
  0xFF; the CRC of b"123456789" is 0x4B) over the payload's bytes other than the checksum's, in
  order. The checksum signal fills one whole byte.
- ``j1939_tsc1``: the message checksum of J1939-71's TSC1 (SPN 4207) and messages built like it, with
  the message counter (SPN 4206) in bits 1-4 and the checksum in bits 5-8 of byte 8 of an 8-byte
  message: ``s = byte1 + ... + byte7 + (counter & 0x0F) + the four bytes of the 29-bit identifier``,
  ``checksum = (((s >> 6) & 3) + (s >> 3) + s) & 7``. The identifier includes the sender's source
  address, so the checksum also tells a frame from another sender.

``verifier`` compiles the check for one message (the monitor's per-frame path), ``seal`` writes the
checksum into many frames at once (the simulator). Tests check the CRC against the ``crc`` package.
On a J1939 message a checksum that does not match with all its bits set (a TSC1 nibble 0xF, which no
fold gives) is J1939's "not available": the input health skips the check there and counts it
(:mod:`cmcan.monitor.health`, rule 2a).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from cmcan.can.codec import Layout

ALGORITHMS = ("crc8_sae_j1850", "j1939_tsc1")


def _crc8_table(poly: int) -> list[int]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = ((c << 1) ^ poly) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table.append(c)
    return table


CRC8_J1850_TABLE = _crc8_table(0x1D)
_CRC8_NP = np.array(CRC8_J1850_TABLE, dtype=np.uint8)


def crc8_sae_j1850(data: bytes) -> int:
    crc = 0xFF
    t = CRC8_J1850_TABLE
    for b in data:
        crc = t[crc ^ b]
    return crc ^ 0xFF


def whole_byte(lay: Layout, nbytes: int) -> int | None:
    """The index of the one byte a signal fills exactly, or None."""
    if lay.length != 8 or lay.shift % 8:
        return None
    return (nbytes - 1 - lay.shift // 8) if lay.big_endian else lay.shift // 8


def problem(algorithm: str, length: int, checksum: Layout, counter: Layout | None) -> str | None:
    """None when the algorithm can check a message laid out so, else why not."""
    if algorithm == "crc8_sae_j1850":
        if whole_byte(checksum, max(8, length)) is None:
            return f"checksum signal {checksum.name} must fill one whole byte for crc8_sae_j1850"
        return None
    if algorithm == "j1939_tsc1":
        if length != 8:
            return "j1939_tsc1 needs an 8-byte message"
        if checksum.big_endian or (checksum.shift, checksum.length) != (60, 4):
            return f"j1939_tsc1 needs the checksum {checksum.name} in bits 5-8 of byte 8 (start bit 60, 4 bits)"
        if counter is None or counter.big_endian or (counter.shift, counter.length) != (56, 4):
            return "j1939_tsc1 needs the message counter in bits 1-4 of byte 8 (start bit 56, 4 bits)"
        return None
    return f"unknown checksum algorithm {algorithm!r}; known: {', '.join(ALGORITHMS)}"


# The TSC1 fold of every sum a frame can give (7 bytes, a 4-bit counter, 4 identifier bytes).
TSC1_FOLD = [(((s >> 6) & 3) + (s >> 3) + s) & 7 for s in range(11 * 255 + 16)]


def id_sum(can_id: int) -> int:
    """The four bytes of a 29-bit identifier summed (the identifier's share of the TSC1 checksum)."""
    return (can_id & 0xFF) + ((can_id >> 8) & 0xFF) + ((can_id >> 16) & 0xFF) + ((can_id >> 24) & 0xFF)


def _tsc1(can_id: int, data: bytes) -> int:
    s = sum(data[:7]) + (data[7] & 0x0F)
    s += (can_id & 0xFF) + ((can_id >> 8) & 0xFF) + ((can_id >> 16) & 0xFF) + ((can_id >> 24) & 0xFF)
    return (((s >> 6) & 3) + (s >> 3) + s) & 7


def verifier(algorithm: str, length: int, checksum: Layout) -> Callable[[int, bytes], bool]:
    """``check(can_id, data) -> bool`` for one message (``problem`` must have said None)."""
    if algorithm == "j1939_tsc1":
        fold = TSC1_FOLD

        def check_tsc1(can_id: int, data: bytes) -> bool:
            if len(data) != 8:  # the 8-byte message: shorter is no TSC1 frame, bytes beyond it are padding
                if len(data) < 8:
                    return False
                data = data[:8]
            c = data[7]  # bytes 1-7, the counter and the identifier: _tsc1 without a slice
            return c >> 4 == fold[sum(data) - (c & 0xF0) + id_sum(can_id)]

        return check_tsc1
    nbytes = max(8, length)
    at = whole_byte(checksum, nbytes)
    assert at is not None
    table = CRC8_J1850_TABLE

    def check_crc8(can_id: int, data: bytes) -> bool:
        if len(data) <= at:
            return False
        crc = 0xFF
        for i, b in enumerate(data[:length]):
            if i != at:
                crc = table[crc ^ b]
        return data[at] == crc ^ 0xFF

    return check_crc8


def crc8_ok(length: int, checksum: Layout, data: NDArray[np.uint8]) -> NDArray[np.bool_] | None:
    """Whether each frame's CRC-8/SAE-J1850 holds, for rows of ``data`` (n, >= ``length``) of frames
    at least ``length`` bytes long: what the ``verifier`` says of each, a byte column at a time. None
    where that verifier reads bytes beyond ``length`` (a checksum byte outside the message)."""
    at = whole_byte(checksum, max(8, length))
    if at is None or at >= length or data.shape[1] < length:
        return None
    return data[:, at] == _crc8_columns(data, length, at)


def _crc8_columns(data: NDArray[np.uint8], length: int, at: int) -> NDArray[np.uint8]:
    """The CRC-8/SAE-J1850 of each row's first ``length`` bytes but the one at ``at``, a byte column
    at a time (what ``crc8_sae_j1850`` gives for each row)."""
    crc = np.full(len(data), 0xFF, dtype=np.uint8)
    for i in range(length):
        if i != at:
            crc = _CRC8_NP[crc ^ data[:, i]]
    return crc ^ 0xFF


def seal(
    algorithm: str, length: int, checksum: Layout, can_id: NDArray[np.int64], data: NDArray[np.uint8]
) -> NDArray[np.uint8]:
    """Frames ``data`` (n, >= length) with the checksum of each written in (counters already set)."""
    out = data.copy()
    if algorithm == "j1939_tsc1":
        ids = np.asarray(can_id, dtype=np.int64)
        s = out[:, :7].astype(np.int64).sum(axis=1) + (out[:, 7] & 0x0F)
        s += (ids & 0xFF) + ((ids >> 8) & 0xFF) + ((ids >> 16) & 0xFF) + ((ids >> 24) & 0xFF)
        cs = (((s >> 6) & 3) + (s >> 3) + s) & 7
        out[:, 7] = (out[:, 7] & 0x0F) | (cs << 4).astype(np.uint8)
        return out
    if algorithm == "crc8_sae_j1850":
        at = whole_byte(checksum, max(8, length))
        assert at is not None
        out[:, at] = _crc8_columns(out, length, at)
        return out
    raise ValueError(f"unknown checksum algorithm {algorithm!r}")


_LANES = np.uint64(0x00FF_00FF_00FF_00FF)
_FOLD16 = np.uint64(0x0001_0001_0001_0001)


def byte_sums(words: NDArray[np.unsignedinteger], mask: int | None = None) -> NDArray[np.uint64]:
    """The sum of the bytes of each (up to 64-bit) word, ``mask`` applied first, in a few array passes
    instead of a reduction over rows of 8 bytes: pairs of bytes added into four 16-bit lanes, the
    lanes added by one multiplication into the top lane (at most 8 x 255 = 2040, no carry out of a
    lane). Two arrays are made; the rest is done in place."""
    w = words.astype(np.uint64) if mask is None else words & np.uint64(mask)
    hi = w >> np.uint64(8)
    hi &= _LANES
    w &= _LANES
    w += hi
    w *= _FOLD16
    w >>= np.uint64(48)
    return w
