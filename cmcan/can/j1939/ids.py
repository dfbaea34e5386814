"""J1939 identifiers (SAE J1939-21): the fields of a 29-bit identifier and the PGN arithmetic.

A 29-bit identifier is priority (3 bits), extended data page (1), data page (1), PDU format PF (8),
PDU specific PS (8) and the sender's source address SA (8). The parameter group number (PGN) is
EDP, DP, PF and PS when PF >= 240 (PDU2, broadcast: PS is a group extension); when PF < 240 (PDU1)
PS is the destination address and not part of the PGN. A receiver matches a parameter group on its
PGN, never on the whole identifier: the priority may be changed by the network designer and the
source address is whatever the sender claimed.

Plain integer arithmetic that works on Python ints and numpy integer arrays alike, so the monitor's
matching and a batched reader share it; tests check it against ``cantools.j1939``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

PDU2_MIN_PF = 240  # PF from here on: PDU2 (broadcast, PS is a group extension)
GLOBAL_ADDRESS = 0xFF  # destination "all"
NULL_ADDRESS = 0xFE  # the source address of a node that could not claim one
MAX_UNICAST_ADDRESS = 0xFD
MAX_PGN = 0x3FFFF
MAX_ID = 0x1FFFFFFF
DEFAULT_PRIORITY = 6


def priority(can_id: Any) -> Any:
    return (can_id >> 26) & 0x7


def source_address(can_id: Any) -> Any:
    return can_id & 0xFF


def pdu_format(can_id: Any) -> Any:
    return (can_id >> 16) & 0xFF


def pdu_specific(can_id: Any) -> Any:
    return (can_id >> 8) & 0xFF


def is_pdu1(pgn_or_pf: int, is_pf: bool = False) -> bool:
    """True for a PDU1 (destination-specific) PGN, or PDU format when ``is_pf``."""
    pf = pgn_or_pf if is_pf else (pgn_or_pf >> 8) & 0xFF
    return pf < PDU2_MIN_PF


def pgn(can_id: Any) -> Any:
    """The PGN of a 29-bit identifier (ints or numpy integer arrays)."""
    p = (can_id >> 8) & MAX_PGN
    if isinstance(p, np.ndarray):
        return np.where(((p >> 8) & 0xFF) < PDU2_MIN_PF, p & 0x3FF00, p)
    return p & 0x3FF00 if ((p >> 8) & 0xFF) < PDU2_MIN_PF else p


def destination(can_id: int) -> int:
    """The destination address of a PDU1 identifier; GLOBAL_ADDRESS for PDU2 (broadcast)."""
    return pdu_specific(can_id) if pdu_format(can_id) < PDU2_MIN_PF else GLOBAL_ADDRESS


def make_id(prio: int, pgn_: int, source: int, dest: int = GLOBAL_ADDRESS) -> int:
    """The 29-bit identifier of a parameter group sent by ``source`` (to ``dest`` for a PDU1 PGN)."""
    if not 0 <= prio <= 7:
        raise ValueError(f"J1939 priority must be 0..7, got {prio}")
    if not 0 <= pgn_ <= MAX_PGN:
        raise ValueError(f"PGN must be 0..{MAX_PGN}, got {pgn_}")
    if not 0 <= source <= 0xFF or not 0 <= dest <= 0xFF:
        raise ValueError(f"addresses must be 0..255, got source {source}, destination {dest}")
    if is_pdu1(pgn_):
        if pgn_ & 0xFF:
            raise ValueError(f"PGN {pgn_} is PDU1 (PF < 240): its low byte must be 0, the destination goes there")
        pgn_ |= dest
    return (prio << 26) | (pgn_ << 8) | source


def with_source(can_id: Any, source: int) -> Any:
    """The same identifier sent from another source address."""
    return (can_id & ~0xFF & MAX_ID) | source
