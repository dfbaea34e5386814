"""The vcan tests: run here where vcan0 exists, otherwise inside the throwaway VM.

Where this kernel has CAN (a developer's Linux machine, a gateway, the VM itself), the real tests of
``cases.py`` are collected from this module. Elsewhere each is replaced by a stand-in of the same
name that boots the VM once (the session fixture ``vm_run``), runs the real tests inside on vcan0,
and passes, fails or skips as its twin did in there.
"""

from __future__ import annotations

import pytest

from tests.vcan import cases
from tests.vcan.support import vcan_here

NAMES = [n for n, f in vars(cases).items() if n.startswith("test_") and callable(f)]

if vcan_here():
    from tests.vcan.cases import *  # noqa: F403 - the real tests and their fixtures
else:

    def _stand_in(name: str):
        @pytest.mark.vcan
        def stand_in(vm_run):
            kind, text = vm_run.report(name)
            if kind == "skipped":
                pytest.skip(f"skipped in the VM: {text}")
            if kind != "passed":
                pytest.fail(f"in the VM: {text}", pytrace=False)

        stand_in.__name__ = name
        stand_in.__doc__ = getattr(cases, name).__doc__
        return stand_in

    for _name in NAMES:
        globals()[_name] = _stand_in(_name)
