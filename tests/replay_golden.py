"""Golden replay outputs of the shipped scenarios: what ``cmcan replay`` emits, fixed in digests.

A refactoring must not change a single output byte; an intended change of behaviour rewrites the
digests on purpose, with the reason in its commit:

    python -m tests.replay_golden --write
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

from tests.conftest import ROOT, run_cli

GOLDEN = ROOT / "tests" / "data" / "replay_golden.json"
# (scenario, duration override in hours or None for the whole run): every shipped scenario, the
# run to failure whole, the continuous ones shortened to keep the slow tier's time in bounds.
CASES = {
    "run_to_failure": None,
    "healthy_mixed_100h": 20.0,
    "training_healthy": 0.5,
    "single_set_healthy": 0.5,
    "single_set_leakage": 2.0,
    "two_set_train": 0.5,
    "two_set_validation": 1.2,
}


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def simulated_log(name: str, hours: float | None, log: Path) -> Path:
    """The candump log ``cmcan simulate NAME --candump LOG [--duration-h HOURS]`` writes, made in this
    process (the command's steps without its run CSV, which the replay does not read)."""
    from cmcan.can.dbc import load_dbc
    from cmcan.io.candump import write_candump
    from cmcan.sim import scenario as scn
    from cmcan.sim.frames import frames_from_run
    from cmcan.sim.run import simulate

    s = scn.load(scn.resolve(name))
    s = s.with_overrides(duration_h=hours) if hours is not None else s
    db = load_dbc(None)
    f = frames_from_run(simulate(s, db, None), db, plan=None)
    write_candump(
        log, f.timestamp_s, f.arbitration_id, f.dlc, f.data, channel=f.channels("can0"), extended=f.is_extended()
    )
    return log


def replay_digests(name: str, hours: float | None, work: Path) -> dict[str, object]:
    """Simulate the scenario to a candump log, replay it with ``cmcan replay``, and digest what came out."""
    log, emit, timeline = work / f"{name}.log", work / f"{name}.emit.log", work / f"{name}.csv"
    simulated_log(name, hours, log)
    r = run_cli("replay", str(log), "--emit", str(emit), "--out", str(timeline), "--json", "--force")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    return {
        "emitted_sha256": digest(emit),
        "timeline_sha256": digest(timeline),
        "warnings": [[round(w["operating_h"], 6), w["from"], w["to"], w["reason"]] for w in summary["warnings"]],
    }


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="rewrite the golden digests")
    ap.add_argument("--work", default="/tmp/cmcan-golden", help="folder for the logs")
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    got = {name: replay_digests(name, hours, work) for name, hours in CASES.items()}
    if args.write:
        GOLDEN.write_text(json.dumps(got, indent=1) + "\n")
        print(f"wrote {GOLDEN}")
        return 0
    want = json.loads(GOLDEN.read_text())
    bad = [n for n in CASES if got[n] != want.get(n)]
    for n in bad:
        fields = [k for k in got[n] if got[n][k] != (want.get(n) or {}).get(k)]
        print(f"differ: {n} ({', '.join(fields)})")
    if not bad:
        print("all equal")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
