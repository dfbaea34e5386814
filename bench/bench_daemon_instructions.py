"""Benchmark: the daemon's work per received frame in instructions, side by side with another checkout.

CPU seconds per frame (``bench_replay.py``'s daemon figure) move by 20-40 % between runs on a shared
virtual machine; the instructions the interpreter executes do not. Each side runs a short script under
valgrind's callgrind twice: the daemon's loop (``Daemon.handle_frames``: the core, the wall-clock
watch, the frames sent to an in-memory bus) over the first ``--warm`` frames of a simulated candump
log, and over ``--frames`` more after those. The difference of the two counts, divided by
``--frames``, is the loop's instructions per frame (start-up, imports and the warm-up cancel out).
The bare receive loop (python-can's ``BusABC.recv`` on the same in-memory bus) is counted the same
way, for the ratio ``bench_replay.py`` prints in seconds.

    python bench/bench_daemon_instructions.py [--baseline DIR] [--frames 20000] [--warm 20000]

``--baseline DIR``: another checkout (e.g. ``git worktree add /tmp/base main``), counted the same way
on the same log. Needs valgrind on the PATH (``apt install valgrind``); callgrind runs some 50 times
slower than the interpreter, so a side takes two minutes or so.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# What runs under callgrind: ROOT on the path first, so each side counts its own code.
FEED = """
import sys
root, log, warm, more, what = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
sys.path[:0] = [root, root + "/bench"]
import can
from bench_replay import MemoryBus
msgs = list(can.LogReader(log))[: warm + more]
bus = MemoryBus(msgs)
if what == "bare":
    while bus.recv(0) is not None:
        pass
    raise SystemExit(0)
from cmcan import config as cfgmod
from cmcan.assemble import assemble
from cmcan.daemon.loop import DRAIN, Daemon, DaemonOptions
cfg = cfgmod.load(None)
mon = assemble(cfg).monitor
d = Daemon(cfg, mon, None, lambda: bus, options=DaemonOptions(idle_after_s=3600))
link = d.links[0]
d._open(link)
for i in range(0, len(msgs), DRAIN):  # in the batches the loop's receive hands over
    d.handle_frames([(link, m) for m in msgs[i : i + DRAIN]])
assert mon.counters["frames_total"] == len(msgs) and d.stats["internal_errors"] == 0
bus.shutdown()
"""


def instructions(root: Path, log: Path, warm: int, more: int, what: str, script: Path) -> int:
    """Instructions callgrind counted for one run of the feed script."""
    env = {**os.environ, "PYTHONHASHSEED": "0", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    r = subprocess.run(
        ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable, str(script),
         str(root), str(log), str(warm), str(more), what],
        capture_output=True, text=True, env=env, cwd=root, check=False,
    )  # fmt: skip
    m = re.search(r"Collected\s*:\s*([\d,]+)", r.stderr) or re.search(r"I\s+refs:\s*([\d,]+)", r.stderr)
    if r.returncode != 0 or m is None:
        raise SystemExit(f"callgrind run failed ({root}, {what}, {more} frames):\n{r.stderr[-2000:]}")
    return int(m.group(1).replace(",", ""))


def per_frame(root: Path, log: Path, warm: int, frames: int, what: str, script: Path) -> float:
    """Instructions per frame of ``frames`` frames after ``warm`` ones (two runs, one after the other)."""
    counted = instructions(root, log, warm, frames, what, script)
    return (counted - instructions(root, log, warm, 0, what, script)) / frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", type=Path, help="another checkout, counted the same way")
    ap.add_argument("--frames", type=int, default=20_000)
    ap.add_argument("--warm", type=int, default=20_000, help="frames before the counted ones (windows full)")
    args = ap.parse_args()
    if shutil.which("valgrind") is None:
        raise SystemExit("valgrind is not installed (apt install valgrind)")
    sys.path[:0] = [str(ROOT), str(ROOT / "bench")]
    import bench_replay as br

    from cmcan import config as cfgmod

    with tempfile.TemporaryDirectory() as d:
        log, script = Path(d) / "r.log", Path(d) / "feed.py"
        br.make_log(log, args.warm + args.frames, cfgmod.load(None))
        script.write_text(FEED)
        sides = [("this", ROOT)] + ([("baseline", args.baseline.resolve())] if args.baseline else [])
        rows = {}
        for name, root in sides:
            rows[name] = (
                per_frame(root, log, args.warm, args.frames, "daemon", script),
                per_frame(root, log, args.warm, args.frames, "bare", script),
            )
    print(f"instructions per received frame ({args.frames:,} frames after {args.warm:,}), callgrind:")
    print(f"{'':12} {'daemon loop':>12} {'bare recv':>10} {'ratio':>7}")
    for name, (daemon, bare) in rows.items():
        print(f"{name:12} {daemon:12,.0f} {bare:10,.0f} {daemon / bare:6.1f}x")
    if "baseline" in rows:
        print(f"this / baseline: {rows['this'][0] / rows['baseline'][0]:.3f}")


if __name__ == "__main__":
    main()
