"""Benchmark: how long short commands take as whole processes (issue 42: imports on demand, the
compiled-DBC cache), side by side with another checkout of cmcan.

Each command runs as a fresh process (``python -m cmcan ...``) with its output thrown away, the
checkout under test and the baseline checkout (``--baseline DIR``: e.g. a ``git worktree`` of main)
in alternating rounds, after a warm-up run of each (which also fills the compiled-DBC cache: the
figures are a warm cache's, as every start after the first has it). Printed per command: each
side's median wall and CPU seconds (the children's user + system, from ``os.wait4``) and the median
of the per-round ratios (this / baseline), which holds while the machine's speed drifts.

Commands: ``cmcan --help``, a replay of a 1,000-frame candump log (simulated, or ``--log``), and
``cmcan check`` with the shipped configuration. Targets (issue 42): --help <= 0.4 s, the replay
<= 0.6 s in a full (test) install.

    python bench/bench_startup.py [--baseline DIR] [--rounds 15] [--log PATH]

Import times of one command: ``python -X importtime -m cmcan check 2>&1 | sort -t'|' -k2 -n | tail``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_once(cwd: Path, args: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall s, cpu s) of one ``python -m cmcan ARGS`` in ``cwd`` with that checkout on the path."""
    t0 = time.perf_counter()
    p = subprocess.Popen(
        [sys.executable, "-m", "cmcan", *args],
        cwd=cwd,
        env={**env, "PYTHONPATH": str(cwd)},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise SystemExit(f"{cwd}: cmcan {' '.join(args)} exited {p.returncode}")
    return wall, usage.ru_utime + usage.ru_stime


def thousand_frame_log(out: Path) -> Path:
    """A candump log of the shipped machine's inputs, 1,000 frames (the simulator's)."""
    sys.path.insert(0, str(ROOT))
    from cmcan.can.dbccache import load_compiled
    from cmcan.io.candump import write_candump
    from cmcan.sim import scenario as scn
    from cmcan.sim.frames import frames_from_run
    from cmcan.sim.run import simulate

    s = scn.load(scn.resolve("single_set_healthy")).with_overrides(duration_h=0.01)
    db = load_compiled()
    f = frames_from_run(simulate(s, db, None), db, plan=None)
    n = min(1000, len(f.timestamp_s))
    write_candump(out, f.timestamp_s[:n], f.arbitration_id[:n], f.dlc[:n], f.data[:n], channel="can0")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", type=Path, help="another cmcan checkout to compare with (default: none)")
    ap.add_argument("--rounds", type=int, default=15, help="counted runs of each command on each side")
    ap.add_argument("--log", type=Path, help="the candump log to replay (default: 1,000 simulated frames)")
    a = ap.parse_args()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}  # a start compiles nothing
    with tempfile.TemporaryDirectory() as tmp:
        log = a.log or thousand_frame_log(Path(tmp) / "k1.log")
        commands = {
            "cmcan --help": ["--help"],
            "replay 1,000 frames": ["replay", str(log), "--out", str(Path(tmp) / "k1.csv"), "--force"],
            "cmcan check": ["check"],
        }
        sides = [ROOT] + ([a.baseline.resolve()] if a.baseline else [])
        print(f"{a.rounds} rounds; this: {ROOT}" + (f"; baseline: {sides[1]}" if a.baseline else ""))
        print(
            f"{'command':22} {'wall s':>8} {'cpu s':>8}"
            + (f" {'base wall':>10} {'base cpu':>9} {'ratio wall':>11} {'ratio cpu':>10}" if a.baseline else "")
        )
        for name, args in commands.items():
            for side in sides:  # warm-up: bytecode, page cache, the compiled-DBC cache
                run_once(side, args, env)
            runs: list[list[tuple[float, float]]] = [[] for _ in sides]
            for _ in range(a.rounds):
                for i, side in enumerate(sides):
                    runs[i].append(run_once(side, args, env))
            med = [(statistics.median(w for w, _ in r), statistics.median(c for _, c in r)) for r in runs]
            line = f"{name:22} {med[0][0]:8.3f} {med[0][1]:8.3f}"
            if a.baseline:
                rw = statistics.median(x[0] / y[0] for x, y in zip(runs[0], runs[1], strict=True))
                rc = statistics.median(x[1] / y[1] for x, y in zip(runs[0], runs[1], strict=True))
                line += f" {med[1][0]:10.3f} {med[1][1]:9.3f} {rw:11.2f} {rc:10.2f}"
            print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
