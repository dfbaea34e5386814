"""Fuzzing every command's file inputs through the real command line.

    python -m tests.fuzz_cli --minutes 10 [--seed 17] [--jobs 2] [--report fuzz.json] [--keep DIR]
    python -m tests.fuzz_cli --seed 17 --case 123      # one case again, its folder kept

Each case copies a consistent set of inputs for one command into a folder of its own (logs of every
format, configurations, DBCs, models, state files and outboxes, run CSVs, operating-point tables, column
maps, scenarios, drive files, fleet manifests, log folders and data sets), spoils one of them (cut
short, bit-flipped, bytes overwritten, replaced by a file of another kind, made huge, emptied, not
UTF-8, a folder in its place, missing) or makes it hostile (see ``HOSTILE``: YAML alias bombs, deep
nesting and recursive aliases; uplink identifiers MQTT cannot carry; candump frames of more than 64
data bytes; fleet sources that are symlinks out of their folder, FIFOs, ``/dev/zero``, ``/etc/passwd``,
manifests naming them, machine folders with a newline in their name; state files with numbers beyond a
float or int64, nesting past the JSON reader, a baseline one number short, prognosis hours that go
back; the daemon's baseline reset request as a FIFO, a link to ``/dev/zero`` or to a secret, a folder)
and runs the command as a process.
It asserts what the project promises for any input:

- the exit code is 0 or one of the documented sysexits codes (64, 65, 66, 69, 73, 74, 75, 77, 78):
  never 70 "internal error", never a signal, never a hang (a time limit per case);
- no traceback, on either stream;
- on failure, one message that names the spoiled file, and nothing written: no output, no temporary
  file, every input byte for byte as it was (the folder is compared before and after);
- on success, nothing written but the outputs the command line names (``--out``, ``--emit``, ...);
- nothing written outside the case's folder (the folder the hostile symlinks point into is compared
  too), and no byte of a file outside it quoted in a message or an output (a canary secret);
- a model file whose bytes changed is refused (its digest, ``cmcan.content_sha256``), never used;
- ``cmcan run`` either refuses to start (as above) or starts and stops cleanly on SIGTERM (exit 0).

Cases are drawn from ``--seed`` and their number alone, so a failure is reproduced with ``--case``.
``tests/test_fuzz_cli.py`` runs a few dozen of them in the default test run; the figure of a
10-minute run is in docs/reliability.md.
"""

from __future__ import annotations

import argparse
import contextlib
import gzip
import hashlib
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ALLOWED = {0, 64, 65, 66, 69, 73, 74, 75, 77, 78}
HUGE_BYTES = 24 << 20
CASE_TIMEOUT_S = 300.0
# A secret outside every case's folder: hostile sources point at it; no message or output may quote it.
CANARY = "CANARY-7f3a9e"
SECRET_TEXT = f"root:{CANARY}:20228:0:99999:7:::\n"
OUTSIDE = "_outside"  # the folder in the corpus holding the secret (compared before and after each case)


# -- the corpus: one consistent set of valid inputs --------------------------------------------------


class Corpus:
    """Valid inputs, made once in ``base``: each item a file (or folder) name in a case's folder and
    its content. A configuration names its DBC and model by relative paths (so each case reads its
    own copies) and its state folder by an absolute path (written per case)."""

    def __init__(self, base: Path) -> None:
        self.base = base
        base.mkdir(parents=True, exist_ok=True)
        self._lock = threading.RLock()  # a builder may need another item
        self._built: dict[str, Path] = {}

    # item name -> (name in the case folder, kind for "wrong type", builder writing base/<name>)
    ITEMS: ClassVar[dict[str, tuple[str, str]]] = {
        "cfg": ("cmcan.yaml", "yaml"),
        "dbc": ("cmcan.dbc", "dbc"),
        "model": ("model.onnx", "onnx"),
        "state": ("state/state.json", "json"),
        "request": ("state/baseline-reset.json", "json"),
        "log": ("run.log", "candump"),
        "loggz": ("run.log.gz", "gzip"),
        "blf": ("run.blf", "blf"),
        "asc": ("run.asc", "asc"),
        "trc": ("run.trc", "trc"),
        "framecsv": ("frames.csv", "csv"),
        "db": ("run.db", "sqlite"),
        "mf4": ("run.mf4", "mf4"),
        "runcsv": ("run.csv", "csv"),
        "scenario": ("scenario.yaml", "yaml"),
        "rigcfg": ("rig.yaml", "yaml"),
        "rigdbc": ("rig.dbc", "dbc"),
        "rigmodel": ("rig.onnx", "onnx"),
        "cycles": ("cycles.csv", "csv"),
        "pointspec": ("points.yaml", "yaml"),
        "drive": ("drive.yaml", "yaml"),
        "uplinkcfg": ("uplink.yaml", "yaml"),
        "outbox": ("state/outbox.sqlite", "sqlite"),
        "manifest": ("manifest.csv", "csv"),
        "flog": ("a.log", "candump"),
        "fleetdir": ("logs", "dir"),
        "dataset": ("ds", "dir"),
    }

    def path(self, item: str) -> Path:
        with self._lock:
            if item not in self._built:
                self._built[item] = self._build(item)
            return self._built[item]

    def _build(self, item: str) -> Path:
        name, _kind = self.ITEMS[item]
        p = self.base / name
        p.parent.mkdir(parents=True, exist_ok=True)
        getattr(self, f"_make_{item}")(p)
        return p

    # builders -----------------------------------------------------------------------------------

    def _frames(self):
        if not hasattr(self, "_frames_cache"):
            from cmcan import config as cfgmod
            from cmcan.assemble import dbc_for
            from cmcan.sim import scenario as scn
            from cmcan.sim.frames import frames_from_run
            from cmcan.sim.run import simulate

            s = scn.load(scn.shipped("two_set_validation")).with_overrides(duration_h=60 / 3600)
            db = dbc_for(cfgmod.load())
            run = simulate(s, db)
            self._run_cache = run
            self._frames_cache = frames_from_run(run, db)
        return self._frames_cache

    def _messages(self):
        import can

        f = self._frames()
        return [
            can.Message(timestamp=t, arbitration_id=i, data=bytes(d), is_extended_id=False)
            for t, i, d in zip(f.timestamp_s.tolist(), f.arbitration_id.tolist(), f.data, strict=True)
        ]

    def _make_log(self, p: Path) -> None:
        from cmcan.io.candump import write_candump

        f = self._frames()
        write_candump(p, f.timestamp_s, f.arbitration_id, f.dlc, f.data)

    def _make_flog(self, p: Path) -> None:
        shutil.copyfile(self.path("log"), p)

    def _make_loggz(self, p: Path) -> None:
        p.write_bytes(gzip.compress(self.path("log").read_bytes()))

    def _python_can_log(self, p: Path) -> None:
        import can

        with can.Logger(str(p)) as w:
            for m in self._messages():
                w.on_message_received(m)

    _make_blf = _make_asc = _make_trc = _make_db = _make_mf4 = _python_can_log

    def _make_framecsv(self, p: Path) -> None:
        tmp = p.with_name("frames_tmp.csv")
        self._python_can_log(tmp)
        tmp.replace(p)

    def _make_runcsv(self, p: Path) -> None:
        from cmcan.io.runcsv import write_run_csv

        self._frames()
        write_run_csv(p, self._run_cache.columns)

    def _make_cfg(self, p: Path) -> None:
        # the baseline and the prognosis on: their parts of the state file are read too
        self._yaml_config(p, {"baseline": dict(BASELINE), "prognosis": {"enabled": True}})

    def _make_uplinkcfg(self, p: Path) -> None:
        # port 1: nothing listens, so --check is refused at once (69) once the configuration passed
        mqtt = {"host": "127.0.0.1", "port": 1, "connect_timeout_s": 2}
        self._yaml_config(p, {"uplink": {"enabled": True, "machine_id": "fuzz-1", "mqtt": mqtt}})

    def _yaml_config(self, p: Path, extra: dict) -> None:
        import yaml

        raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
        raw["dbc"] = "cmcan.dbc"
        raw["model"] = "model.onnx"
        raw["bus"].update(interface="virtual", channel="@CHANNEL@")
        raw["state"]["directory"] = "@STATE@"
        raw.update(extra)
        p.write_text(yaml.safe_dump(raw, sort_keys=False))

    def _make_dbc(self, p: Path) -> None:
        shutil.copyfile(ROOT / "dbc" / "cmcan.dbc", p)

    def _make_model(self, p: Path) -> None:
        shutil.copyfile(ROOT / "cmcan" / "model" / "default.onnx", p)

    def _make_state(self, p: Path) -> None:
        """A state of every part: the run's totals and baseline (learning) under the corpus's
        configuration, a level change, a prognosis history with a trend, DTC counts."""
        from cmcan.assemble import assemble
        from cmcan.config import load
        from cmcan.io.candump import iter_frames
        from cmcan.replay import replay
        from tests.statefile_support import trend

        self.path("dbc"), self.path("model")  # the configuration names them
        mon = assemble(load(self.path("cfg"))).monitor
        replay(mon, iter_frames(self.path("log")))
        t = mon.save_totals()
        t.history.append(
            {"t_s": 1767225700.0, "from": "ok", "to": "low", "reason": "ratio_low", "ratio_filt_pct": 97.5}
        )
        t.warning_count += 1
        assert t.prognosis is not None and t.baseline is not None
        t.prognosis |= {"points": trend(), "open": None}
        t.dtc_occurrences, t.dtc_active = {"520192:7": 3}, ["520192:7"]
        p.write_text(json.dumps(t.to_dict(), indent=1))

    def _make_request(self, p: Path) -> None:
        """What ``cmcan baseline reset`` leaves for the running daemon."""
        p.write_text(json.dumps({"reason": "fuzz: pump replaced", "at": "2026-01-01T00:00:00Z"}) + "\n")

    def _make_outbox(self, p: Path) -> None:
        from cmcan.uplink.records import Entry
        from cmcan.uplink.writer import OutboxWriter

        w = OutboxWriter(str(p), 10**9, 1e9).start()
        for i in range(40):
            w.submit(Entry("event" if i % 5 == 0 else "summary", 1767225600.0 + i, {"i": i}))
        w.close()
        for extra in p.parent.glob(p.name + "-*"):  # WAL leftovers: the checkpointed file alone
            extra.unlink()

    def _make_scenario(self, p: Path) -> None:
        import yaml

        from tests.conftest import small_scenario

        p.write_text(yaml.safe_dump(small_scenario(duration_h=0.005)))

    def _make_rigcfg(self, p: Path) -> None:
        text = (ROOT / "examples" / "zema-rig" / "cmcan.yaml").read_text()
        p.write_text(text.replace("dbc: rig.dbc", "dbc: rig.dbc").replace("model: rig.onnx", "model: rig.onnx"))

    def _make_rigdbc(self, p: Path) -> None:
        shutil.copyfile(ROOT / "examples" / "zema-rig" / "rig.dbc", p)

    def _make_rigmodel(self, p: Path) -> None:
        shutil.copyfile(ROOT / "examples" / "zema-rig" / "rig.onnx", p)

    def _make_cycles(self, p: Path) -> None:
        shutil.copyfile(ROOT / "examples" / "zema-rig" / "data" / "cycles.csv", p)

    def _make_pointspec(self, p: Path) -> None:
        shutil.copyfile(ROOT / "examples" / "zema-rig" / "points.yaml", p)

    def _make_drive(self, p: Path) -> None:
        shutil.copyfile(ROOT / "examples" / "zema-rig" / "drive.yaml", p)

    def _make_manifest(self, p: Path) -> None:
        p.write_text("machine,log\nwl-1,a.log\n")

    def _make_fleetdir(self, p: Path) -> None:
        (p / "wl-1").mkdir(parents=True)
        shutil.copyfile(self.path("log"), p / "wl-1" / "a.log")

    def secret(self) -> Path:
        """A file outside every case's folder, as a credentials file would be."""
        with self._lock:
            d = self.base / OUTSIDE
            d.mkdir(exist_ok=True)
            p = d / "secret.log"
            if not p.exists():
                p.write_text(SECRET_TEXT)
                p.chmod(0o600)
            return p

    def _make_dataset(self, p: Path) -> None:
        work = self.base / "_fleet"
        work.mkdir(exist_ok=True)
        shutil.copyfile(self.path("log"), work / "a.log")
        (work / "manifest.csv").write_text("machine,log\nwl-1,a.log\n")
        r = subprocess.run(
            [sys.executable, "-m", "cmcan", "fleet", "replay", str(work / "manifest.csv"), *("--out", str(p)), "-q"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=300,
        )
        if r.returncode != 0:
            raise RuntimeError(f"cannot build the fleet data set: {r.stderr}")


# -- targets: a command and the inputs it reads ------------------------------------------------------


@dataclass(frozen=True)
class Target:
    name: str
    inputs: tuple[str, ...]  # corpus items copied into the case folder
    mutable: tuple[str, ...]  # the ones the fuzzer may spoil
    argv: tuple[str, ...]  # the command line, relative to the case folder
    daemon: bool = False  # cmcan run: started, then stopped with SIGTERM
    weight: float = 1.0
    needs: str = ""  # an optional module the command needs
    # fleet replay: a log that fails is quarantined in the data set, which is the command's output
    # (exit 65 and the log named say so); nothing else may write on failure.
    writes_on_failure: bool = False
    # exit codes of a command that ran as it should whatever the spoiling (uplink --check: 69, no broker)
    ok_codes: tuple[int, ...] = (0,)
    # what the command may write besides the outputs its command line names (the uplink's state folder)
    may_write: tuple[str, ...] = ()
    timeout_s: float = CASE_TIMEOUT_S

    def outputs(self) -> tuple[str, ...]:
        """What the command line names as outputs (``--out``, ``--emit``, ``--candump``), and may_write."""
        out = [a for flag, a in zip(self.argv, self.argv[1:], strict=False) if flag in OUTPUT_FLAGS]
        return (*out, *self.may_write)


OUTPUT_FLAGS = ("--out", "--emit", "--candump")
DAEMON_FILES = ("cfg", "dbc", "model", "state")
RUN_FILES = (*DAEMON_FILES, "request")  # the daemon also reads a baseline reset left for it
BASELINE = {"enabled": True, "coverage_pct": 20, "min_points": 40, "min_hours": 0.02}
TARGETS = [
    Target("check", DAEMON_FILES, DAEMON_FILES, ("check", "--config", "cmcan.yaml", "--state"), weight=2),
    Target(
        "run",
        RUN_FILES,
        RUN_FILES,
        ("run", "--config", "cmcan.yaml"),
        daemon=True,
        weight=2,
        may_write=("state/",),
    ),
    *[
        Target(
            f"replay.{item}",
            (item,),
            (item,),
            ("replay", Corpus.ITEMS[item][0], "--out", "timeline.csv", "--emit", "emitted.log"),
            needs="asammdf" if item == "mf4" else "",
        )
        for item in ("log", "loggz", "blf", "asc", "trc", "framecsv", "db", "mf4")
    ],
    Target(
        "replay.streaming",
        ("log",),
        ("log",),
        ("replay", "run.log", "--engine", "streaming", "--out", "timeline.csv", "--emit", "emitted.log"),
    ),
    Target(
        "replay.config",
        ("log", "cfg", "dbc", "model"),
        ("cfg", "dbc", "model"),
        ("replay", "run.log", "--config", "cmcan.yaml", "--model", "model.onnx", "--out", "timeline.csv"),
    ),
    Target("train.csv", ("runcsv",), ("runcsv",), ("train", "run.csv", "--t-trn-h", "0.012", "--out", "m.onnx")),
    Target("train.log", ("log",), ("log",), ("train", "run.log", "--t-trn-h", "0.012", "--out", "m.onnx")),
    Target(
        "score",
        ("runcsv", "model"),
        ("runcsv", "model"),
        ("score", "run.csv", "--model", "model.onnx", "--out", "scores.csv"),
    ),
    Target(
        "score.points",
        ("cycles", "rigcfg", "rigdbc", "rigmodel"),
        ("cycles", "rigcfg", "rigdbc", "rigmodel"),
        ("score", "cycles.csv", "--points", "--config", "rig.yaml", "--out", "scores.csv"),
    ),
    Target("evaluate", ("runcsv",), ("runcsv",), ("evaluate", "run.csv", "--t-trn-h", "0.012")),
    Target(
        "simulate",
        ("scenario",),
        ("scenario",),
        ("simulate", "scenario.yaml", "--out", "sim.csv", "--candump", "sim.log"),
    ),
    Target("gap", ("runcsv",), ("runcsv",), ("gap", "diagnose", "run.csv", "--out", "gap", "--no-plots")),
    Target(
        "gap.points",
        ("cycles", "pointspec", "drive"),
        ("cycles", "pointspec", "drive"),
        (
            *("gap", "diagnose", "cycles.csv", "--points", "points.yaml", "--drive", "drive.yaml"),
            *("--quantity", "flow_lpm", "--where", "pump_leak=0", "--out", "gap", "--no-plots"),
        ),
    ),
    Target(
        "uplink.status",
        ("uplinkcfg", "outbox"),
        ("uplinkcfg", "outbox"),
        ("uplink", "--status", "--config", "uplink.yaml"),
    ),
    Target(
        "uplink.check",
        ("uplinkcfg",),
        ("uplinkcfg",),
        ("uplink", "--check", "--config", "uplink.yaml"),
        ok_codes=(0, 69),
        may_write=("state/",),
    ),
    Target(
        "fleet.replay",
        ("manifest", "flog"),
        ("manifest", "flog"),
        ("fleet", "replay", "manifest.csv", "--out", "fleet-ds", "--workers", "1"),
        weight=0.5,
        needs="dask",
        writes_on_failure=True,
        timeout_s=120.0,
    ),
    Target(
        "fleet.replay.dir",
        ("fleetdir",),
        ("fleetdir",),
        ("fleet", "replay", "logs", "--out", "fleet-ds", "--workers", "1"),
        weight=0.5,
        needs="dask",
        writes_on_failure=True,
        timeout_s=120.0,
    ),
    Target(
        "fleet.query",
        ("dataset",),
        ("dataset",),
        ("fleet", "query", "ds", "select machine, count(*) from timeline group by machine"),
        weight=0.5,
        needs="duckdb",
    ),
    Target(
        "fleet.report",
        ("dataset",),
        ("dataset",),
        ("fleet", "report", "ds", "--out", "report.html"),
        weight=0.5,
        needs="duckdb",
    ),
]


# -- mutations ------------------------------------------------------------------------------------


TEXT_KINDS = {"yaml", "dbc", "json", "candump", "asc", "trc", "csv"}
MUTATIONS = {  # name -> weight
    "truncate": 3.0,
    "bitflip": 3.0,
    "bytes": 1.5,
    "wrongtype": 1.5,
    "nonutf8": 1.0,
    "empty": 0.7,
    "huge": 0.5,
    "folder": 0.3,
    "missing": 0.3,
}


def mutate(path: Path, kind: str, how: str, rng: np.random.Generator, corpus: Corpus) -> str:
    """Spoil ``path`` in place; returns a short description."""
    if path.is_dir():  # a data set: spoil one of its files
        files = sorted(p for p in path.rglob("*") if p.is_file())
        target = files[int(rng.integers(len(files)))]
        return f"{target.relative_to(path.parent)}: " + mutate(target, "parquet", how, rng, corpus)
    data = path.read_bytes()
    if how == "truncate":
        keep = int(rng.integers(0, max(1, len(data))))
        path.write_bytes(data[:keep])
        return f"truncated to {keep} of {len(data)} bytes"
    if how == "bitflip":
        b = bytearray(data)
        n = int(rng.integers(1, 9))
        for _ in range(n):
            if b:
                i = int(rng.integers(len(b)))
                b[i] ^= 1 << int(rng.integers(8))
        path.write_bytes(bytes(b))
        return f"{n} bits flipped"
    if how == "bytes":
        b = bytearray(data)
        if b:
            i = int(rng.integers(len(b)))
            n = int(rng.integers(1, min(64, len(b) - i) + 1))
            b[i : i + n] = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        path.write_bytes(bytes(b))
        return "bytes overwritten"
    if how == "wrongtype":
        others = [it for it, (_n, k) in Corpus.ITEMS.items() if k not in (kind, "dir")]
        other = others[int(rng.integers(len(others)))]
        path.write_bytes(corpus.path(other).read_bytes())
        return f"replaced by {Corpus.ITEMS[other][0]}"
    if how == "nonutf8":
        b = bytearray(data)
        i = int(rng.integers(len(b) + 1))
        b[i:i] = bytes([0xFF, 0xFE, 0xC3])
        path.write_bytes(bytes(b))
        return f"invalid UTF-8 at byte {i}"
    if how == "empty":
        path.write_bytes(b"")
        return "emptied"
    if how == "huge":
        if kind in TEXT_KINDS and data:
            reps = HUGE_BYTES // len(data) + 1
            with open(path, "ab") as f:
                for _ in range(reps):
                    f.write(data)
            return f"repeated to {reps * len(data) >> 20} MiB"
        with open(path, "ab") as f:
            f.write(rng.integers(0, 256, HUGE_BYTES, dtype=np.uint8).tobytes())
        return f"{HUGE_BYTES >> 20} MiB of random bytes appended"
    if how == "folder":
        path.unlink()
        path.mkdir()
        return "a folder in its place"
    if how == "missing":
        path.unlink()
        return "missing"
    raise ValueError(how)


# -- hostile inputs: made to attack, not damaged --------------------------------------------------------

# name -> (weight, the corpus items it applies to: an item name, or "kind:<kind>" for every item of a kind)
HOSTILE: dict[str, tuple[float, tuple[str, ...]]] = {
    "aliasbomb": (1.0, ("kind:yaml",)),
    "deepnest": (0.7, ("kind:yaml",)),
    "recursive": (0.3, ("kind:yaml",)),
    "mqttstring": (3.0, ("uplinkcfg",)),
    "bigframe": (1.5, ("log", "flog")),
    "symlinkout": (1.0, ("fleetdir", "manifest", "request")),
    "special": (1.0, ("fleetdir", "manifest", "request")),
    "machinenl": (0.5, ("fleetdir", "manifest")),
    "statenum": (1.0, ("state",)),
    "stateshape": (1.0, ("state",)),
    "jsondeep": (0.5, ("state", "request")),
}
HOSTILE_SHARE = 0.5  # of the cases whose spoiled item has hostile mutations
MQTT_FIELDS = (("machine_id",), ("mqtt", "client_id"), ("mqtt", "username"), ("mqtt", "topic_prefix"), ("mqtt", "host"))
MQTT_VALUES = (
    "fuzz\x00x", "fuzz-1\n", "site/+/x", "site/#", "$SYS", "x" * 70_000, "ü" * 40_000, "a\ud800b", "a\x7fb",
    "ok\u0085", "tab\there", "", "../../etc", "ok",
)  # fmt: skip
BIG_FRAME_BYTES = (65, 100, 2000, 3000, 20_000, 32_768, 40_000)


def hostile_for(item: str) -> list[str]:
    kind = Corpus.ITEMS[item][1]
    return [h for h, (_w, on) in HOSTILE.items() if item in on or f"kind:{kind}" in on]


def make_hostile(path: Path, item: str, how: str, rng: np.random.Generator, corpus: Corpus) -> tuple[str, list[str]]:
    """Make ``path`` (the case's copy of ``item``) hostile; returns a description and the names a
    message refusing it may name (the file, or the hostile entry inside it)."""
    name = path.name
    if how == "aliasbomb":
        levels = int(rng.integers(6, 13))
        lines = ["zz_b0: &zzb0 [" + ", ".join(["lol"] * 10) + "]"]
        lines += [f"zz_b{i}: &zzb{i} [" + ", ".join([f"*zzb{i - 1}"] * 10) + "]" for i in range(1, levels)]
        with open(path, "a") as f:
            f.write("\n" + "\n".join(lines) + "\n")
        return f"an alias bomb of 10^{levels} nodes appended", [name]
    if how == "deepnest":
        depth = int(rng.choice([65, 1000, 100_000, 300_000]))
        with open(path, "a") as f:
            f.write("\nzz_deep: " + "[" * depth + "]" * depth + "\n")
        return f"nested {depth} deep", [name]
    if how == "recursive":
        with open(path, "a") as f:
            f.write("\nzz_rec: &zzr [1, {again: *zzr}]\n")
        return "an alias inside its own node", [name]
    if how == "mqttstring":
        import yaml

        raw = yaml.safe_load(path.read_text())
        keys = MQTT_FIELDS[int(rng.integers(len(MQTT_FIELDS)))]
        value = MQTT_VALUES[int(rng.integers(len(MQTT_VALUES)))]
        node = raw["uplink"]
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = value
        path.write_text(yaml.safe_dump(raw, sort_keys=False))
        return f"uplink.{'.'.join(keys)} = {value[:20]!r}{'...' if len(value) > 20 else ''}", [name]
    if how == "bigframe":
        lines = path.read_text().splitlines(keepends=True)
        i = int(rng.integers(len(lines)))
        ts, iface, frame = lines[i].split()
        n = int(rng.choice(BIG_FRAME_BYTES))
        fd = bool(rng.integers(2))
        ident = frame.split("#")[0]
        payload = rng.integers(0, 256, n, dtype=np.uint8).tobytes().hex().upper()
        lines.insert(i, f"{ts} {iface} {ident}{'##1' if fd else '#'}{payload}\n")
        path.write_text("".join(lines))
        return f"a {'CAN FD ' if fd else ''}frame of {n} data bytes at line {i + 1}", [name]
    secret = corpus.secret()
    if item == "state":
        return hostile_state(path, how, rng), [name]
    if item == "request":
        return hostile_request(path, how, rng, secret), [name]
    if item == "fleetdir":
        machine = path / "wl-1"
        if how == "machinenl":
            machine.rename(path / "wl-1\n")
            return "machine folder 'wl-1\\n'", [name, "wl-1"]
        if how == "symlinkout":
            (machine / "evil.log").symlink_to(secret)
            return "evil.log -> a file outside the folder", [name, "evil.log"]
        choice = int(rng.integers(3))
        if choice == 0:
            os.mkfifo(machine / "fifo.log")
            return "fifo.log, a FIFO nobody writes to", [name, "fifo.log"]
        target = ("/dev/zero", "/etc/passwd")[choice - 1]
        (machine / "dev.log").symlink_to(target)
        return f"dev.log -> {target}", [name, "dev.log", target]
    # the manifest: rows naming what is not a log of this folder
    import csv
    import io

    rows = list(csv.reader(io.StringIO(path.read_text())))
    if how == "machinenl":
        rows[1][0] = "wl-1\n"
        what, names = "machine 'wl-1\\n'", [name, "wl-1"]
    elif how == "symlinkout":
        choice = int(rng.integers(2))
        rows[1][1] = str(secret) if choice else os.path.relpath(secret, path.parent)
        what, names = f"log {rows[1][1]}", [name, "secret.log"]
    else:
        choice = int(rng.integers(3))
        if choice == 0:
            os.mkfifo(path.parent / "fifo.log")
            rows[1][1] = "fifo.log"
        else:
            rows[1][1] = ("/dev/zero", "/etc/passwd")[choice - 1]
        what, names = f"log {rows[1][1]}", [name, rows[1][1]]
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    path.write_text(out.getvalue())
    return what, names


# A state file crafted against the daemon (issue 38): numbers beyond a float or int64, not finite or
# implausible, nesting past the reader's limit, a baseline or a prognosis that contradicts itself.
# Each: a description and the edit of the document (a JSON text for numbers json cannot write).
STATE_NUMBERS = (
    ("evaluated_s an integer of 310 digits", ("evaluated_s",), "1" + "0" * 309),
    ("baseline.n[0] above int64", ("baseline", "n", 0), str(2**63)),
    ("a prognosis leak of 1e300", ("prognosis", "points", 3, 1), "1e300"),
    ("a time of 1e400", ("time_in_level_s", "ok"), "1e400"),
    ("NaN in the ratio filter", ("filter_ratios", 0), "NaN"),
    ("a prognosis leak of 1e7 l/min", ("prognosis", "points", 3, 1), "1e7"),
)


def hostile_state(path: Path, how: str, rng: np.random.Generator) -> str:
    doc = json.loads(path.read_text())
    if how == "jsondeep":
        depth = int(rng.choice([70, 100_000]))
        if depth == 70:
            doc["baseline"]["history"] = [{"deep": json.loads("[" * depth + "]" * depth)}]
            path.write_text(json.dumps(doc))
        else:
            path.write_text(json.dumps(doc)[:-1] + ', "zz": ' + "[" * depth + "]" * depth + "}")
        return f"nested {depth} deep"
    if how == "statenum":
        what, where, text = STATE_NUMBERS[int(rng.integers(len(STATE_NUMBERS)))]
        node = doc
        for k in where[:-1]:
            node = node[k]
        node[where[-1]] = "@NUMBER@"
        path.write_text(json.dumps(doc).replace('"@NUMBER@"', text))
        return what
    choice = int(rng.integers(4))
    pts = doc["prognosis"]["points"]
    if choice == 0:
        doc["baseline"]["sy"].pop()
    elif choice == 1:
        doc["baseline"]["sxx"][int(rng.integers(len(doc["baseline"]["sxx"])))].pop()
    elif choice == 2:
        pts[5][0], pts[6][0] = pts[6][0], pts[5][0]
    else:
        doc["prognosis"]["clock"] = {"operating_s": -1.0, "last_t_s": None}
    path.write_text(json.dumps(doc))
    return ("a baseline one number short", "a baseline row one number short", "prognosis hours that go back",
            "a negative operating clock")[choice]  # fmt: skip


def hostile_request(path: Path, how: str, rng: np.random.Generator, secret: Path) -> str:
    """The baseline reset request as something the daemon must neither follow, block on nor read
    endlessly: a link to a secret or to /dev/zero, a FIFO, a folder, JSON nested past the reader."""
    if how == "jsondeep":
        path.write_text("[" * 100_000 + "]" * 100_000)
        return "nested 100000 deep"
    path.unlink()
    if how == "symlinkout":
        path.symlink_to(secret)
        return f"{path.name} -> a file outside the folder"
    choice = int(rng.integers(3))
    if choice == 0:
        os.mkfifo(path)
        return f"{path.name}, a FIFO nobody writes to"
    if choice == 1:
        path.symlink_to("/dev/zero")
        return f"{path.name} -> /dev/zero"
    path.mkdir()
    return f"{path.name}, a folder"


# -- one case -----------------------------------------------------------------------------------------


@dataclass
class Case:
    index: int
    target: Target
    item: str
    how: str
    detail: str = ""
    dir: Path = Path()
    argv: list[str] = field(default_factory=list)
    pristine: str = ""  # SHA-256 of the spoiled input before it was spoiled
    names: list[str] = field(default_factory=list)  # what a refusal may name (the spoiled file by default)


@dataclass
class Outcome:
    case: Case
    code: int | None
    seconds: float
    problems: list[str]
    stderr: str


def draw(
    seed: int, index: int, targets: list[Target], round_robin: bool
) -> tuple[Target, str, str, np.random.Generator]:
    rng = np.random.default_rng([seed, index])
    if round_robin:
        target = targets[index % len(targets)]
        rng.random()
    else:
        w = np.array([t.weight for t in targets])
        target = targets[int(rng.choice(len(targets), p=w / w.sum()))]
    item = target.mutable[int(rng.integers(len(target.mutable)))]
    names = list(MUTATIONS)
    p = np.array([MUTATIONS[m] for m in names])
    how = names[int(rng.choice(len(names), p=p / p.sum()))]
    if how == "nonutf8" and Corpus.ITEMS[item][1] not in TEXT_KINDS:
        how = "bitflip"
    hostile = hostile_for(item)
    if hostile and rng.random() < HOSTILE_SHARE:
        w = np.array([HOSTILE[h][0] for h in hostile])
        how = hostile[int(rng.choice(len(hostile), p=w / w.sum()))]
    return target, item, how, rng


def prepare_case(corpus: Corpus, work: Path, seed: int, index: int, targets: list[Target], rr: bool) -> Case:
    target, item, how, rng = draw(seed, index, targets, rr)
    d = work / f"case-{index:06d}"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    (d / "state").mkdir()
    for it in target.inputs:
        src = corpus.path(it)
        dst = d / Corpus.ITEMS[it][0]
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_dir():
            shutil.copytree(src, dst)
        else:
            text = src.read_bytes()
            if Corpus.ITEMS[it][1] == "yaml":  # the case's own state folder and virtual channel
                text = text.replace(b"@STATE@", str(d / "state").encode())
                text = text.replace(b"@CHANNEL@", f"fuzz-{os.getpid()}-{index}".encode())
            dst.write_bytes(text)
    case = Case(index, target, item, how, dir=d, argv=list(target.argv))
    spoiled = d / Corpus.ITEMS[item][0]
    case.pristine = hashlib.sha256(spoiled.read_bytes()).hexdigest() if spoiled.is_file() else ""
    case.names = [spoiled.name]
    if how in HOSTILE:
        case.detail, case.names = make_hostile(spoiled, item, how, rng, corpus)
    else:
        case.detail = mutate(spoiled, Corpus.ITEMS[item][1], how, rng, corpus)
    return case


def snapshot(d: Path) -> dict[str, str]:
    """Every path under ``d`` with what it is: a folder, a symlink and its target, a FIFO or another
    special file, or a regular file's SHA-256. Symlinks are not followed (one may point at /dev/zero)."""
    out = {}
    for root, dirs, files in os.walk(d, followlinks=False):
        for n in dirs + files:
            p = Path(root) / n
            st = p.lstat()
            rel = str(p.relative_to(d))
            if stat.S_ISLNK(st.st_mode):
                out[rel] = "link:" + os.readlink(p)
            elif stat.S_ISDIR(st.st_mode):
                out[rel] = "dir"
            elif stat.S_ISREG(st.st_mode):
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
            else:
                out[rel] = f"special:{stat.S_IFMT(st.st_mode):o}"
    return out


def quotes_canary(d: Path, paths: set[str]) -> list[str]:
    """The written files (of ``paths`` under ``d``) that hold the canary: as bytes, or for a Parquet file
    in any of its values (its pages may be compressed)."""
    found = []
    for rel in sorted(paths):
        p = d / rel
        if p.is_symlink() or not p.is_file():
            continue
        data = p.read_bytes()
        hit = CANARY.encode() in data
        if not hit and p.suffix == ".parquet":
            try:
                import pyarrow.parquet as pq

                hit = CANARY in str(pq.read_table(p).to_pylist())
            except Exception:  # not readable as Parquet: the bytes were searched
                hit = False
        if hit:
            found.append(rel)
    return found


def _under(path: str, prefixes: tuple[str, ...]) -> bool:
    return any(path == o.rstrip("/") or path.startswith(o.rstrip("/") + "/") for o in prefixes)


def run_case(case: Case, outside: Path | None = None) -> Outcome:
    before = snapshot(case.dir)
    outside_before = snapshot(outside) if outside is not None and outside.exists() else {}
    cmd = [sys.executable, "-m", "cmcan", *case.argv]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    err_path = case.dir.parent / f"{case.dir.name}.stderr"
    out_path = case.dir.parent / f"{case.dir.name}.stdout"
    t0 = time.monotonic()
    problems: list[str] = []
    with open(err_path, "w") as err, open(out_path, "w") as out:
        # a session of its own: a case that hangs is killed with what it started (Dask's workers)
        proc = subprocess.Popen(cmd, cwd=case.dir, env=env, stdout=out, stderr=err, start_new_session=True)
        code = _wait(proc, case, err_path, problems)
    seconds = time.monotonic() - t0
    stderr = err_path.read_text(errors="replace")
    stdout = out_path.read_text(errors="replace")
    err_path.unlink()
    out_path.unlink()
    after = snapshot(case.dir)
    changed = {k for k in set(before) | set(after) if before.get(k) != after.get(k)}
    if CANARY in stderr or CANARY in stdout:
        problems.append("a message quotes a file outside the folder (the canary secret)")
    leaked = quotes_canary(case.dir, changed)
    if leaked:
        problems.append(f"an output quotes a file outside the folder (the canary secret): {leaked[:3]}")
    if outside is not None and outside.exists() and snapshot(outside) != outside_before:
        problems.append(f"written outside the case's folder: {outside}")
    if code is not None:
        if code not in ALLOWED:
            problems.append(f"exit code {code} is not one of {sorted(ALLOWED)}")
        if "Traceback" in stderr or "Traceback" in stdout:
            problems.append("a traceback")
        if "internal error" in stderr:
            problems.append("an internal error")
        rel, kind = Corpus.ITEMS[case.item]
        if code == 0 and kind == "onnx" and before.get(rel) != case.pristine:
            problems.append("a spoiled model was accepted")  # its digest must catch any changed byte
        outputs = case.target.outputs()
        stray = sorted(k for k in changed if not _under(k, outputs))
        if code not in case.target.ok_codes:
            names = case.names or [Path(rel).name]
            lines = [x for x in stderr.splitlines() if x.strip()]
            if not lines:
                problems.append("no message")
            elif not any(n in stderr for n in names):
                problems.append(f"the message does not name {' or '.join(repr(n) for n in names)}")
            written = stray if case.target.writes_on_failure else sorted(changed)
            if written:
                problems.append(f"written on failure: {written[:6]}")
        elif stray:
            problems.append(f"written besides its outputs {list(outputs)}: {stray[:6]}")
    return Outcome(case, code, seconds, problems, stderr[-2000:])


def _wait(proc: subprocess.Popen, case: Case, err_path: Path, problems: list[str]) -> int | None:
    deadline = time.monotonic() + case.target.timeout_s
    if case.target.daemon:  # started: stop it the way systemd does
        while proc.poll() is None and time.monotonic() < deadline:
            if "cmcan running on" in err_path.read_text(errors="replace"):
                time.sleep(0.3)
                proc.send_signal(signal.SIGTERM)
                try:
                    code = proc.wait(15)
                except subprocess.TimeoutExpired:
                    _kill(proc)
                    problems.append("did not stop within 15 s of SIGTERM")
                    return None
                if code != 0:
                    problems.append(f"stopped by SIGTERM with exit code {code}")
                return code
            time.sleep(0.05)
    try:
        code = proc.wait(max(0.0, deadline - time.monotonic()))
    except subprocess.TimeoutExpired:
        _kill(proc)
        problems.append(f"still running after {case.target.timeout_s:.0f} s")
        return None
    if code < 0:
        problems.append(f"killed by signal {-code}")
    return code


def _kill(proc: subprocess.Popen) -> None:
    """SIGKILL to the case's process group (the command and every process it started), then reap it."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


# -- the run ----------------------------------------------------------------------------------------


@dataclass
class Summary:
    cases: int = 0
    seconds: float = 0.0
    codes: Counter = field(default_factory=Counter)
    targets: Counter = field(default_factory=Counter)
    mutations: Counter = field(default_factory=Counter)
    failures: list[dict] = field(default_factory=list)

    def add(self, o: Outcome) -> None:
        self.cases += 1
        self.codes[str(o.code)] += 1
        self.targets[o.case.target.name] += 1
        self.mutations[o.case.how] += 1
        if o.problems:
            self.failures.append(
                {
                    "case": o.case.index,
                    "target": o.case.target.name,
                    "input": Corpus.ITEMS[o.case.item][0],
                    "mutation": f"{o.case.how}: {o.case.detail}",
                    "exit_code": o.code,
                    "problems": o.problems,
                    "stderr": o.stderr[-600:],
                }
            )

    def to_dict(self) -> dict:
        return {
            "cases": self.cases,
            "seconds": round(self.seconds, 1),
            "exit_codes": dict(self.codes),
            "targets": dict(self.targets),
            "mutations": dict(self.mutations),
            "failures": self.failures,
        }


def available(targets: list[Target]) -> list[Target]:
    import importlib.util

    return [t for t in targets if not t.needs or importlib.util.find_spec(t.needs) is not None]


def fuzz(
    seed: int,
    *,
    minutes: float | None = None,
    cases: int | None = None,
    only: list[int] | None = None,
    jobs: int = 2,
    work: Path | None = None,
    keep: bool = False,
    round_robin: bool = False,
    progress: Callable[[Outcome], None] | None = None,
) -> Summary:
    """Run cases ``0, 1, 2, ...`` of ``seed`` (or ``only`` those) until ``minutes`` or ``cases``."""
    own = work is None
    work = Path(tempfile.mkdtemp(prefix="cmcan-fuzz-")) if work is None else work
    corpus = Corpus(work / "base")
    targets = available(TARGETS)
    summary = Summary()
    t0 = time.monotonic()
    deadline = t0 + minutes * 60 if minutes is not None else None
    indices = iter(only) if only is not None else iter(range(10**9))
    lock = threading.Lock()

    def next_index() -> int | None:
        with lock:
            if deadline is not None and time.monotonic() >= deadline:
                return None
            if cases is not None and summary.cases + pending[0] >= cases:
                return None
            i = next(indices, None)
            if i is not None:
                pending[0] += 1
            return i

    pending = [0]

    def worker() -> None:
        while (i := next_index()) is not None:
            case = prepare_case(corpus, work / "cases", seed, i, targets, round_robin)
            o = run_case(case, corpus.base / OUTSIDE)
            with lock:
                pending[0] -= 1
                summary.add(o)
            if progress is not None:
                progress(o)
            if not o.problems and not keep:
                shutil.rmtree(case.dir, ignore_errors=True)

    try:
        corpus.path("log")  # the shared simulated run, before the workers start
        corpus.secret()  # and the folder outside every case, compared around each of them
        with ThreadPoolExecutor(jobs) as pool:
            for f in [pool.submit(worker) for _ in range(jobs)]:
                f.result()
    finally:
        summary.seconds = time.monotonic() - t0
        if own and not keep and not summary.failures:
            shutil.rmtree(work, ignore_errors=True)
    return summary


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, help="run for this long")
    ap.add_argument("--cases", type=int, help="run this many cases")
    ap.add_argument("--case", type=int, action="append", help="run only this case (repeatable); its folder is kept")
    ap.add_argument("--seed", type=int, default=17)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--keep", type=Path, help="work in this folder and keep every case's folder")
    ap.add_argument("--report", type=Path, help="write the summary as JSON here")
    ap.add_argument("--round-robin", action="store_true", help="targets in turn instead of by weight")
    args = ap.parse_args(argv)
    if args.minutes is None and args.cases is None and not args.case:
        ap.error("give --minutes, --cases or --case")

    def show(o: Outcome) -> None:
        mark = "FAIL" if o.problems else "ok  "
        print(
            f"{mark} #{o.case.index:<6} {o.case.target.name:<16} {Corpus.ITEMS[o.case.item][0]:<20} "
            f"{o.case.how:<10} exit {o.code!s:<4} {o.seconds:5.1f} s  {'; '.join(o.problems)}",
            flush=True,
        )

    work = args.keep
    s = fuzz(
        args.seed,
        minutes=args.minutes,
        cases=args.cases,
        only=args.case,
        jobs=args.jobs,
        work=work,
        keep=work is not None or bool(args.case),
        round_robin=args.round_robin,
        progress=show,
    )
    doc = s.to_dict()
    print(json.dumps({k: v for k, v in doc.items() if k != "failures"}, indent=1))
    print(f"{s.cases} cases in {s.seconds / 60:.1f} min, {len(s.failures)} failing")
    for f in s.failures:
        print(json.dumps(f, indent=1))
    if args.report:
        args.report.write_text(json.dumps(doc, indent=1))
    return 1 if s.failures else 0


if __name__ == "__main__":
    sys.exit(main())
