"""The replay's C helpers: built by the install's hook when a compiler is at hand, and not missed
where none is (the numpy code does the same work: tests elsewhere hold the two equal)."""

from __future__ import annotations

import ctypes
import os
import shutil
import sys

import pytest

from cmcan.sim import drive
from cmcan.sim.physics import DriveParams
from tests.conftest import ROOT

sys.path.insert(0, str(ROOT))
import hatch_build


def sources_in(tmp_path):
    for s in hatch_build.SOURCES:
        (tmp_path / s).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / s, tmp_path / s)


@pytest.mark.skipif(shutil.which(os.environ.get("CC", "cc")) is None, reason="no C compiler here")
def test_the_hook_builds_a_library_that_parses_a_line(tmp_path):
    sources_in(tmp_path)
    lib_path = hatch_build.build_native(tmp_path)
    assert lib_path == tmp_path / hatch_build.LIBRARY and lib_path.is_file()
    assert [p.name for p in lib_path.parent.iterdir() if p.name.endswith(".tmp")] == []
    lib = ctypes.CDLL(str(lib_path))
    text = b"(1767225600.500000) can0 123#0102\n(1) can0 1#\n"
    assert lib.cmcan_count_lines(text, ctypes.c_int64(len(text))) == 2
    assert lib.cmcan_drive_constants() == len(drive._hoisted(DriveParams()))  # and the integrator


def test_without_a_compiler_the_build_says_so_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    sources_in(tmp_path)
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    assert hatch_build.build_native(tmp_path) is None
    assert "the C helpers were not built" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "cmcan/io").iterdir()) == ["_candump_fast.c", "_textcols_fast.c"]


def test_cmcan_native_0_builds_nothing(tmp_path, monkeypatch):
    sources_in(tmp_path)
    monkeypatch.setenv("CMCAN_NATIVE", "0")
    assert hatch_build.build_native(tmp_path) is None
    assert not (tmp_path / hatch_build.LIBRARY).exists()


def test_a_library_that_does_not_load_leaves_the_numpy_code(tmp_path, monkeypatch):
    """A library built for another machine (or damaged) is not an error: the numpy code runs."""
    import importlib

    from cmcan.io import native

    bad = tmp_path / "io"
    bad.mkdir()
    (bad / native.LIB_NAME).write_bytes(b"not a shared library")
    monkeypatch.setattr(native, "__file__", str(bad / "native.py"))
    assert native._load() is None
    monkeypatch.setenv("CMCAN_NATIVE", "0")
    importlib.reload(native)
    try:
        assert native.LIB is None
    finally:
        monkeypatch.delenv("CMCAN_NATIVE")
        importlib.reload(native)


@pytest.mark.skipif(os.environ.get("CI") != "true", reason="CI's machine has a compiler: the install must build them")
def test_ci_built_and_loads_the_c_helpers():
    from cmcan.io import native

    assert native.LIB is not None
    assert hasattr(native.LIB, "cmcan_drive_integrate")
