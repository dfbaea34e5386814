"""python-can's MF4 support, imported when a log is an MF4 and not before.

python-can imports its MF4 reader at ``import can``, and the reader imports asammdf (and with it
pandas): 1.1-1.4 s of every process that touches python-can or cantools, though only an ``.mf4`` log
needs it. :func:`defer` (the command line calls it before anything imports python-can) makes that
first import find no asammdf, so python-can loads with its MF4 support switched off, as it does where
asammdf is not installed. :func:`enable` turns it on for a log that is an MF4: python-can's MF4
module is executed again, now with asammdf; its classes look asammdf up in the module's globals, so
the reader python-can's ``LogReader`` already holds works from then on.
"""

from __future__ import annotations

import importlib
import logging
import sys

_DEFERRED = "asammdf"


def defer() -> None:
    """Before python-can is imported: its MF4 support off until :func:`enable` (nothing if python-can
    or asammdf is already imported: what is loaded stays)."""
    if "can" in sys.modules or _DEFERRED in sys.modules:
        return
    sys.modules[_DEFERRED] = None  # type: ignore[assignment]  # "import asammdf" raises ImportError


def enable() -> None:
    """python-can's MF4 support on (asammdf imported), where asammdf is installed."""
    if _DEFERRED in sys.modules and sys.modules[_DEFERRED] is None:
        del sys.modules[_DEFERRED]
    mf4 = sys.modules.get("can.io.mf4")
    if mf4 is not None and getattr(mf4, "asammdf", None) is None:
        logger = logging.getLogger("asammdf")
        level = logger.level  # the command line's (asammdf sets its own when imported)
        importlib.reload(mf4)
        logger.setLevel(level)
