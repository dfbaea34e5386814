"""A state file with every part filled (warning totals, J1939 DTC counts and clears, a learned
baseline, a prognosis history with a trend) and the configuration it belongs to, for the tests of
state files as untrusted input (tests/test_statefile.py, tests/test_statefile_fuzz.py)."""

from __future__ import annotations

import copy
import functools
import json
import logging
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from cmcan import config as cfgmod
from cmcan.assemble import Assembled, assemble, build_monitor
from cmcan.can.frame import Frame
from cmcan.monitor.core import Monitor
from cmcan.monitor.totals import Totals
from cmcan.replay import replay_file
from tests.daemon_proc import virtual_config
from tests.helpers import as_frames, sim_frames, write_log

BASELINE = {"enabled": True, "coverage_pct": 20, "min_points": 40, "min_hours": 0.02}
PROGNOSIS = {"enabled": True}
SIM_H = 0.3  # long enough for the baseline to be learned (22 % of the envelope)
TAIL_S = 4.0  # the frames fed after a restart: some 15 ticks evaluated, the baseline's correction applied


def config_file(tmp: Path, name: str = "cmcan.yaml") -> Path:
    """The shipped configuration on the virtual bus with the baseline and the prognosis enabled."""
    return virtual_config(tmp, name=name, baseline=BASELINE, prognosis=PROGNOSIS)


@functools.cache
def _made() -> tuple[str, tuple[Frame, ...]]:
    work = Path(tempfile.mkdtemp(prefix="cmcan-statefile-"))
    cfg = cfgmod.load(config_file(work))
    _, frames = sim_frames(duration_h=SIM_H)
    mon = assemble(cfg).monitor
    replay_file(write_log(work / "run.log", frames), mon)
    assert mon.baseline is not None and mon.baseline.applies, "the baseline must be learned"
    doc = mon.save_totals().to_dict()
    doc["prognosis"] |= {"points": trend(), "open": None}
    doc["prognosis"]["clock"]["operating_s"] = 3600.0 * doc["prognosis"]["points"][-1][0]
    doc |= {"dtc_occurrences": {"520192:7": 3}, "dtc_active": ["520192:7"]}
    clear = {"t_s": 1767225700.0, "t_run_s": 1767225700.0, "kind": "dm11", "by_address": 0x17}
    doc["dtc_clears"] = [clear | {"by_name": None, "cleared": ["520192:7"]}]
    doc["history"].append(
        {"t_s": 1767225700.0, "from": "ok", "to": "low", "reason": "ratio_low", "ratio_filt_pct": 97.5}
    )
    doc["warning_count"] += 1
    tail = as_frames(frames)
    t_end = tail[-1].timestamp_s
    return json.dumps(doc), tuple(f for f in tail if f.timestamp_s > t_end - TAIL_S)


def trend() -> list[list[Any]]:
    """80 half-hour points (40 h) of a leak rising with scatter, as a worn unit's: the estimate finds a
    trend and draws its curves when the state is read. Each point's ticks at one operating point (the
    orifice gain's sums as the laminar one's)."""
    rng = np.random.default_rng(5)
    hours = 0.25 + 0.5 * np.arange(80)
    leak = 0.004 * hours**2 + rng.normal(0.0, 0.05, len(hours))
    return [
        [float(h), float(x), float(100.0 - 0.8 * x), 900, 850.0, 850.0 * float(x), 850.0, 850.0]
        for h, x in zip(hours, leak, strict=True)
    ]


def good_doc() -> dict[str, Any]:
    """The state document (a fresh copy)."""
    return copy.deepcopy(json.loads(_made()[0]))


def tail_frames() -> tuple[Frame, ...]:
    """The last seconds of the run the state was made from."""
    return _made()[1]


@functools.cache
def _parts(cfg_path: str) -> Assembled:
    return assemble(cfgmod.load(cfg_path))


def build(cfg_path: Path, totals: Totals) -> Monitor:
    """The monitor the daemon builds from ``totals`` (the configuration's DBC and model read once)."""
    parts = _parts(str(cfg_path))
    return build_monitor(parts.cfg, parts.db, parts.model, totals)


def still_up(mon: Monitor, frames: tuple[Frame, ...] = ()) -> int:
    """Feed ``frames`` (the tail by default) as the daemon does, then idle ticks: nothing raises, the
    ticks come; returns how many ticks were evaluated."""
    frames = frames or tail_frames()
    for f in frames:
        mon.feed(f)
    mon.advance(frames[-1].timestamp_s + 2.0)
    mon.flush()
    evaluated = int(mon.counters["evaluated"])
    assert mon.n_ticks > 0 and evaluated > 0
    snap = mon.snapshot()
    assert snap["level"] in ("ok", "low", "high", "fault")
    return evaluated


def part_of(totals: Totals, part: str) -> dict[str, Any]:
    """The fields of one part (statefile.PARTS) as saved."""
    from cmcan.service.statefile import PARTS

    doc = totals.to_dict()
    return {f: doc[f] for f in PARTS[part][0]}


def journal(caplog: Any) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
