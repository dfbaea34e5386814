"""The command line starts on what it uses (issues 37 and 42): its help, and each subcommand's,
imports argparse and the cli's own light modules, not the libraries a command needs when it runs
(cantools alone brings python-can, asammdf, pandas and canmatrix: over a second). Each check runs in
a fresh interpreter, as ``sys.modules`` of the test process holds whatever other tests imported."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from cmcan.cli import SUBCOMMANDS
from tests.conftest import ROOT

HEAVY = (
    "numpy",
    "cantools",
    "can",
    "asammdf",
    "canmatrix",
    "pandas",
    "openpyxl",
    "onnxruntime",
    "onnx",
    "matplotlib",
    "scipy",
    "dask",
    "distributed",
    "pyarrow",
    "duckdb",
    "yaml",
    "paho",
)

# What a command uses when it runs, never to describe itself.
CMCAN_HEAVY = ("cmcan.config", "cmcan.assemble", "cmcan.monitor", "cmcan.daemon.loop", "cmcan.replay", "cmcan.model")


def imported_by(code: str) -> set[str]:
    """The modules a fresh interpreter holds after running ``code`` (its output discarded); a name
    held as None (blocked, as cmcan.io.mf4support defers asammdf) is not imported."""
    script = (
        "import contextlib, io, json, sys\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        + "".join(f"    {line}\n" for line in code.splitlines())
        + "print(json.dumps(sorted(k for k, v in sys.modules.items() if v is not None)))\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        check=True,
    )
    return set(json.loads(r.stdout.splitlines()[-1]))


def among(modules: set[str], packages: tuple[str, ...]) -> list[str]:
    return sorted(m for m in modules if m in packages or m.startswith(tuple(p + "." for p in packages)))


def test_the_help_of_cmcan_and_of_each_subcommand_imports_nothing_heavy():
    helps = "".join(
        f"try:\n    parser.parse_args([{name!r}, '--help'])\nexcept SystemExit:\n    pass\n" for name in SUBCOMMANDS
    )
    code = "import cmcan.cli\nparser = cmcan.cli.build_parser()\n" + helps
    mods = imported_by(code)
    assert "cmcan.cli.check" in mods and "cmcan.cli.fleet" in mods  # the parser was built
    assert among(mods, HEAVY) == []
    assert among(mods, CMCAN_HEAVY) == []


def test_the_help_by_the_command_line_itself_imports_nothing_heavy():
    code = "import cmcan.cli\ntry:\n    cmcan.cli.main(['--help'])\nexcept SystemExit:\n    pass"
    assert among(imported_by(code), HEAVY) == []


@pytest.mark.parametrize("module", ["cmcan.config", "cmcan.assemble"])
def test_the_configuration_does_not_import_cantools_or_python_can(module):
    """cantools is imported where a DBC is read (cmcan.can.dbc), not by the modules that name its types."""
    mods = imported_by(f"import {module}")
    assert among(mods, ("cantools", "can", "asammdf", "pandas", "onnxruntime")) == []


def test_what_the_parsers_say_without_importing_the_commands_is_what_the_commands_have():
    from cmcan.cli import replay as cli_replay
    from cmcan.cli import simulate as cli_simulate
    from cmcan.replay import ENGINES
    from cmcan.sim.scenario import shipped_dir

    assert cli_replay.ENGINES == ENGINES
    assert cli_simulate.shipped_scenarios() == sorted(p.stem for p in shipped_dir().glob("*.yaml"))
    assert "training_healthy" in cli_simulate.shipped_scenarios()


def test_the_check_finds_heavy_modules():
    found = among({"numpy", "numpy.linalg", "canmatrix.formats", "cmcan", "candle", "cantools", "yamlsafe"}, HEAVY)
    assert found == ["canmatrix.formats", "cantools", "numpy", "numpy.linalg"]


def test_a_replay_of_a_candump_log_imports_no_mf4_support(tmp_path):
    """python-can's MF4 reader (asammdf, pandas) only for an MF4: not for a candump log."""
    log = tmp_path / "x.log"
    log.write_text("(1.000000) can0 100#0102030405060708\n")
    code = f"import cmcan.cli\ntry:\n    cmcan.cli.main(['replay', {str(log)!r}])\nexcept SystemExit:\n    pass"
    mods = imported_by(code)
    # python-can itself comes with cantools, on a cold compiled-DBC cache only (see below)
    assert "cmcan.replay" in mods
    assert among(mods, ("asammdf", "pandas", "openpyxl")) == []
    assert among(mods, ("multiprocessing", "cmcan.io.readproc")) == []  # an MF4's reader process


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_a_command_run_builds_its_own_parser_alone_and_parses_as_the_whole_one(name, capsys):
    """main builds the named subcommand's parser only (cmcan.cli.command_of): its help and its usage
    errors are the whole parser's."""
    from cmcan.cli import build_parser, command_of

    assert command_of(["-v", name, "--x"]) == name
    assert command_of(["-vv", "--", name]) is None and command_of(["nosuch", name]) is None
    outs = []
    for parser in (build_parser(), build_parser(only=name)):
        for argv in ([name, "--help"], [name, "--no-such-option"]):
            with pytest.raises(SystemExit) as ex:
                parser.parse_args(argv)
            outs.append((ex.value.code, *capsys.readouterr()))
    assert outs[:2] == outs[2:]
