"""J1939-71's reserved values of a parameter: "not available" and "error" are not measurements.

A J1939 parameter sent in whole bytes keeps the top of its raw range for indicators (J1939-71,
"parameter ranges"): with n >= 8 bits and the top byte b of the raw value,

- b <= 0xFA: a valid signal;
- 0xFB <= b <= 0xFD: a parameter-specific indicator (reserved): no measurement either;
- b == 0xFE: the error indicator (the sender knows its value is wrong);
- b == 0xFF: not available (the sender does not have the parameter, or does not send it now).

A discrete parameter of 2 to 7 bits keeps its two top codes: all ones is not available, all ones
less one is the error indicator (for 2 bits: 11b and 10b). A 1-bit parameter has no reserved code.
Only unsigned parameters carry the indicators (J1939 has no signed raw values; a signed DBC signal on
a J1939 message is read as it is).

:func:`classify` says it of one raw value, :func:`classify_columns` of many.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

VALID, NOT_AVAILABLE, ERROR = 0, 1, 2


def thresholds(length: int, signed: bool) -> tuple[int, int, int] | None:
    """(first reserved raw value, the first error code, the first not-available code) of an n-bit
    parameter; None when it has no reserved codes."""
    if signed or length < 2:
        return None
    if length < 8:
        top = (1 << length) - 1
        return top - 1, top - 1, top
    shift = length - 8
    return 0xFB << shift, 0xFE << shift, 0xFF << shift


def classify(raw: int, t: tuple[int, int, int]) -> int:
    """VALID, ERROR or NOT_AVAILABLE (a reserved indicator counts as not available)."""
    reserved, error, na = t
    if raw < reserved:
        return VALID
    if error <= raw < na:
        return ERROR
    return NOT_AVAILABLE


def classify_columns(raw: NDArray[np.generic], t: tuple[int, int, int]) -> NDArray[np.int8]:
    reserved, error, na = t
    out = np.zeros(len(raw), dtype=np.int8)
    out[raw >= reserved] = NOT_AVAILABLE
    out[(raw >= error) & (raw < na)] = ERROR
    return out
