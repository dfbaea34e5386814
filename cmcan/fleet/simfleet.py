"""``cmcan simulate fleet``: the planned fleet (:mod:`cmcan.sim.fleet`) written to disk.

Layout of ``OUT``::

    dbc/cmcan.dbc                      the shared signal contract
    types/<type>/cmcan.yaml            one configuration per machine type (its V_M, its model)
    types/<type>/model.onnx            trained on a healthy sweep of that type's drive
    logs/<machine>/<machine>_<YYYYmmddTHHMM>.log   candump -l logs, one per ``log_hours`` of operation
    manifest.csv                       machine, log, config, model (paths relative to OUT)
    types.csv                          machine, type (for ``cmcan fleet train --types``)
    truth.json                         the ground truth: each machine's type, duty, oil and failures
                                       (and, with unit-to-unit variation, its own draws: ``unit``)

Every file is written to a temporary name and renamed; an existing ``OUT`` with files in it is
refused unless ``force`` (then only the files above are replaced).
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cmcan import __version__
from cmcan import config as cfgmod
from cmcan.can.dbc import default_dbc_path
from cmcan.can.dbccache import load_compiled
from cmcan.io.candump import write_candump
from cmcan.model.features import operating_points, series_from_columns
from cmcan.model.train import train_on_points
from cmcan.schema import load_yaml
from cmcan.sim import fleet as sf
from cmcan.sim.frames import Frames, frames_from_run
from cmcan.sim.run import simulate

TRUTH_FORMAT = "cmcan-fleet-truth/1"
TYPES_FILE = "types.csv"


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _write_bytes(path: Path, blob: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(blob)
    os.replace(tmp, path)


def type_config(t: sf.MachineType) -> str:
    """The shipped configuration with the type's motor displacement, its own model and the fleet's DBC."""
    raw = load_yaml(cfgmod.default_config_path())
    raw["dbc"] = "../../dbc/cmcan.dbc"
    raw["model"] = "model.onnx"
    raw["drive"] = {"motor_disp_cc": t.motor_disp_cc}
    head = (
        f"# cmcan configuration of the simulated fleet's '{t.name}' machines (pump {t.pump_disp_max_cc:g} cm3/rev, "
        f"motor {t.motor_disp_max_cc:g} cm3/rev at {t.motor_disp_setting:.0%}),\n"
        "# written by `cmcan simulate fleet` from the shipped config/cmcan.yaml.\n"
    )
    return head + yaml.safe_dump(raw, sort_keys=False)


def train_type(t: sf.MachineType, seed: int, cfg: cfgmod.Config) -> tuple[bytes, dict[str, Any]]:
    """A model for the type: its healthy sweep, gated as the configuration gates, trained on the start."""
    s = sf.training_scenario(t, seed)
    run = simulate(s, load_compiled(cfg.dbc_path))
    series, truth = series_from_columns(run.columns, s.name)
    op = operating_points(series, cfg.gate_limits, cfg.rate_hz, truth=truth)
    blob, _model, stats = train_on_points(
        op,
        sf.TRAINING_T_TRN_H,
        t.motor_disp_cc,
        f"scenario:{s.name}",
        extra_training_info={"scenario_seed": s.seed, "machine_type": t.name},
    )
    return blob, stats


def _split(frames: Frames, edges_s: list[float]) -> list[Frames]:
    cut = np.searchsorted(frames.timestamp_s, edges_s)
    out = []
    for a, b in itertools.pairwise(cut):
        out.append(Frames(frames.timestamp_s[a:b], frames.arbitration_id[a:b], frames.dlc[a:b], frames.data[a:b]))
    return out


def write_fleet(
    spec: sf.FleetSpec, out: Path, force: bool = False, progress: Callable[[str], None] | None = None
) -> dict[str, Any]:
    """Simulate and write the whole fleet; returns a summary (machines, logs, frames, seconds)."""
    say = progress or (lambda _msg: None)
    started = time.monotonic()
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not force:
        from cmcan.errors import CmcanError, Kind

        raise CmcanError(f"{out}: folder exists and is not empty; pass --force to write into it", Kind.CANT_CREATE)
    plans = sf.plan_fleet(spec)
    (out / "dbc").mkdir(parents=True, exist_ok=True)
    _write_bytes(out / "dbc" / "cmcan.dbc", default_dbc_path().read_bytes())
    db = load_compiled(out / "dbc" / "cmcan.dbc")

    used_types = sorted({p.type.name for p in plans}, key=list(sf.TYPES).index)
    model_stats = {}
    for k, name in enumerate(used_types):
        t = sf.TYPES[name]
        d = out / "types" / name
        d.mkdir(parents=True, exist_ok=True)
        _write_text(d / "cmcan.yaml", type_config(t))
        cfg = cfgmod.load(d / "cmcan.yaml")
        blob, stats = train_type(t, spec.seed * 1000 + k, cfg)
        _write_bytes(d / "model.onnx", blob)
        model_stats[name] = stats
        say(f"type {name}: model trained, D_tst RMSE {stats['rmse']:.1f} {stats['unit']}")

    rows = []
    machines = []
    n_frames = 0
    spans = sf.log_spans(spec)
    for p in plans:
        run = simulate(p.scenario, db)
        frames = frames_from_run(run, db)
        edges = [p.start_epoch_s + a * 3600.0 for a, _ in spans] + [p.start_epoch_s + spec.hours * 3600.0 + 3600.0]
        d = out / "logs" / p.machine
        d.mkdir(parents=True, exist_ok=True)
        logs = []
        for (a, b), part in zip(spans, _split(frames, edges), strict=True):
            if len(part) == 0:
                continue
            stamp = time.strftime("%Y%m%dT%H%M", time.gmtime(p.start_epoch_s + a * 3600.0))
            log = d / f"{p.machine}_{stamp}.log"
            write_candump(log, part.timestamp_s, part.arbitration_id, part.dlc, part.data)
            rel = log.relative_to(out).as_posix()
            rows.append((p.machine, rel, f"types/{p.type.name}/cmcan.yaml", f"types/{p.type.name}/model.onnx"))
            logs.append({"log": rel, "from_h": a, "to_h": b, "frames": len(part)})
            n_frames += len(part)
        machines.append({**p.truth, "logs": logs})
        leak = p.truth.get("unit", {}).get("arriving_leak_lpm", 0.0)
        say(
            f"{p.machine}: {p.type.name}, {p.truth['duty']}, {p.truth['degradation'] or 'healthy'}"
            + (f", arriving leak {leak:g} l/min" if leak else "")
            + f", {len(logs)} logs"
        )

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(("machine", "log", "config", "model"))
    w.writerows(rows)
    _write_text(out / "manifest.csv", buf.getvalue())
    # machine -> type, what `cmcan fleet train --types` reads (the data set records no type)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(("machine", "type"))
    w.writerows((p.machine, p.type.name) for p in plans)
    _write_text(out / TYPES_FILE, buf.getvalue())
    truth = {
        "format": TRUTH_FORMAT,
        "cmcan_version": __version__,
        "spec": sf.spec_record(spec),
        "types": {n: {**asdict(sf.TYPES[n]), "model_d_tst": model_stats[n]} for n in used_types},
        "machines": machines,
    }
    _write_text(out / "truth.json", json.dumps(truth, indent=2) + "\n")
    return {
        "machines": len(plans),
        "degrading": sum(p.degrading for p in plans),
        "arriving_leaks": spec.arriving_leaks,
        "logs": len(rows),
        "frames": n_frames,
        "types": used_types,
        "out": str(out),
        "seconds": round(time.monotonic() - started, 1),
    }


def remove_outputs(out: Path) -> None:
    """What ``write_fleet`` writes (for --force): the logs, types, dbc folders and the three files."""
    for d in ("logs", "types", "dbc"):
        shutil.rmtree(out / d, ignore_errors=True)
    for f in ("manifest.csv", TYPES_FILE, "truth.json"):
        (out / f).unlink(missing_ok=True)
