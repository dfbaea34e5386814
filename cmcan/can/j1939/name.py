"""The J1939 NAME (SAE J1939-81): a controller application's 64-bit identity on the bus.

Bits, least significant first (as sent in the Address Claimed message's 8 data bytes, little endian):

| bits | field |
|---|---|
| 0-20 | identity number (21 bits): unique among the manufacturer's units, e.g. from a serial number |
| 21-31 | manufacturer code (11 bits), assigned by SAE |
| 32-34 | ECU instance (3 bits) |
| 35-39 | function instance (5 bits): the first, second, ... controller of one function |
| 40-47 | function (8 bits): 0-127 the same in every industry, 128-254 per industry group and vehicle system |
| 48 | reserved (0) |
| 49-55 | vehicle system (7 bits) |
| 56-59 | vehicle system instance (4 bits) |
| 60-62 | industry group (3 bits): 0 global, 1 on-highway, 2 agriculture, 3 construction, 4 marine, 5 industrial |
| 63 | arbitrary address capable (1 bit): the node can move to another address when it loses its own |

In an address-claim contention the NAME with the lower value wins (J1939-81), so the arbitrary-address
bit, the most significant, makes a self-configurable node yield to a fixed-address one.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

# (field, bit offset, width)
LAYOUT = (
    ("identity_number", 0, 21),
    ("manufacturer_code", 21, 11),
    ("ecu_instance", 32, 3),
    ("function_instance", 35, 5),
    ("function", 40, 8),
    ("vehicle_system", 49, 7),
    ("vehicle_system_instance", 56, 4),
    ("industry_group", 60, 3),
    ("arbitrary_address_capable", 63, 1),
)
WIDTHS = {name: width for name, _, width in LAYOUT}


@dataclass(frozen=True, order=False)
class Name:
    identity_number: int
    manufacturer_code: int
    function: int
    industry_group: int = 0
    arbitrary_address_capable: bool = False
    ecu_instance: int = 0
    function_instance: int = 0
    vehicle_system: int = 0
    vehicle_system_instance: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = int(getattr(self, f.name))
            if not 0 <= v < 1 << WIDTHS[f.name]:
                raise ValueError(f"NAME field {f.name} must be 0..{(1 << WIDTHS[f.name]) - 1}, got {v}")

    @property
    def value(self) -> int:
        """The 64-bit NAME (the lower wins an address-claim contention)."""
        return sum(int(getattr(self, field)) << shift for field, shift, _ in LAYOUT)

    def to_bytes(self) -> bytes:
        """The Address Claimed message's data: the NAME, least significant byte first."""
        return self.value.to_bytes(8, "little")

    @classmethod
    def from_value(cls, value: int) -> Name:
        if not 0 <= value < 1 << 64:
            raise ValueError(f"a NAME is a 64-bit value, got {value}")
        if value >> 48 & 1:
            value &= ~(1 << 48)  # the reserved bit: not part of any field (read as 0)
        kw: dict[str, Any] = {f: (value >> s) & ((1 << w) - 1) for f, s, w in LAYOUT}
        kw["arbitrary_address_capable"] = bool(kw["arbitrary_address_capable"])
        return cls(**kw)

    @classmethod
    def from_bytes(cls, data: bytes) -> Name:
        if len(data) != 8:
            raise ValueError(f"a NAME is 8 bytes, got {len(data)}")
        return cls.from_value(int.from_bytes(data, "little"))

    def hex(self) -> str:
        return f"0x{self.value:016X}"


def name_hex(value: int) -> str:
    """A NAME value as people read it: 16 hex digits."""
    return f"0x{value:016X}"
