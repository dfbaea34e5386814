"""Benchmark: an MF4 log through cmcan's replay against the same frames as a candump log, and against
asammdf's own decoding of the MF4.

One log of the leakage scenario (``--frames``, 2.23 million by default) is written as a candump log and
as an MF4 file (python-can's ``MF4Writer``, as loggers write it: deflated blocks). Then, as whole
processes in alternating rounds (``--rounds``, the best of each counting, as timeit does):

- ``cmcan replay r.log --out timeline.csv``: the candump path (decode + the whole monitor + timeline);
- ``cmcan replay r.mf4 --out timeline.csv``: the MF4 read in columns (``cmcan/io/mf4columns.py``);
- asammdf's ``MDF(r.mf4).extract_bus_logging({"CAN": [(cmcan.dbc, 0)]})``: decoding only, the signals
  of the shipped DBC out of the same MF4 (no monitor, nothing written);
- cmcan's MF4 reading alone (``cmcan.io.columns.mf4_chunks``): what the replay's reader process does
  (``cmcan/io/readproc.py``), for its peak memory, which adds to the replay's own.

Each with its CPU seconds and peak RSS (``wait4``'s: the CPU includes the children the process waited
for, the peak is the largest of them). The two timelines must be
identical. Targets (issue 42): the MF4 replay within 1.5x of the candump replay, and faster than
asammdf's decoding alone.

    python bench/bench_mf4.py [--frames 2230000] [--rounds 3] [--work DIR]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FRAMES_PER_H = 1_116_000  # the leakage scenario's frames per hour (its 100 Hz and 10 Hz frames)


def write_logs(work: Path, frames: int) -> tuple[Path, Path]:
    """The candump log and its MF4, written once per size (kept in ``work``)."""
    log, mf4 = work / f"r{frames}.log", work / f"r{frames}.mf4"
    if log.exists() and mf4.exists():
        return log, mf4
    import can

    from cmcan.can.frame import to_message_kwargs
    from cmcan.io import mf4support
    from cmcan.io.candump import iter_frames, write_candump
    from tests.helpers import sim_frames

    _run, sim = sim_frames("single_set_leakage", duration_h=frames / FRAMES_PER_H)
    n = min(frames, len(sim.timestamp_s))
    write_candump(log, sim.timestamp_s[:n], sim.arbitration_id[:n], sim.dlc[:n], sim.data[:n])
    mf4support.enable()
    t0 = time.perf_counter()
    with can.Logger(str(mf4)) as w:
        for f in iter_frames(log):
            w.on_message_received(can.Message(**to_message_kwargs(f)))
    print(f"wrote {n:,} frames as {log.name} and {mf4.name} ({time.perf_counter() - t0:.0f} s for the MF4)")
    return log, mf4


ASAMMDF_DECODE = """
import sys
from asammdf import MDF
mdf = MDF(sys.argv[1])
out = mdf.extract_bus_logging({"CAN": [(sys.argv[2], 0)]})
print(sum(len(g.channels) for g in out.groups), "channels")
"""


MF4_READ = """
import sys
from pathlib import Path
from cmcan.io.columns import mf4_chunks
print(sum(len(c) for c in mf4_chunks(Path(sys.argv[1]))), "frames")
"""


def run(cmd: list[str]) -> tuple[float, float, float]:
    """Wall seconds, peak RSS (MB: the largest of the process and the children it waited for) and CPU
    seconds (user + system, the waited children's included) of one process."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=ROOT)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    err = p.stderr.read().decode() if p.stderr else ""
    if status != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({status}): {err[-500:]}")
    return wall, ru.ru_maxrss / 1024.0, ru.ru_utime + ru.ru_stime


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2_230_000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--work", type=Path, default=Path("/tmp/cmcan-bench-mf4"))
    ap.add_argument("--write-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    if args.write_only:
        write_logs(args.work, args.frames)
        return 0
    # written in a process of its own: a child forked from a process holding the frames would count
    # them in its peak RSS
    subprocess.run([sys.executable, __file__, "--write-only", "--frames", str(args.frames), "--work", str(args.work)],
                   check=True)  # fmt: skip
    log, mf4 = args.work / f"r{args.frames}.log", args.work / f"r{args.frames}.mf4"
    py = sys.executable
    dbc = str(ROOT / "dbc" / "cmcan.dbc")
    replay = [py, "-m", "cmcan", "replay"]
    arms = {
        "cmcan replay, candump": [*replay, str(log), "--out", str(args.work / "t_log.csv"), "--force"],
        "cmcan replay, MF4": [*replay, str(mf4), "--out", str(args.work / "t_mf4.csv"), "--force"],
        "asammdf extract_bus_logging (decode only)": [py, "-c", ASAMMDF_DECODE, str(mf4), dbc],
        # the MF4 replay's reader process does this: its peak adds to the replay's own
        "cmcan MF4 reading alone (the reader's work)": [py, "-c", MF4_READ, str(mf4)],
    }
    best: dict[str, tuple[float, float, float]] = {}
    for r in range(args.rounds):
        for name, cmd in arms.items():
            wall, rss, cpu = run(cmd)
            print(f"round {r + 1}: {name}: {wall:.2f} s, {cpu:.2f} s CPU, {rss:.0f} MB", flush=True)
            if name not in best or wall < best[name][0]:
                best[name] = (wall, rss, cpu)
    same = (args.work / "t_log.csv").read_bytes() == (args.work / "t_mf4.csv").read_bytes()
    c, m, a, rd = (best[k] for k in arms)
    print(f"\n{args.frames:,} frames, best of {args.rounds} rounds (wall s, CPU s, peak RSS MB):")
    for name, (wall, rss, cpu) in best.items():
        print(f"  {name:<44} {wall:7.2f} s  {cpu:7.2f} s  {rss:6.0f} MB")
    print(f"  MF4 replay's peak memory, its two processes together: at most {m[1] + rd[1]:.0f} MB")
    print(f"  MF4 / candump replay: {m[0] / c[0]:.2f}x (target <= 1.5x)")
    print(f"  MF4 replay / asammdf decoding alone: {m[0] / a[0]:.2f}x (target < 1)")
    print(f"  timelines identical: {same}")
    ok = same and m[0] <= 1.5 * c[0] and m[0] < a[0]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main(sys.argv[1:]))
