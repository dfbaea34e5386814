"""Units of DBC signals against the units of the roles they are mapped to.

A configuration maps a role (``high_pressure_bar``: a pressure in bar) onto a DBC signal and may give a
``scale`` (and ``offset``) that converts the signal's physical value into the role's unit. When the
DBC names a unit this module knows, the mapping is checked: a signal of another dimension (a
temperature mapped to a speed) is wrong whatever the scale, and a signal of the right dimension
needs the conversion's scale (kPa to bar: 0.01), give or take a trim (:data:`MAX_TRIM`). A unit it
does not know (``%``, ``count``, a vendor's spelling) or no unit at all is not judged. Pure: strings
and numbers in, a verdict out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# A scale within this factor of the conversion's is the conversion with a calibration trim on top;
# further off, the conversion was forgotten, doubled or is another one (kPa read as bar is 100x, a
# resolution written twice 2x, psi as bar 14.5x, rev/s as rpm 60x). A signal already in the role's
# unit needs a scale of 1, trimmed at most as much: a pressure, temperature, displacement or flow
# scaled by 0.01 or 2 is a resolution applied twice, not a property of the machine.
MAX_TRIM = 1.25
# Except speeds: a speed sensor on another shaft reads the pump's or motor's speed through a gear
# ratio, which cannot be told from a mistake: between speed units that need no conversion (rpm and
# 1/min), any scale is the machine's.
FREE_SCALE = frozenset({"speed"})
# An offset within this share of the conversion's (at least 0.01 of the unit) is the conversion
# rounded as people write it (degF: scale 0.5556, offset -17.78).
OFFSET_RTOL = 0.01

# Each dimension's unit spellings (as :func:`normalize` leaves them) -> (scale, offset) into the
# dimension's base unit, which is the unit the roles use (cmcan.roles.UNITS): value_base = value *
# scale + offset.
_PSI_BAR = 0.06894757293168  # 1 lbf/in2 = 6894.757293168 Pa
_IN3_CC = 16.387064  # 1 in3 = 16.387064 cm3 (exact)
_GAL_L = 3.785411784  # 1 US gallon = 3.785411784 l (exact)
_DIMENSIONS: dict[str, dict[str, tuple[float, float]]] = {
    "speed": {  # base: rpm
        **dict.fromkeys(("rpm", "1/min", "/min", "min-1", "r/min", "rev/min", "revs/min", "u/min", "tr/min"), (1, 0)),
        **dict.fromkeys(("rps", "r/s", "rev/s", "1/s", "/s", "s-1"), (60.0, 0)),
        "rad/s": (60.0 / (2.0 * math.pi), 0),
    },
    "displacement": {  # base: cm3/rev
        **dict.fromkeys(
            ("cc", "cm3", "ccm", "ml", "cc/rev", "cm3/rev", "ccm/rev", "ml/rev", "cc/r", "cm3/r", "ml/r", "cm3/u"),
            (1, 0),
        ),
        **dict.fromkeys(("in3", "in3/rev", "cuin", "cu.in", "cuin/rev", "cu.in/rev"), (_IN3_CC, 0)),
        **dict.fromkeys(("l/rev", "dm3/rev"), (1000.0, 0)),
    },
    "pressure": {  # base: bar
        **dict.fromkeys(("bar", "bara", "barg", "bar(a)", "bar(g)", "bar_a", "bar_g"), (1, 0)),
        "mbar": (1e-3, 0),
        "pa": (1e-5, 0),
        "hpa": (1e-3, 0),
        "kpa": (1e-2, 0),
        "mpa": (10.0, 0),  # after lower-casing: MPa (no drive reports millipascal)
        **dict.fromkeys(("psi", "psia", "psig", "lbf/in2", "lb/in2"), (_PSI_BAR, 0)),
    },
    "temperature": {  # base: degC
        **dict.fromkeys(("degc", "°c", "c", "celsius", "degreec", "degreesc", "deg_c", "cel"), (1, 0)),
        **dict.fromkeys(("k", "kelvin"), (1, -273.15)),
        **dict.fromkeys(("degf", "°f", "fahrenheit", "deg_f"), (5.0 / 9.0, -32.0 * 5.0 / 9.0)),
    },
    "flow": {  # base: l/min
        **dict.fromkeys(("l/min", "lpm", "ltr/min", "dm3/min", "l/mn"), (1, 0)),
        **dict.fromkeys(("l/h", "lph", "dm3/h"), (1.0 / 60.0, 0)),
        **dict.fromkeys(("l/s", "dm3/s"), (60.0, 0)),
        **dict.fromkeys(("ml/min", "cm3/min", "cc/min"), (1e-3, 0)),
        **dict.fromkeys(("ml/s", "cm3/s", "cc/s"), (0.06, 0)),
        "m3/h": (1000.0 / 60.0, 0),
        **dict.fromkeys(("gpm", "usgpm", "gal/min"), (_GAL_L, 0)),
    },
}
# A dimension's name as a message says it.
_ARTICLE = {
    "speed": "a speed",
    "displacement": "a displacement",
    "pressure": "a pressure",
    "temperature": "a temperature",
    "flow": "a flow",
}


@dataclass(frozen=True)
class Unit:
    """A recognized unit: its dimension and the conversion into the dimension's base unit."""

    text: str  # as written
    dimension: str
    scale: float
    offset: float


_TABLE: dict[str, tuple[str, float, float]] = {
    spelling: (dim, float(k), float(o))
    for dim, spellings in _DIMENSIONS.items()
    for spelling, (k, o) in spellings.items()
}


def normalize(text: str) -> str:
    """A unit as the table spells it: lower case, no blanks, superscripts and ``^`` written plainly
    (``cm³``, ``cm^3`` -> ``cm3``; ``min⁻¹``, ``min^-1`` -> ``min-1``; ``° C``, ``ºC`` -> ``°c``)."""
    t = text.strip().replace("Â°", "°").replace("º", "°").replace("˚", "°")
    t = t.replace("³", "3").replace("²", "2").replace("⁻¹", "-1").replace("^", "")
    return "".join(t.split()).lower()


def lookup(text: str | None) -> Unit | None:
    """The unit ``text`` names, or None when it is empty or not one this module knows."""
    if not text:
        return None
    hit = _TABLE.get(normalize(text))
    return None if hit is None else Unit(text.strip(), *hit)


@dataclass(frozen=True)
class Conversion:
    """What a signal in ``source`` needs to read as ``target`` (value_target = value * scale + offset)."""

    scale: float
    offset: float
    dimension: str = ""

    @property
    def identity(self) -> bool:
        return self.scale == 1.0 and self.offset == 0.0


def conversion(source: Unit, target: Unit) -> Conversion | None:
    """The affine map from ``source`` to ``target``; None when their dimensions differ."""
    if source.dimension != target.dimension:
        return None
    scale = source.scale / target.scale
    return Conversion(scale, (source.offset - target.offset) / target.scale, source.dimension)


@dataclass(frozen=True)
class Problem:
    """A mapping whose units do not fit: ``key`` is the configuration key at fault under
    ``signals.<role>`` ("" for the mapping itself, "scale" or "offset"), ``text`` says why."""

    key: str
    text: str


def _num(x: float) -> str:
    return f"{x:.10g}"


def check_mapping(
    role: str, role_unit: str, message: str, signal: str, dbc_unit: str | None, scale: float, offset: float
) -> Problem | None:
    """None when role ``role`` (in ``role_unit``) may read ``message.signal`` (in ``dbc_unit``) with
    this ``scale`` and ``offset``, or when either unit is not recognized (not judged). A scale may
    flip the sign (a direction convention): only its magnitude must be the conversion's. The offset
    is judged only where the conversion itself has one (kelvin, Fahrenheit); elsewhere an offset is
    the machine's business (a gauge against an absolute pressure, a sensor's zero)."""
    target, source = lookup(role_unit), lookup(dbc_unit)
    if target is None or source is None:
        return None
    where = f"{message}.{signal}"
    conv = conversion(source, target)
    if conv is None:
        return Problem(
            "",
            f"{where} is in {source.text} ({_ARTICLE[source.dimension]}) but {role} is {_ARTICLE[target.dimension]} "
            f"in {target.text}: map a {target.dimension} signal",
        )
    needs = f"{source.text} to {target.text} needs scale: {_num(conv.scale)}"
    if conv.offset != 0.0:
        needs += f" and offset: {_num(conv.offset)}"
    if not scale_fits(scale, conv):
        if conv.identity:
            return Problem(
                "scale",
                f"{where} is in {source.text}, as {role} is: it needs no scale (1, within a trim of "
                f"{MAX_TRIM:g}x), got scale {_num(scale)}; the DBC's scale already gives {source.text}",
            )
        return Problem(
            "scale", f"{where} is in {source.text}, {role} in {target.text}: {needs}, got scale {_num(scale)}"
        )
    if conv.offset != 0.0 and abs(offset - conv.offset) > OFFSET_RTOL * max(1.0, abs(conv.offset)):
        return Problem(
            "offset", f"{where} is in {source.text}, {role} in {target.text}: {needs}, got offset {_num(offset)}"
        )
    return None


def scale_fits(scale: float, conv: Conversion) -> bool:
    """A configured scale (either sign: a direction convention) for a signal that needs ``conv``:
    within :data:`MAX_TRIM` of its scale; any scale between speed units that need no conversion
    (:data:`FREE_SCALE`: a gear ratio)."""
    if conv.identity and conv.dimension in FREE_SCALE:
        return True
    return scale != 0.0 and 1.0 / MAX_TRIM <= abs(scale) / conv.scale <= MAX_TRIM


def judged(role_unit: str, dbc_unit: str | None) -> bool:
    """Whether :func:`check_mapping` judges a mapping between these units (both recognized)."""
    return lookup(role_unit) is not None and lookup(dbc_unit) is not None
