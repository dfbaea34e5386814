"""``cmcan`` commands of the vcan tier started warm: forked from a process that has imported cmcan.

In the emulated guest a Python start costs 20-25 s, nearly all of it imports (numpy, onnxruntime,
python-can, cantools and cmcan's own modules), and the tier starts some twenty daemons and commands.
Here each runs in a process forked by multiprocessing's forkserver, which imported those modules
once: the same ``cmcan.cli.main`` with the same arguments, environment, working folder and output
files, a real process that gets real signals, only without the interpreter's start. The host tier
starts ``cmcan run`` cold (``tests/daemon_proc.py``, ``tests/test_cli_run.py``), so the start itself
stays tested.

The forkserver's preload is ``tests.vcan.warm_preload`` (importing this module loads nothing).
"""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
import tempfile
from pathlib import Path

_context: multiprocessing.context.ForkServerContext | None = None


def _forkserver() -> multiprocessing.context.ForkServerContext:
    global _context
    if _context is None:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["tests.vcan.warm_preload", __name__])
        _context = ctx
    return _context


def _command(argv: list[str], env: dict[str, str], cwd: str, stdout: str, stderr: str) -> None:
    """The child: the caller's environment, folder and output files, then the command line's main."""
    os.environ.clear()
    os.environ.update(env)
    os.chdir(cwd)
    for fd, path in ((1, stdout), (2, stderr)):
        f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        os.dup2(f, fd)
        os.close(f)
    from cmcan.cli import main

    sys.exit(main(argv))


class WarmProcess:
    """``cmcan ARGV`` in a warm forked process, with the parts of ``subprocess.Popen`` the tests use."""

    def __init__(
        self, argv: list[str], env: dict[str, str] | None = None, stdout: Path | None = None, stderr: Path | None = None
    ) -> None:
        self.args = ["cmcan", *argv]
        out, err = (str(p) if p is not None else os.devnull for p in (stdout, stderr))
        self._proc = _forkserver().Process(
            target=_command, args=(list(argv), dict(os.environ if env is None else env), os.getcwd(), out, err)
        )
        self._proc.start()
        self.pid = self._proc.pid

    @property
    def returncode(self) -> int | None:
        return self._proc.exitcode  # negative: killed by that signal, as Popen says it

    def poll(self) -> int | None:
        return self._proc.exitcode

    def wait(self, timeout: float | None = None) -> int:
        self._proc.join(timeout)
        if self._proc.exitcode is None:
            raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
        return self._proc.exitcode

    def send_signal(self, sig: int) -> None:
        if self._proc.exitcode is None:
            os.kill(self.pid, sig)

    def terminate(self) -> None:
        self._proc.terminate()

    def kill(self) -> None:
        self._proc.kill()


def run(argv: list[str], timeout: float, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """``subprocess.run(["cmcan", *argv], capture_output=True, text=True)``, started warm (the output
    goes through two files of a temporary folder)."""
    with tempfile.TemporaryDirectory() as tmp:
        out, err = Path(tmp) / "out", Path(tmp) / "err"
        out.touch()
        err.touch()
        p = WarmProcess(argv, env, out, err)
        try:
            code = p.wait(timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(10)
            raise
        return subprocess.CompletedProcess(p.args, code, out.read_text(), err.read_text())
