from __future__ import annotations

import pytest

from tests.vcan.support import VmRun, run_vcan_tests_in_vm


@pytest.fixture(scope="session")
def vm_run(request) -> VmRun:
    """Boot the VM once and run every vcan test inside; its output goes straight to the terminal."""
    capman = request.config.pluginmanager.getplugin("capturemanager")
    with capman.global_and_fixture_disabled():
        print("\n[vcan] this kernel has no CAN: running the vcan tests in a throwaway VM", flush=True)
        run = run_vcan_tests_in_vm()
        print(f"[vcan] VM done: exit code {run.exit_code}", flush=True)
    return run
