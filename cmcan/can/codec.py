"""Signal layouts of DBC messages and the one bit extractor, per frame and over arrays of frames.

cantools decodes and encodes one frame at a time (about 10 us each): too slow for a simulator that
writes millions of frames, for training that reads them back, and for the monitor's per-frame path.
Here a signal's place in a frame is a :class:`Layout` read from cantools' own definition: a shift
and a mask of one integer holding the frame, little-endian (Intel) or big-endian (Motorola).
:func:`extract` and :func:`insert` work on a Python ``int`` (one frame) and on ``numpy`` arrays of
``uint64`` (many frames) alike, so the monitor, the simulator and training share one bit extractor;
tests check it against cantools, every width from 1 to 64 bits. Integer signals only: a float signal
or a multiplexed one cannot be a cmcan input or output (``check_codable`` says so).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # hints only: importing cantools pulls in python-can and asammdf (issue 37)
    from cantools.database.can import Message


@dataclass(frozen=True)
class Layout:
    """Where a signal sits: bits ``shift .. shift+length-1`` of the frame as one integer (read
    little-endian for Intel signals, big-endian for Motorola ones), and its physical conversion."""

    name: str
    shift: int
    length: int
    signed: bool
    big_endian: bool
    scale: float
    offset: float
    minimum: float
    maximum: float

    @property
    def mask(self) -> int:
        return (1 << self.length) - 1


def check_codable(msg: Message, names: Sequence[str] | None = None) -> str | None:
    """None when the signals ``names`` of the message can be coded here, else why not (a sentence
    naming the signal). ``names`` None: the whole message, as cmcan sends an output message.

    A signal of a multiplexed message that is not multiplexed itself sits in every frame at the same
    place and is read as any other; a multiplexed one (present only for some values of the
    multiplexer switch) is not. A floating-point signal is not read either."""
    if names is None and msg.is_multiplexed():
        return f"message {msg.name} is multiplexed: cmcan sends messages whose signals are in every frame"
    for s in msg.signals:
        if names is not None and s.name not in names:
            continue
        if s.multiplexer_ids is not None:
            ids = ", ".join(str(i) for i in s.multiplexer_ids)
            return (
                f"signal {msg.name}.{s.name} is multiplexed (in a frame only when {s.multiplexer_signal} is {ids}): "
                "cmcan reads signals that are in every frame of their message; map one that is not multiplexed"
            )
        if s.is_float:
            return f"signal {msg.name}.{s.name} is a floating-point signal: cmcan reads integer signals"
    return None


def layout(msg: Message, name: str) -> Layout:
    s = msg.get_signal_by_name(name)
    nbits = 8 * frame_bytes(msg)
    if s.byte_order == "big_endian":
        # cantools gives a Motorola signal's most significant bit in DBC (sawtooth) numbering.
        msb_from_top = 8 * (s.start // 8) + (7 - s.start % 8)
        shift = nbits - msb_from_top - s.length
    else:
        shift = s.start
    return Layout(
        s.name,
        shift,
        s.length,
        bool(s.is_signed),
        s.byte_order == "big_endian",
        float(s.scale),
        float(s.offset),
        float(s.minimum) if s.minimum is not None else -math.inf,
        float(s.maximum) if s.maximum is not None else math.inf,
    )


def frame_bytes(msg: Message) -> int:
    """Bytes of the integer a frame is read as: 8 for classic CAN, the message length beyond."""
    return max(8, msg.length)


# -- the bit extractor --------------------------------------------------------------------------------


def extract(word: Any, lay: Layout) -> Any:
    """The raw (integer) value of a signal from the frame word(s): ``int`` or ``uint64`` arrays.

    Every width a DBC allows (1 to 64 bits) is read exactly. Arrays come back as ``int64``, which
    holds every signed value and every unsigned one below 2**63; an unsigned 64-bit signal's values
    reach 2**64 - 1, so its array holds Python ints (dtype ``object``), exact as the per-frame path."""
    if isinstance(word, np.ndarray):
        bits = (word.astype(np.uint64, copy=False) >> np.uint64(lay.shift)) & np.uint64(lay.mask)
        if lay.signed:  # the sign bit moved to the top and shifted back arithmetically: no Python int
            up = np.uint64(64 - lay.length)
            return (bits << up).view(np.int64) >> np.int64(64 - lay.length)
        return bits.astype(np.int64) if lay.length < 64 else bits.astype(object)
    raw = (word >> lay.shift) & lay.mask
    if lay.signed and raw >> (lay.length - 1):
        raw -= 1 << lay.length
    return raw


def fits_int64(lay: Layout) -> bool:
    """Whether every raw value of the signal fits an ``int64`` (all but unsigned 64-bit signals)."""
    return lay.signed or lay.length < 64


def insert(word: Any, raw: Any, lay: Layout) -> Any:
    """``word`` with the signal's bits set to ``raw`` (two's complement for negative values)."""
    if isinstance(word, np.ndarray):
        r = np.asarray(raw)
        if r.dtype == object:  # Python ints beyond int64 (an unsigned 64-bit signal)
            bits = np.array([int(v) & lay.mask for v in r.tolist()], dtype=np.uint64)
        else:
            bits = r.astype(np.int64).astype(np.uint64) & np.uint64(lay.mask)
        return word | (bits << np.uint64(lay.shift))
    return word | ((int(raw) & lay.mask) << lay.shift)


def _raw_limits(lay: Layout) -> tuple[float, float]:
    """The signal's raw range as floats within it (2**63 - 1 is 2**63 as a float: the next one down)."""
    lo = -(1 << (lay.length - 1)) if lay.signed else 0
    hi = (1 << (lay.length - 1)) - 1 if lay.signed else lay.mask
    hi_f = float(hi)
    if int(hi_f) > hi:
        hi_f = math.nextafter(hi_f, 0.0)
    return float(lo), hi_f


class _RawSpec(NamedTuple):
    """What :func:`to_raw` needs of a layout for one value, worked out once (the per-frame encoder
    keeps one per signal)."""

    offset: float
    scale: float
    minimum: float
    maximum: float
    raw_lo: float
    raw_hi: float
    nan_value: float  # what NaN is sent as: the range minimum, or 0 where there is none


def _raw_spec(lay: Layout) -> _RawSpec:
    lo, hi = _raw_limits(lay)
    nan_value = lay.minimum if lay.minimum > -math.inf else 0.0
    return _RawSpec(lay.offset, lay.scale, lay.minimum, lay.maximum, lo, hi, nan_value)


def _scalar_raw(spec: _RawSpec, value: Any) -> int:
    """:func:`to_raw` of one value (the arithmetic the array path does with numpy)."""
    offset, scale, vmin, vmax, lo, hi, nan_value = spec
    v = float(value)
    if v != v:
        v = nan_value
    v = vmin if v < vmin else vmax if v > vmax else v
    r = (v - offset) / scale
    return round(lo if r < lo else hi if r > hi else r)


def to_raw(lay: Layout, value: Any) -> Any:
    """Physical value -> raw, saturated to the signal's range (and to what its bits hold) and rounded
    to its resolution (half to even, like cantools). NaN becomes the range minimum (or 0): encoding
    never fails."""
    spec = _raw_spec(lay)
    if isinstance(value, np.ndarray):
        v = np.clip(np.nan_to_num(value, nan=spec.nan_value), lay.minimum, lay.maximum)
        r = np.clip(np.round((v - lay.offset) / lay.scale), spec.raw_lo, spec.raw_hi)
        if fits_int64(lay):
            return r.astype(np.int64)
        return np.array([int(x) for x in r.tolist()], dtype=object)  # beyond int64: Python ints
    return _scalar_raw(spec, value)


def quantize(msg: Message, name: str, phys: NDArray[np.float64]) -> NDArray[np.float64]:
    """Physical values as the signal carries them: clipped to its range, rounded to its resolution."""
    lay = layout(msg, name)
    return to_raw(lay, np.asarray(phys, dtype=float)) * lay.scale + lay.offset


# -- many frames (numpy) ------------------------------------------------------------------------------


def message_layouts(msg: Message, names: Sequence[str] | None = None) -> tuple[Layout, ...]:
    """Layouts of the signals ``names`` (all by default), in that order."""
    return tuple(layout(msg, n) for n in (names if names is not None else [s.name for s in msg.signals]))


def _words(data: NDArray[np.uint8], big_endian: bool) -> NDArray[np.uint64]:
    n = data.shape[0]
    padded = np.zeros((n, 8), dtype=np.uint8)
    width = min(data.shape[1], 8)
    padded[:, :width] = data[:, :width]
    return padded.view(">u8" if big_endian else "<u8").reshape(n).astype(np.uint64)


def extract_all(data: NDArray[np.uint8], lays: Sequence[Layout], size: int) -> list[NDArray[np.int64]]:
    """Raw values of each layout from frames (n, >= their length) of a message read as ``size`` bytes."""
    if size > 8:
        out = [np.empty(data.shape[0], dtype=np.int64 if fits_int64(x) else object) for x in lays]
        need_be = any(x.big_endian for x in lays)
        for i, row in enumerate(data):
            d = bytes(row[:size]).ljust(size, b"\0")
            le = int.from_bytes(d, "little")
            be = int.from_bytes(d, "big") if need_be else 0
            for o, x in zip(out, lays, strict=True):
                o[i] = extract(be if x.big_endian else le, x)
        return out
    le = _words(data, False) if any(not x.big_endian for x in lays) else None
    be = _words(data, True) if any(x.big_endian for x in lays) else None
    return [extract(be if x.big_endian else le, x) for x in lays]


def as_float(raw: NDArray[Any]) -> NDArray[np.float64]:
    """Raw values as ``float64`` (an ``object`` array of an unsigned 64-bit signal too), each the
    nearest double to its integer, as numpy converts ``int64``."""
    return raw.astype(np.float64)


def decode_raw(msg: Message, data: NDArray[np.uint8], names: Sequence[str]) -> dict[str, NDArray[np.int64]]:
    """Raw values of the signals ``names`` from frames (n, >= msg.length)."""
    return dict(zip(names, extract_all(data, message_layouts(msg, names), frame_bytes(msg)), strict=True))


def decode(msg: Message, data: NDArray[np.uint8], names: Sequence[str] | None = None) -> dict[str, NDArray[np.float64]]:
    """Physical values of the signals ``names`` (all by default) from frames (n, >= msg.length)."""
    names = [s.name for s in msg.signals] if names is None else list(names)
    raws = decode_raw(msg, data, names)
    out = {}
    for k in names:
        lay = layout(msg, k)
        out[k] = as_float(raws[k]) * lay.scale + lay.offset
    return out


def covered(msg: Message) -> bytes:
    """The message's bytes with a 1 in every bit some signal occupies."""
    size = frame_bytes(msg)
    le = be = 0
    for s in msg.signals:
        lay = layout(msg, s.name)
        if lay.big_endian:
            be = insert(be, lay.mask, lay)
        else:
            le = insert(le, lay.mask, lay)
    both = int.from_bytes(le.to_bytes(size, "little"), "big") | be
    return both.to_bytes(size, "big")[: msg.length]


def unused(msg: Message) -> bytes:
    """The message's bytes with a 1 in every bit no signal occupies (J1939 sends those as 1)."""
    return bytes(~b & 0xFF for b in covered(msg))


def encode_all(
    lays: Sequence[Layout], size: int, length: int, values: Mapping[str, NDArray[np.float64]]
) -> NDArray[np.uint8]:
    """Frames (n, length) with each signal's physical values (missing signals 0, values saturated)."""
    n = len(next(iter(values.values()))) if values else 0
    if size > 8:
        enc = frame_encoder(lays, size, length)
        rows = [enc({k: float(v[i]) for k, v in values.items()}) for i in range(n)]
        return np.frombuffer(b"".join(rows), dtype=np.uint8).reshape(n, length).copy()
    le = np.zeros(n, dtype=np.uint64)
    be = np.zeros(n, dtype=np.uint64)
    for lay in lays:
        if lay.name not in values:
            continue
        raw = to_raw(lay, np.asarray(values[lay.name], dtype=float))
        if lay.big_endian:
            be = insert(be, raw, lay)
        else:
            le = insert(le, raw, lay)
    out = le.astype("<u8").view(np.uint8).reshape(n, 8) | be.astype(">u8").view(np.uint8).reshape(n, 8)
    return out[:, :length].copy()


def encode(msg: Message, values: Mapping[str, NDArray[np.float64]], fill_unused: bool = False) -> NDArray[np.uint8]:
    """Frames (n, msg.length) of ``msg`` with each signal's physical values; missing signals are 0,
    bits of no signal 0 (1 with ``fill_unused``, as J1939 wants).

    Values are clipped to the signal's range first (a saturated sensor), so encoding never fails.
    """
    out = encode_all(message_layouts(msg), frame_bytes(msg), msg.length, values)
    if fill_unused:
        out |= np.frombuffer(unused(msg), dtype=np.uint8)[None, :]
    return out


# -- one frame (the monitor's per-frame path) ---------------------------------------------------------


def raw_decoder(lays: Sequence[Layout], size: int) -> Callable[[bytes], tuple[int, ...]]:
    """Raw values of the layouts of one frame (a message read as ``size`` bytes), in that order."""
    need_be = any(x.big_endian for x in lays)

    def decode(data: bytes) -> tuple[int, ...]:
        d = bytes(data[:size]).ljust(size, b"\0")
        le = int.from_bytes(d, "little")
        be = int.from_bytes(d, "big") if need_be else 0
        return tuple(extract(be if x.big_endian else le, x) for x in lays)

    return decode


def raw_bounds(lay: Layout) -> tuple[int, int]:
    """The raw values r whose physical value ``r * scale + offset`` (in floating point, as cantools and
    the decoder compute it) lies in the signal's range, as an interval [lo, hi] (empty when lo > hi).
    ``r * scale + offset`` is monotonic in r in floating point too, so each bound is a binary search."""
    r_min = -(1 << (lay.length - 1)) if lay.signed else 0
    r_max = (1 << (lay.length - 1)) - 1 if lay.signed else lay.mask
    if lay.scale == 0:
        ok = lay.minimum <= lay.offset <= lay.maximum
        return (r_min, r_max) if ok else (1, 0)

    def first(pred: Callable[[int], bool]) -> int:
        """The smallest r in [r_min, r_max + 1] from which ``pred`` holds (it holds from some r on)."""
        lo, hi = r_min, r_max + 1
        while lo < hi:
            mid = (lo + hi) // 2
            if pred(mid):
                hi = mid
            else:
                lo = mid + 1
        return lo

    def phys(r: int) -> float:
        return r * lay.scale + lay.offset

    if lay.scale > 0:  # in range from the first r above the minimum to the last r below the maximum
        return first(lambda r: phys(r) >= lay.minimum), first(lambda r: phys(r) > lay.maximum) - 1
    return first(lambda r: phys(r) <= lay.maximum), first(lambda r: phys(r) < lay.minimum) - 1


def checked_decoder(lays: Sequence[Layout], size: int) -> Callable[[bytes], tuple[int, ...] | None]:
    """Raw values of one frame (a message read as ``size`` bytes), or None when a value's physical
    value (raw * scale + offset) is outside its DBC range: an implausible frame. The range is checked
    on the raw value against :func:`raw_bounds` (the same verdict without floating point per frame),
    and the bits are read with :func:`extract`'s arithmetic inline: this is the monitor's per-frame
    path."""
    specs = []
    for x in lays:
        lo, hi = raw_bounds(x)
        specs.append((x.shift, x.mask, 1 << (x.length - 1) if x.signed else 0, x.big_endian, lo, hi))
    need_be = any(x.big_endian for x in lays)
    from_bytes = int.from_bytes

    def decode(data: bytes) -> tuple[int, ...] | None:
        if len(data) != size:
            data = bytes(data[:size]).ljust(size, b"\0")
        le = from_bytes(data, "little")
        be = from_bytes(data, "big") if need_be else 0
        out = []
        for shift, mask, sign, big, lo, hi in specs:
            raw = ((be if big else le) >> shift) & mask
            if raw & sign:
                raw -= sign << 1
            if not lo <= raw <= hi:
                return None
            out.append(raw)
        return tuple(out)

    return decode


def frame_encoder(
    lays: Sequence[Layout], size: int, length: int, fill: int = 0
) -> Callable[[Mapping[str, float]], bytes]:
    """One frame from physical values; ``fill`` (the frame as a big-endian integer) ORed in. Each
    signal's limits are worked out here once: this is the daemon's per-tick path."""
    specs = [(lay.name, lay.big_endian, lay.mask, lay.shift, _raw_spec(lay)) for lay in lays]

    def encode(values: Mapping[str, float]) -> bytes:
        le = be = 0
        for name, big, mask, shift, spec in specs:
            v = values.get(name)
            if v is None:
                continue
            bits = (_scalar_raw(spec, v) & mask) << shift  # as insert() puts it
            if big:
                be |= bits
            else:
                le |= bits
        both = int.from_bytes(le.to_bytes(size, "little"), "big") | be | fill
        return both.to_bytes(size, "big")[:length]

    return encode
