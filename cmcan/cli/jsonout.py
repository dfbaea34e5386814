"""JSON on standard output, as strict parsers read it: a number that is not finite (a figure with no
points behind it) is ``null``, never the ``NaN`` or ``Infinity`` Python's json module writes."""

from __future__ import annotations

import json
import math
import sys
from typing import Any


def finite(obj: Any) -> Any:
    """``obj`` with every non-finite float (also inside dicts, lists and tuples) made None."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [finite(v) for v in obj]
    return obj


def print_json(obj: Any) -> None:
    """``obj`` as indented JSON and a newline on stdout; non-finite numbers as null."""
    json.dump(finite(obj), sys.stdout, indent=2, allow_nan=False)
    sys.stdout.write("\n")
