"""Build hook: the C helpers (``cmcan/io/_native.so``: the replay's parser and formatter, the
simulator's integrator), when a C compiler is at hand.

The library is plain C loaded with ctypes (no Python API), so one build serves every Python 3; it is
built in place, where an editable install and the tests of a checkout find it, and put in the wheel,
which is then tagged for this platform. Without a compiler, or with ``CMCAN_NATIVE=0`` in the
environment, the wheel stays pure Python and cmcan does the same work with numpy.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
import sysconfig
from pathlib import Path
from typing import Any

try:
    from hatchling.builders.hooks.plugin.interface import BuildHookInterface
except ImportError:  # imported outside a build (the tests use build_native)
    BuildHookInterface = object  # type: ignore[assignment,misc]

SOURCES = ("cmcan/io/_candump_fast.c", "cmcan/io/_textcols_fast.c", "cmcan/sim/_drive_fast.c")
LIBRARY = "cmcan/io/_native.so"


def build_native(root: Path) -> Path | None:
    """Compile the library in place (through a temporary file, so a failed build leaves no half a
    library behind); None, with a warning, when there is no working compiler."""
    if os.environ.get("CMCAN_NATIVE", "1") == "0":
        return None
    out = root / LIBRARY
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    cc = shlex.split(os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc")
    # -ffp-contract=off: no fused multiply-adds, so the integrator's numbers are the Python loop's to
    # the bit (the same code for the parser and formatter on x86-64, which has none at -O2 anyway)
    flags = ["-O2", "-ffp-contract=off", "-shared", "-fPIC"]
    cmd = [*cc, *flags, "-o", str(tmp), *(str(root / s) for s in SOURCES), "-lm"]
    try:
        subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=300)
        os.replace(tmp, out)
    except (OSError, subprocess.SubprocessError) as exc:
        detail = getattr(exc, "stderr", None) or exc
        print(
            f"cmcan: the C helpers were not built ({detail}); replay uses numpy, simulate its Python loop",
            file=sys.stderr,
        )
        tmp.unlink(missing_ok=True)
        return None
    return out


class NativeBuildHook(BuildHookInterface):
    PLUGIN_NAME = "custom"

    def initialize(self, version: str, build_data: dict[str, Any]) -> None:
        if self.target_name != "wheel":
            return
        lib = build_native(Path(self.root))
        if lib is None or version == "editable":  # an editable install imports the checkout's copy
            return
        build_data["force_include"][str(lib)] = LIBRARY
        build_data["pure_python"] = False
        build_data["tag"] = "py3-none-" + sysconfig.get_platform().replace("-", "_").replace(".", "_")
