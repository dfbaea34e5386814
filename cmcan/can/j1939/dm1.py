"""DM1, active diagnostic trouble codes (SAE J1939-73, PGN 65226): the message's bytes.

Layout (bytes numbered from 1, bits from 1 = least significant):
- byte 1: lamp status, 2 bits each: bits 8-7 malfunction indicator lamp, 6-5 red stop lamp,
  4-3 amber warning lamp, 2-1 protect lamp (00 off, 01 on);
- byte 2: the lamps' flash states in the same places (11: do not flash; cmcan never flashes);
- then 4 bytes per DTC: SPN bits 8-1, SPN bits 16-9, (SPN bits 19-17 in bits 8-6 | FMI in bits
  5-1), (conversion method in bit 8 = 0 | occurrence count in bits 7-1).
With no active DTC the message carries one all-zero DTC. The message is at least 8 bytes, padded
with 0xFF; with more than one DTC it is longer than 8 bytes and goes over the transport protocol.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

PGN_DM1 = 65226
DM1_PRIORITY = 6
SPN_MAX = (1 << 19) - 1
PROPRIETARY_SPNS = range(520192, 524288)  # SPNs a manufacturer assigns (J1939-71)
OC_MAX = 126  # 127 means "not available"
OC_NOT_AVAILABLE = 127
NO_FLASH = 0xFF


class Fmi(IntEnum):
    """Failure mode identifiers cmcan uses (J1939-73)."""

    DATA_ERRATIC = 2
    ABNORMAL_UPDATE_RATE = 9
    BAD_DEVICE = 12
    ABOVE_NORMAL_LEAST = 15
    ABOVE_NORMAL_MODERATE = 16
    BELOW_NORMAL_LEAST = 17
    BELOW_NORMAL_MODERATE = 18


class Lamp(IntEnum):
    OFF = 0
    ON = 1


@dataclass(frozen=True, order=True)
class Dtc:
    spn: int
    fmi: int
    occurrence: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.spn <= SPN_MAX:
            raise ValueError(f"SPN must be 0..{SPN_MAX}, got {self.spn}")
        if not 0 <= self.fmi <= 31:
            raise ValueError(f"FMI must be 0..31, got {self.fmi}")
        if not 0 <= self.occurrence <= OC_NOT_AVAILABLE:
            raise ValueError(f"occurrence count must be 0..127, got {self.occurrence}")

    @property
    def key(self) -> str:
        """The DTC's identity without its count: ``"SPN:FMI"`` (how the state file keeps counts)."""
        return f"{self.spn}:{self.fmi}"


@dataclass(frozen=True)
class Lamps:
    protect: Lamp = Lamp.OFF
    amber_warning: Lamp = Lamp.OFF
    red_stop: Lamp = Lamp.OFF
    malfunction: Lamp = Lamp.OFF

    def byte(self) -> int:
        return (self.malfunction << 6) | (self.red_stop << 4) | (self.amber_warning << 2) | self.protect

    @classmethod
    def from_byte(cls, b: int) -> Lamps:
        def on(shift: int) -> Lamp:  # 01 on; 00 off, 10 error, 11 not available all read as not on
            return Lamp.ON if (b >> shift) & 3 == 1 else Lamp.OFF

        return cls(on(0), on(2), on(4), on(6))


def encode_dtc(d: Dtc) -> bytes:
    return bytes((d.spn & 0xFF, (d.spn >> 8) & 0xFF, ((d.spn >> 16) << 5) | d.fmi, d.occurrence & 0x7F))


def decode_dtc(b: bytes) -> Dtc:
    """One DTC from its 4 bytes (conversion method 0, the only one in use since 1996)."""
    return Dtc(b[0] | (b[1] << 8) | ((b[2] >> 5) << 16), b[2] & 0x1F, b[3] & 0x7F)


def encode(lamps: Lamps, dtcs: list[Dtc]) -> bytes:
    """The DM1 payload: lamps, flash states, the DTCs (or the all-zero one), padded to 8 bytes."""
    body = b"".join(encode_dtc(d) for d in dtcs) if dtcs else b"\0\0\0\0"
    payload = bytes((lamps.byte(), NO_FLASH)) + body
    return payload.ljust(8, b"\xff")


def decode(payload: bytes) -> tuple[Lamps, list[Dtc]]:
    """Lamps and active DTCs of a DM1 payload (the all-zero DTC and 0xFF padding mean none)."""
    if len(payload) < 6:
        raise ValueError(f"a DM1 payload has at least 6 bytes, got {len(payload)}")
    dtcs = []
    for i in range(2, len(payload) - 3, 4):
        chunk = payload[i : i + 4]
        if chunk == b"\xff\xff\xff\xff" or chunk == b"\0\0\0\0":
            continue
        dtcs.append(decode_dtc(chunk))
    return Lamps.from_byte(payload[0]), dtcs
