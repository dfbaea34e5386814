"""Run the vcan tests: natively where vcan0 exists, otherwise in the throwaway VM.

    python -m tests.vcan.run [pytest arguments]

Exit code: pytest's, from wherever the tests ran. ``python -m pytest`` runs the same tests as part
of the whole suite.
"""

from __future__ import annotations

import subprocess
import sys

from tests.vcan.support import TEST_FILE, run_vcan_tests_in_vm, vcan_here


def main(argv: list[str]) -> int:
    if vcan_here():
        print("[vcan] vcan0 is here: running natively", flush=True)
        return subprocess.call([sys.executable, "-m", "pytest", "-m", "vcan", "-n0", TEST_FILE, *argv])
    print("[vcan] this kernel has no CAN: running in a throwaway VM", flush=True)
    run = run_vcan_tests_in_vm(argv)
    if run.error:
        print(f"[vcan] {run.error}", file=sys.stderr)
        return 2
    return int(run.exit_code or 0)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
