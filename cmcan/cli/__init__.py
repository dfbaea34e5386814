"""The ``cmcan`` command line: one module per subcommand, as cantools lays out its CLI."""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

from cmcan import __version__
from cmcan.cli.errors import EX_SOFTWARE, EX_USAGE, exit_code
from cmcan.cli.journal import error_line, setup_logging
from cmcan.errors import CmcanError

SUBCOMMANDS = (
    "simulate",
    "train",
    "evaluate",
    "score",
    "replay",
    "run",
    "check",
    "demo",
    "gap",
    "uplink",
    "fleet",
    "baseline",
)


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error exits with sysexits' EX_USAGE (64) as the README documents, not 2."""

    def error(self, message: str) -> NoReturn:
        self.print_usage(sys.stderr)
        self.exit(EX_USAGE, f"{self.prog}: error: {message}\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser; with ``only`` (a subcommand) that subcommand's alone: a command
    that is run does not build (and import) the eleven others' (some 50 ms of every start)."""
    parser = _Parser(
        prog="cmcan",
        description="Condition monitoring of hydrostatic drives on CAN: simulate, train, monitor, replay.",
    )
    parser.add_argument("--version", action="version", version=f"cmcan {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMANDS if only is None else (only,):
        importlib.import_module(f"cmcan.cli.{name}").add_subparser(sub)
    return parser


def command_of(argv: Sequence[str]) -> str | None:
    """The subcommand an argument list names: its first argument that is not an option, when that
    is a subcommand (cmcan's own options take no value); None otherwise (the whole parser then
    says what is wrong, or prints the help)."""
    for arg in argv:
        if arg == "--":
            return None
        if not arg.startswith("-"):
            return arg if arg in SUBCOMMANDS else None
    return None


def _unraisable(u: sys.UnraisableHookArgs) -> None:
    """An exception in a library's destructor (asammdf's, on a file it failed to open) is no error of
    the command's, which has said what went wrong: no traceback for it, a debug line with -vv."""
    logging.getLogger("cmcan").debug("ignored in %r: %s: %s", u.object, u.exc_type.__name__, u.exc_value)


def one_blas_thread() -> None:
    """OpenBLAS on one thread unless the caller says otherwise, set before numpy is imported: the
    monitor's arrays are small, so a thread pool per core only costs its start (some 50 ms of every
    command on a 2-core gateway) and makes sums depend on the core count; fleet work spreads over
    processes instead (Dask's workers inherit this)."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def main(argv: Sequence[str] | None = None) -> int:
    one_blas_thread()
    from cmcan.io import mf4support

    mf4support.defer()  # python-can without asammdf and pandas until a log is an MF4 (1.1 s a start)
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(command_of(argv))
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    setup_logging(level, "%(levelname)s %(name)s: %(message)s")
    sys.unraisablehook = _unraisable
    # asammdf logs a traceback for each .mf4 it cannot read; the reader's error says it in one line.
    logging.getLogger("asammdf").setLevel(logging.DEBUG if args.verbose >= 2 else logging.CRITICAL)
    try:
        return int(args.func(args) or 0)
    except CmcanError as exc:
        print(error_line(f"cmcan {args.command}: {exc}"), file=sys.stderr)
        return exit_code(exc)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return 0
    except Exception as exc:  # the last line of defence: say what broke, never a bare traceback
        logging.getLogger("cmcan").debug("unexpected error", exc_info=True)
        print(error_line(f"cmcan {args.command}: internal error: {type(exc).__name__}: {exc}"), file=sys.stderr)
        return EX_SOFTWARE
