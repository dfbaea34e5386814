"""Vectorized encoding and decoding of many frames of one DBC message at once.

The simulator writes millions of frames and training reads them back; cantools encodes one frame at
a time (about 10 us each). For little-endian (Intel) signals the bit layout is a shift and a mask of
one 64-bit word, done here over whole arrays from cantools' own signal definitions. Big-endian or
multiplexed messages go through cantools frame by frame. Tests check both paths agree with cantools.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import numpy as np
from cantools.database.can import Message
from numpy.typing import NDArray


def _vectorizable(msg: Message) -> bool:
    return (
        not msg.is_multiplexed()
        and msg.length <= 8
        and all(s.byte_order == "little_endian" and not s.is_float for s in msg.signals)
    )


def quantize(msg: Message, name: str, phys: NDArray[np.float64]) -> NDArray[np.float64]:
    """Physical values as the signal carries them: clipped to its range, rounded to its resolution."""
    sig = msg.get_signal_by_name(name)
    lo = sig.minimum if sig.minimum is not None else -np.inf
    hi = sig.maximum if sig.maximum is not None else np.inf
    raw = np.round((np.clip(phys, lo, hi) - sig.offset) / sig.scale)
    return raw * sig.scale + sig.offset


def encode(msg: Message, values: Mapping[str, NDArray[np.float64]]) -> NDArray[np.uint8]:
    """Frames (n, msg.length) of ``msg`` with each signal's physical values; missing signals are 0.

    Values are clipped to the signal's range first (a saturated sensor), so encoding never fails.
    """
    n = len(next(iter(values.values()))) if values else 0
    if not _vectorizable(msg):
        return _encode_cantools(msg, values, n)
    word = np.zeros(n, dtype=np.uint64)
    for sig in msg.signals:
        if sig.name not in values:
            continue
        q = quantize(msg, sig.name, np.asarray(values[sig.name], dtype=float))
        raw = np.round((q - sig.offset) / sig.scale).astype(np.int64)
        mask = (1 << sig.length) - 1
        word |= (raw.astype(np.uint64) & np.uint64(mask)) << np.uint64(sig.start)
    return word.astype("<u8").view(np.uint8).reshape(n, 8)[:, : msg.length].copy()


def decode(msg: Message, data: NDArray[np.uint8], names: list[str] | None = None) -> dict[str, NDArray[np.float64]]:
    """Physical values of the signals ``names`` (all by default) from frames (n, >= msg.length)."""
    sigs = [s for s in msg.signals if names is None or s.name in names]
    if not _vectorizable(msg):
        return _decode_cantools(msg, data, [s.name for s in sigs])
    n = data.shape[0]
    padded = np.zeros((n, 8), dtype=np.uint8)
    width = min(data.shape[1], 8)
    padded[:, :width] = data[:, :width]
    word = padded.view("<u8").reshape(n)
    out = {}
    for sig in sigs:
        raw = ((word >> np.uint64(sig.start)) & np.uint64((1 << sig.length) - 1)).astype(np.int64)
        if sig.is_signed:
            raw = np.where(raw >= (1 << (sig.length - 1)), raw - (1 << sig.length), raw)
        out[sig.name] = raw * sig.scale + sig.offset
    return out


def _encode_cantools(msg: Message, values: Mapping[str, NDArray[np.float64]], n: int) -> NDArray[np.uint8]:
    names = [s.name for s in msg.signals]
    cols = {k: quantize(msg, k, np.asarray(v, dtype=float)) for k, v in values.items()}
    out = np.zeros((n, msg.length), dtype=np.uint8)
    for i in range(n):
        frame = {k: (float(cols[k][i]) if k in cols else 0) for k in names}
        out[i] = np.frombuffer(msg.encode(frame, scaling=True, strict=False), dtype=np.uint8)
    return out


def _decode_cantools(msg: Message, data: NDArray[np.uint8], names: list[str]) -> dict[str, NDArray[np.float64]]:
    out = {k: np.empty(data.shape[0]) for k in names}
    for i in range(data.shape[0]):
        d = msg.decode(bytes(data[i, : msg.length]), decode_choices=False, scaling=True)
        for k in names:
            out[k][i] = float(d[k])
    return out


def compile_decoder(msg: Message, names: list[str]) -> Callable[[bytes], tuple[float, ...]]:
    """A fast decoder of the signals ``names`` of one frame (the monitor's per-frame path).

    Little-endian integer signals become shifts and masks of one integer; anything else goes through
    cantools. Returns physical values in the order of ``names``.
    """
    sigs = [msg.get_signal_by_name(n) for n in names]
    if not _vectorizable(msg):

        def slow(data: bytes) -> tuple[float, ...]:
            d = msg.decode(bytes(data[: msg.length]).ljust(msg.length, b"\0"), decode_choices=False)
            return tuple(float(d[n]) for n in names)

        return slow
    specs = [
        (s.start, (1 << s.length) - 1, (1 << (s.length - 1)) if s.is_signed else 0, 1 << s.length, s.scale, s.offset)
        for s in sigs
    ]
    from_bytes = int.from_bytes

    def fast(data: bytes) -> tuple[float, ...]:
        word = from_bytes(data, "little")
        out = []
        for start, mask, sign, span, scale, offset in specs:
            raw = (word >> start) & mask
            if sign and raw & sign:
                raw -= span
            out.append(raw * scale + offset)
        return tuple(out)

    return fast


def compile_encoder(msg: Message) -> Callable[[Mapping[str, float]], bytes]:
    """A fast encoder of one frame from physical values (missing signals 0, values saturated to the
    signal's range): the monitor's output frames."""
    if not _vectorizable(msg):

        def slow(values: Mapping[str, float]) -> bytes:
            row = {}
            for s in msg.signals:
                v = float(values.get(s.name, 0.0))
                lo = s.minimum if s.minimum is not None else v
                hi = s.maximum if s.maximum is not None else v
                row[s.name] = min(max(v, lo), hi)
            return bytes(msg.encode(row, scaling=True, strict=False))

        return slow
    specs = [
        (
            s.name,
            s.start,
            (1 << s.length) - 1,
            s.scale,
            s.offset,
            s.minimum if s.minimum is not None else -math.inf,
            s.maximum if s.maximum is not None else math.inf,
        )
        for s in msg.signals
    ]
    length = msg.length

    def fast(values: Mapping[str, float]) -> bytes:
        word = 0
        for name, start, mask, scale, offset, lo, hi in specs:
            v = values.get(name)
            if v is None:
                continue
            v = lo if v < lo else hi if v > hi else v
            if v != v:  # NaN: encode as the range minimum rather than fail
                v = lo if lo > -math.inf else 0.0
            raw = round((v - offset) / scale)
            word |= (raw & mask) << start
        return word.to_bytes(8, "little")[:length]

    return fast


def compile_checked_decoder(
    msg: Message, names: list[str], conv: list[tuple[float, float]]
) -> Callable[[bytes], tuple[float, ...] | None]:
    """Like :func:`compile_decoder`, with each value checked against its DBC range (None when one
    is outside: an implausible frame) and converted by ``value * scale + offset`` to its role's unit.

    For little-endian signals the decoder is generated as straight-line code, as ``namedtuple``
    generates its classes: the monitor runs it for every received frame.
    """
    sigs = [msg.get_signal_by_name(n) for n in names]
    ranges = [
        (s.minimum if s.minimum is not None else -math.inf, s.maximum if s.maximum is not None else math.inf)
        for s in sigs
    ]
    if not _vectorizable(msg):
        plain = compile_decoder(msg, names)

        def slow(data: bytes) -> tuple[float, ...] | None:
            vals = plain(data)
            for v, (lo, hi) in zip(vals, ranges, strict=True):
                if not (lo <= v <= hi):
                    return None
            return tuple(v * sc + off for v, (sc, off) in zip(vals, conv, strict=True))

        return slow
    ns: dict[str, object] = {"from_bytes": int.from_bytes}
    body = ["def decode(data):", "    w = from_bytes(data, 'little')"]
    outs = []
    for i, (s, (lo, hi), (sc, off)) in enumerate(zip(sigs, ranges, conv, strict=True)):
        ns.update({f"sc{i}": s.scale, f"of{i}": s.offset, f"lo{i}": lo, f"hi{i}": hi, f"rs{i}": sc, f"ro{i}": off})
        body.append(f"    r{i} = (w >> {s.start}) & {(1 << s.length) - 1}")
        if s.is_signed:
            body.append(f"    if r{i} & {1 << (s.length - 1)}: r{i} -= {1 << s.length}")
        body.append(f"    v{i} = r{i} * sc{i} + of{i}")
        body.append(f"    if not (lo{i} <= v{i} <= hi{i}): return None")
        outs.append(f"v{i} * rs{i} + ro{i}")
    body.append(f"    return ({', '.join(outs)},)")
    exec("\n".join(body), ns)
    return ns["decode"]  # type: ignore[return-value]
