"""The demo: the run-to-failure scenario streamed through the real daemon on an in-process CAN bus.

The simulator's frames are played into the daemon (the same class as ``cmcan run``) on in-process
python-can buses, with their own timestamps (operating hours); the daemon monitors them and
broadcasts its frames, and the demo reads those frames back like a telematics unit would: the
warnings, set against the failures the scenario schedules, with the lead time of each.

A kernel bus (vcan0) stamps every frame with its receive time, so a 550 h time-lapse cannot run
over it; the vcan integration tests play logs in real time with canplayer instead.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import can
import numpy as np
from numpy.typing import NDArray

from cmcan import config as cfgmod
from cmcan.assemble import bus_plan, dbc_for
from cmcan.can.frame import Frame, from_message, to_message_kwargs
from cmcan.can.j1939 import dm1 as j1939_dm1
from cmcan.can.j1939 import ids as j1939_ids
from cmcan.can.j1939.transport import BamReceiver
from cmcan.daemon.loop import Daemon, DaemonOptions, bus_kwargs
from cmcan.daemon.preflight import prepare
from cmcan.errors import CmcanError, Kind
from cmcan.monitor.baseline import MODE_NAMES
from cmcan.monitor.payloads import Outputs
from cmcan.monitor.tick import LEVEL_NAMES
from cmcan.monitor.warnings import Reason
from cmcan.roles import MOTOR_SPEED
from cmcan.sim import scenario as scn
from cmcan.sim.frames import Frames, frames_from_run
from cmcan.sim.run import simulate

log = logging.getLogger("cmcan.demo")

LEAD_TIME_MIN_H = 10.0
HEALTHY_UNTIL_H = 200.0
# The demo's machine learns its own baseline on board (docs/commissioning.md) over about this many
# operating hours of the time-lapse, from an envelope around the rig's one operating point.
LEARNING_H = 20.0
# The prognosis is judged this many hours before each failure, within this share of the truth
PROGNOSIS_BEFORE_H = 10.0
# The default end of life's replay estimates only where asked (judge_default_eol): the longest interval.
_FEW_ESTIMATES_H = 100.0
PROGNOSIS_WITHIN = 0.2


@dataclass
class DemoResult:
    scenario: str
    bus: str  # the virtual bus it ran on
    config: str  # the configuration file
    frames: str  # the machine's frames: "11-bit identifiers", "J1939 (cmcan at source address 0x8C)", ...
    frames_sent: int
    frames_processed: int
    wall_s: float
    transitions: list[dict[str, Any]] = field(default_factory=list)
    failures: list[dict[str, Any]] = field(default_factory=list)
    ratio_h: list[float] = field(default_factory=list)
    ratio_pct: list[float] = field(default_factory=list)
    checks: dict[str, bool] = field(default_factory=dict)
    windows: dict[str, float] = field(default_factory=dict)
    # the on-board baseline as CM_BASELINE showed it: (operating h, state name) at each change
    baseline: list[tuple[float, str]] = field(default_factory=list)
    # CM_PROGNOSIS as :func:`prognosis_at` decodes it, for the figure's panel (not in the JSON: thousands)
    prognosis: list[tuple[float, str, float, float, float]] = field(default_factory=list)
    # what end of life the demo configured and why, and the default's (:func:`end_of_life`)
    end_of_life: dict[str, Any] = field(default_factory=dict)

    @property
    def learning_h(self) -> tuple[float, float] | None:
        """The learning phase (first CM_BASELINE frame to the end of learning), None if none was seen."""
        if not self.baseline or self.baseline[0][1] != "learning":
            return None
        end = next((h for h, s in self.baseline[1:] if s != "learning"), None)
        return (self.baseline[0][0], end) if end is not None else None

    @property
    def passed(self) -> bool:
        return all(self.checks.values())

    def to_dict(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "bus": self.bus,
            "config": self.config,
            "frames": self.frames,
            "frames_sent": self.frames_sent,
            "frames_processed": self.frames_processed,
            "wall_s": round(self.wall_s, 1),
            "scaled_windows": self.windows,
            "warnings": self.transitions,
            "failures": self.failures,
            "checks": self.checks,
            "baseline": [{"operating_h": h, "state": s} for h, s in self.baseline],
            "end_of_life": self.end_of_life,
            "passed": self.passed,
        }


def scale_windows(cfg: cfgmod.Config, burst_s: float, every_min: float) -> cfgmod.Config:
    """Shorten the filter and the debounce for a sparser time-lapse than the shipped scenario's.

    Both count evaluated samples. The shipped run_to_failure samples 10 s every 10 min, so the
    configured 300-sample filter spans about half an hour of operation; the demo samples 5 s every
    30 min by default, six times sparser, so the same windows would span six times as many hours.
    Scaling them by the sampling density keeps the demo's time-lapse comparable to the scenario.
    """
    ref = scn.load(scn.shipped("run_to_failure")).sampling
    scale = min(1.0, (burst_s / every_min) / (ref.burst_s / ref.every_min))
    samples = max(30, round(cfg.filter.samples * scale))
    flt = replace(cfg.filter, samples=samples, min_samples=min(samples, max(10, round(cfg.filter.min_samples * scale))))
    th = replace(cfg.thresholds, debounce_s=max(10.0, cfg.thresholds.debounce_s * scale))
    return replace(cfg, filter=flt, thresholds=th)


def windows_of(cfg: cfgmod.Config) -> dict[str, float]:
    return {
        "filter_samples": cfg.filter.samples,
        "filter_min_samples": cfg.filter.min_samples,
        "debounce_s": cfg.thresholds.debounce_s,
    }


def with_baseline(cfg: cfgmod.Config, s: scn.Scenario) -> cfgmod.Config:
    """The on-board baseline on: the envelope the machine works in (the rig's one operating point, a
    few percent either way, and its oil's swing), learning for :data:`LEARNING_H` operating hours
    (the operating clock counts the time between the time-lapse's bursts, as on a gateway)."""
    d, oil = s.duty, s.oil
    speed, dp = float(d["pump_speed_rpm"]), float(d["dp_bar"])
    t_lo, t_hi = oil["temp_c"] - oil["swing_c"] - 2.0, oil["temp_c"] + oil["swing_c"] + 2.0
    edges = {"pump_speed_rpm": (0.95 * speed, 1.05 * speed), "dp_bar": (0.95 * dp, 1.05 * dp), "temp_c": (t_lo, t_hi)}
    settings = replace(cfg.baseline.settings, edges=edges, min_hours=LEARNING_H, coverage_pct=100.0)
    b = replace(cfg.baseline, enabled=True, settings=settings)
    return replace(cfg, baseline=b)


def with_prognosis(cfg: cfgmod.Config, s: scn.Scenario) -> cfgmod.Config:
    """The prognosis on, with the rig's known ends of life: the wear leakage at which its units lose
    function (the scenario's ``fail_extra_lpm``, stated at its reference pressure and oil temperature)
    and the ratio at which its mispositioned motor does (:func:`misposition_eol_pct`)."""
    wear = [e for e in s.events if e["type"] == "wear"]
    if not wear:
        return cfg
    e = wear[0]
    high = misposition_eol_pct(s.events)
    p = cfgmod.PrognosisConfig.on(
        eol_kind="leak_lpm",
        eol_value=float(e["fail_extra_lpm"]),
        **({"eol_high_pct": high} if high is not None else {}),
        dp_ref_bar=float(e["ref_dp_bar"]),
        temp_ref_c=float(e["ref_temp_c"]),
        estimate_every_h=1.0,
    )
    return replace(cfg, prognosis=p)


def end_of_life(cfg: cfgmod.Config) -> dict[str, Any]:
    """What end of life the demo's prognosis counts to, and why: the rig's own loss of function, which
    the scenario knows and a machine in the field does not; and the default a machine gets."""
    p, d = cfg.prognosis.params, cfgmod.PrognosisConfig.on().params
    return {
        "configured": {"kind": p.eol_kind, "value": p.eol_value, "high_pct": p.eol_high_pct},
        "configured_text": p.end_of_life_text,
        "why": "the scenario's own loss of function (its wear's fail_extra_lpm, the ratio its misposition fails at): "
        "the demo's estimates count to the failures themselves, which a machine in the field does not know",
        "default": {"kind": d.eol_kind, "value": d.eol_value, "high_pct": d.eol_high_pct},
        "default_text": f"{d.end_of_life_text} (docs/prognosis.md)",
    }


def judge_default_eol(
    frames: Frames,
    cfg: cfgmod.Config,
    start_epoch_s: float,
    report: list[dict[str, Any]],
    ratio: tuple[list[float], list[float]],
) -> None:
    """Beside each failure: what the default end of life gives on the same run (the same frames
    through the same core with the prognosis's defaults), against when the filtered ratio reached
    that end of life on the bus.

    The estimate is a function of the history alone (no pooling by default), so the replay keeps the
    history and the estimate is taken where the report asks for one, :data:`PROGNOSIS_BEFORE_H` before
    each failure: an estimate every half hour of a 550 h life was a third of the demo's time."""
    from cmcan.assemble import assemble
    from cmcan.replay import replay_columns

    asked = sorted({f["fail_h"] - PROGNOSIS_BEFORE_H for f in report if f["kind"] in ("wear", "misposition")})
    if not asked:
        return
    cfg_d = replace(cfg, prognosis=cfgmod.PrognosisConfig.on(estimate_every_h=_FEW_ESTIMATES_H))
    mon = assemble(cfg_d).monitor
    stage = mon.prognosis
    assert stage is not None  # enabled just above
    seen: dict[float, Any] = {}

    def parts() -> Iterator[Any]:
        """The frames in chunks cut at the hours asked; each estimate taken once the frames before it
        are in (a generator resumes when the replay asks for the next chunk)."""
        pending = list(asked)
        for c in frames.to_columns(cfg.bus.channel):
            h = (c.timestamp_s - start_epoch_s) / 3600.0
            lo = 0
            while pending and h[-1] >= pending[0]:
                cut = int(np.searchsorted(h, pending[0]))
                if cut > lo:
                    yield c.take(np.arange(lo, cut))
                lo = cut
                stage.fold()
                seen[pending.pop(0)] = stage.history.estimate()
            if lo < len(c):
                yield c.take(np.arange(lo, len(c)))

    replay_columns(mon, parts())
    p = cfg_d.prognosis.params
    h, pct = np.asarray(ratio[0], dtype=float), np.asarray(ratio[1], dtype=float)
    previous = 0.0
    for f in report:
        if f["kind"] not in ("wear", "misposition"):
            continue
        past = pct >= p.eol_high_pct if f["kind"] == "misposition" else pct <= p.eol_value
        reached = reached_after(h, past, previous, f["fail_h"])
        previous = f["fail_h"]
        at = f["fail_h"] - PROGNOSIS_BEFORE_H
        e = seen.get(at)
        trend = e is not None and e.state != "none"
        f["prognosis_default_eol"] = {
            "at_h": at,
            "state": None if e is None else e.state,
            # None where a drawn curve never gets there within the history's reach
            "to_eol_h": [x if math.isfinite(x) else None for x in e.to_eol_h] if trend else None,
            "reached_h": reached,
        }


def reached_after(h: Any, past: Any, after_h: float, until_h: float) -> float | None:
    """The first hour in (``after_h``, ``until_h``] at which ``past`` holds after it did not: a unit
    repaired at ``after_h`` starts the window still past its end of life until the ratio recovers."""
    rows = np.flatnonzero((h > after_h) & (h <= until_h))
    inside = np.flatnonzero(~past[rows])
    if not len(inside):
        return None
    later = np.flatnonzero(past[rows][inside[0] :])
    return float(h[rows[inside[0] + later[0]]]) if len(later) else None


def misposition_eol_pct(events: list[dict[str, Any]]) -> float | None:
    """The ratio at the failure of the first misposition that raises it: the motor's displacement
    short by the drift reached at ``fail_h``, so it turns (and the ratio reads) 1 / (1 + pct/100)."""
    for e in events:
        if e["type"] != "misposition" or e.get("fail_h") is None:
            continue
        reached = 1.0
        if e["mode"] != "step":
            reached = min(max((e["fail_h"] - e["start_h"]) / (e["end_h"] - e["start_h"]), 0.0), 1.0)
        factor = 1.0 + float(e["pct"]) / 100.0 * reached
        if factor < 1.0:
            return 100.0 / factor
    return None


def prognosis_at(
    received: list[Frame], db: Any, cfg: cfgmod.Config, start_epoch_s: float, outputs: Outputs | None = None
) -> list[tuple[float, str, float, float, float]]:
    """CM_PROGNOSIS as a telematics unit reads it: (operating h, state, p10, p50, p90 h to end of life)."""
    if not cfg.prognosis.enabled:
        return []
    msg = db.get_message_by_name(cfg.outputs.cm_prognosis.message)
    fid = outputs.prognosis.frame_id if outputs is not None and outputs.prognosis is not None else msg.frame_id
    out = []
    for m in received:
        if m.arbitration_id == fid:
            d = msg.decode(m.data, decode_choices=False)
            state = {1: "none", 2: "trend", 3: "imminent"}.get(int(d["prognosis_state"]), "?")
            p10, p50, p90 = (float(d[f"prognosis_to_eol_{q}_h"]) for q in ("p10", "p50", "p90"))
            out.append(((m.timestamp_s - start_epoch_s) / 3600.0, state, p10, p50, p90))
    return sorted(out)


def judge_prognosis(report: list[dict[str, Any]], seen: list[tuple[float, str, float, float, float]]) -> None:
    """Beside each failure: the estimate :data:`PROGNOSIS_BEFORE_H` before it against the truth."""
    for f in report:
        at = f["fail_h"] - PROGNOSIS_BEFORE_H
        near = [x for x in seen if abs(x[0] - at) <= 0.5]
        best = min(near, key=lambda x: abs(x[0] - at)) if near else None
        if best is None or best[1] == "none":
            f["prognosis"] = {"at_h": at, "state": best[1] if best else None, "ok": False}
            continue
        truth = f["fail_h"] - best[0]
        f["prognosis"] = {
            "at_h": best[0],
            "state": best[1],
            "to_eol_h": [best[2], best[3], best[4]],
            "truth_h": truth,
            "ok": abs(best[3] - truth) <= PROGNOSIS_WITHIN * truth,
        }


def demo_scenario(burst_s: float, every_min: float) -> scn.Scenario:
    s = scn.load(scn.shipped("run_to_failure"))
    return s.with_overrides(sampling={"mode": "bursts", "burst_s": burst_s, "every_min": every_min})


def on_virtual_buses(cfg: cfgmod.Config, prefix: str, state_dir: Path) -> tuple[cfgmod.Config, dict[str, str]]:
    """The configuration on in-process buses (:class:`PlayerBus`), each channel renamed ``prefix-NAME``."""
    names = {c.name: f"{prefix}-{c.name}" for c in cfg.channel_list}
    cfg = cfgmod.rename_channels(cfg, names)
    return cfgmod.with_overrides(cfg, interface="virtual", state_dir=str(state_dir)), names


class PlayerBus(can.BusABC):
    """An in-process python-can bus that plays one channel of a log into the daemon as fast as the
    daemon reads it: each receive hands over the channel's next frame, with its own timestamp; what
    the daemon sends is kept in :attr:`sent`. Once the log is played it is a silent bus.

    The daemon reads it through python-can's ``BusABC.recv`` (its filters included), as it reads any
    bus. python-can's virtual bus would need a player thread and copies every frame into a locked
    queue per reader: about a third of the demo's time went there, none of it the daemon's."""

    def __init__(self, channel: str, messages: Iterator[can.Message], can_filters: Any = None, **_: Any) -> None:
        super().__init__(channel=channel, can_filters=can_filters)
        self.channel_info = f"cmcan demo player {channel}"
        self._messages = messages
        self.sent: list[can.Message] = []
        self.played = threading.Event()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = next(self._messages, None)
        if msg is None:
            self.played.set()
            time.sleep(0.1 if timeout is None else min(timeout, 0.1))  # a silent bus: the daemon waits
        return msg, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)


def _messages(frames: Frames, rows: NDArray[np.int64], channel: str) -> Iterator[can.Message]:
    """The frames at ``rows`` as python-can messages on ``channel``, made as they are read."""
    ts = frames.timestamp_s[rows].tolist()
    fid = frames.arbitration_id[rows].tolist()
    ext = frames.is_extended()[rows].tolist()
    dlc = frames.dlc[rows].tolist()
    data = frames.data[rows]
    for i in range(len(ts)):
        f = Frame(ts[i], channel, fid[i], ext[i], False, False, False, data[i, : dlc[i]].tobytes())
        yield can.Message(**to_message_kwargs(f))


def stream(frames: Frames, cfg: cfgmod.Config, state_dir: Path, channel: str) -> tuple[list[Frame], int, int, Outputs]:
    """Play ``frames`` into the daemon, each configured channel on its own :class:`PlayerBus` (named
    after ``channel``); return the daemon's frames as sent, the counts, and what it sends as."""
    cfg, names = on_virtual_buses(cfg, channel, state_dir)
    prep = prepare(cfg)
    monitor = prep.parts.monitor
    primary = cfg.bus.channel
    # each of the log's channels on the configured channel of its name (an unnamed one on the primary)
    onto = np.array([names.get(c, primary) for c in frames.channel_names] or [primary])
    index = frames.channel_index if frames.channel_index is not None else np.zeros(len(frames), dtype=np.int64)
    buses = {
        ch.name: PlayerBus(
            messages=_messages(frames, np.flatnonzero(np.isin(index, np.flatnonzero(onto == ch.name))), ch.name),
            **bus_kwargs(cfg, ch, monitor.inputs),
        )
        for ch in cfg.channel_list
    }
    # the frames carry the time-lapse's own times: its jumps of 30 min are the log's, not wall-clock steps
    opts = DaemonOptions(stamps_on_wall_clock=False)
    daemon = Daemon(cfg, monitor, prep.store, {n: (lambda b=b: b) for n, b in buses.items()}, options=opts)
    thread = threading.Thread(target=daemon.run, name="cmcan-daemon", daemon=True)
    try:
        thread.start()
        for b in buses.values():
            while not b.played.wait(0.5) and thread.is_alive():
                pass
        deadline = time.monotonic() + 60.0
        while monitor.counters["frames_total"] < len(frames) and time.monotonic() < deadline and thread.is_alive():
            time.sleep(0.01)
        # Let the daemon's idle timer evaluate the last ticks, then stop it.
        time.sleep(daemon.opt.idle_after_s + 3 * daemon.opt.recv_timeout_s)
        daemon.stop()
        thread.join(timeout=10)
    finally:
        for b in buses.values():
            b.shutdown()
    received = [from_message(m, channel=n) for n, b in buses.items() for m in b.sent]
    return received, len(frames), monitor.counters["frames_total"], monitor.outputs


def dm1_messages(received: list[Frame], source: int) -> list[tuple[float, j1939_dm1.Lamps, list[j1939_dm1.Dtc]]]:
    """The DM1 messages ``source`` sent, single-frame and reassembled from BAM, with their times."""
    bam = BamReceiver()
    out = []
    for f in sorted(received, key=lambda x: x.timestamp_s):
        if not f.extended or j1939_ids.source_address(f.arbitration_id) != source:
            continue
        if j1939_ids.pgn(f.arbitration_id) == j1939_dm1.PGN_DM1:
            out.append((f.timestamp_s, *j1939_dm1.decode(f.data)))
            continue
        done = bam.feed(f.arbitration_id, f.data)
        if done is not None and done[1] == j1939_dm1.PGN_DM1:
            out.append((f.timestamp_s, *j1939_dm1.decode(done[2])))
    return out


_REASONS = {r: r.name.lower() for r in Reason}


def _name(names: dict[Any, str], value: float) -> str:
    """A decoded enumeration value by cmcan's name for it (the number itself if it has none)."""
    v = int(value)
    return names.get(v, str(v))


def analyse(
    received: list[Frame],
    db: Any,
    cfg: cfgmod.Config,
    start_epoch_s: float,
    failures: list[dict[str, Any]],
    outputs: Outputs | None = None,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], dict[str, bool], list[float], list[float]]:
    """Warnings as the bus shows them, the lead time before each scheduled failure, and the checks.
    ``outputs`` are the identifiers cmcan sends with (on J1939 from its own source address)."""
    warn_msg = db.get_message_by_name(cfg.outputs.warning.message)
    ratio_msg = db.get_message_by_name(cfg.outputs.cm_ratio.message)
    warn_id = outputs.warning.frame_id if outputs is not None else warn_msg.frame_id
    ratio_id = outputs.ratio.frame_id if outputs is not None else ratio_msg.frame_id
    transitions = []
    last_level = "ok"
    ratio_h, ratio_pct = [], []
    for m in sorted(received, key=lambda x: x.timestamp_s):
        if m.arbitration_id == warn_id:
            # the numbers, named by cmcan's own vocabulary: a DBC need not carry value tables
            d = warn_msg.decode(m.data, decode_choices=False)
            level, reason = _name(LEVEL_NAMES, d["warning_level"]), _name(_REASONS, d["warning_reason"])
            if level != last_level:
                transitions.append(
                    {
                        "operating_h": (m.timestamp_s - start_epoch_s) / 3600.0,
                        "from": last_level,
                        "to": level,
                        "reason": reason,
                        "warning_count": int(d["warning_count"]),
                    }
                )
                last_level = level
        elif m.arbitration_id == ratio_id:
            d = ratio_msg.decode(m.data, decode_choices=False)
            if d["cm_filt_valid"]:
                ratio_h.append((m.timestamp_s - start_epoch_s) / 3600.0)
                ratio_pct.append(float(d["cm_ratio_filt_pct"]))
    report = []
    previous = 0.0
    for f in failures:
        raised = [t for t in transitions if t["to"] in ("low", "high") and previous < t["operating_h"] <= f["fail_h"]]
        first = raised[0] if raised else None
        lead = f["fail_h"] - first["operating_h"] if first else None
        report.append(
            {
                **f,
                "first_warning_h": first["operating_h"] if first else None,
                "level": first["to"] if first else None,
                "lead_h": lead,
                "ok": bool(first is not None and lead is not None and lead >= LEAD_TIME_MIN_H),
            }
        )
        previous = f["fail_h"]
    early = [t for t in transitions if t["operating_h"] < HEALTHY_UNTIL_H and t["to"] != "ok"]
    checks = {
        f"warning >= {LEAD_TIME_MIN_H:g} h before the {f['component']} {f['kind']} failure at {f['fail_h']:g} h": f[
            "ok"
        ]
        for f in report
    }
    checks[f"no warning in the healthy first {HEALTHY_UNTIL_H:g} h"] = not early
    mis = [f for f in report if f["kind"] == "misposition"]
    if mis:
        checks["the misposition raises the high warning"] = all(f["level"] == "high" for f in mis)
    if cfg.j1939.dm1.enabled and cfg.j1939.source_address is not None:
        checks.update(dm1_checks(received, cfg, transitions, start_epoch_s))
    return transitions, report, checks, ratio_h, ratio_pct


def baseline_states(
    received: list[Frame], db: Any, cfg: cfgmod.Config, start_epoch_s: float, outputs: Outputs | None = None
) -> list[tuple[float, str]]:
    """The baseline's state at each change as CM_BASELINE frames carried it (operating h, name)."""
    if not cfg.baseline.enabled:
        return []
    msg = db.get_message_by_name(cfg.outputs.cm_baseline.message)
    fid = outputs.baseline.frame_id if outputs is not None and outputs.baseline is not None else msg.frame_id
    out: list[tuple[float, str]] = []
    for m in sorted(received, key=lambda x: x.timestamp_s):
        if m.arbitration_id == fid:
            state = int(msg.decode(m.data, decode_choices=False)["baseline_state"])
            name = MODE_NAMES.get(state, str(state))  # type: ignore[call-overload]  # IntEnum keys take ints
            if not out or out[-1][1] != name:
                out.append(((m.timestamp_s - start_epoch_s) / 3600.0, name))
    return out


def dm1_checks(
    received: list[Frame], cfg: cfgmod.Config, transitions: list[dict[str, Any]], start_epoch_s: float
) -> dict[str, bool]:
    """DM1 as a J1939 service tool would read it: after each low or high warning the amber lamp is on
    and the drive's DTC carries the matching FMI with an occurrence count; back to ok, it is off."""
    assert cfg.j1939.source_address is not None
    msgs = dm1_messages(received, cfg.j1939.source_address)
    spn = cfg.j1939.dm1.spn
    fmis = {"low": (17, 18), "high": (15, 16), "ok": ()}
    ok = bool(msgs)
    for tr in transitions:
        if tr["to"] not in fmis:
            continue
        t = start_epoch_s + tr["operating_h"] * 3600.0
        after = [m for m in msgs if m[0] >= t - 1e-6]
        if not after:
            ok = False
            continue
        _, lamps, dtcs = after[0]
        drive = [d for d in dtcs if d.spn == spn]
        if tr["to"] == "ok":
            ok &= lamps.amber_warning == j1939_dm1.Lamp.OFF and not drive
        else:
            ok &= lamps.amber_warning == j1939_dm1.Lamp.ON and any(
                d.fmi in fmis[tr["to"]] and d.occurrence >= 1 for d in drive
            )
    return {"DM1 (J1939): the amber lamp and the drive's DTC follow every warning": ok}


def frames_kind(cfg: cfgmod.Config) -> str:
    """The machine's bus in a few words, for the figure's title and the JSON."""
    fd = " on CAN FD" if cfg.frames.fd else ""
    if cfg.j1939.enabled:
        sa = cfg.j1939.source_address
        return f"J1939{fd}" + (f", cmcan at source address 0x{sa:02X}" if sa is not None else "")
    return ("29-bit" if cfg.frames.extended_ids else "11-bit") + f" identifiers{fd}"


def title_of(res: DemoResult) -> str:
    return f"cmcan demo: {res.scenario} at 480 bar through the daemon, {Path(res.config).name} ({res.frames})"


def run_demo(
    out_dir: Path, burst_s: float = 5.0, every_min: float = 30.0, plot: bool = True, config_path: str | None = None
) -> DemoResult:
    t0 = time.monotonic()
    s = demo_scenario(burst_s, every_min)
    cfg = with_baseline(scale_windows(cfgmod.load(config_path), burst_s, every_min), s)
    cfg = with_prognosis(cfg, s)
    if cfg.quantity != MOTOR_SPEED:
        raise CmcanError(
            f"{cfg.source}: drive.quantity is {cfg.quantity}: the demo simulates a closed-circuit drive, whose "
            f"output is the motor speed ({MOTOR_SPEED})",
            Kind.USAGE,
        )
    for diff in scn.drive_differences(s.params, cfg.motor_disp_cc, cfg.drive.pump_disp_max_cc, cfg.oil):
        # the shipped scenario is the reference drive: another machine's model reads it as worn
        log.warning(
            "the demo simulates the reference drive, not the machine of %s: %s; its checks assume the "
            "configured machine is the reference drive",
            cfg.source,
            diff,
        )
    db = dbc_for(cfg)
    log.info("simulating %s (%g h, %g s bursts every %g min)", s.name, s.duration_h, burst_s, every_min)
    plan = bus_plan(cfg, db)
    run = simulate(s, db, plan.mapping)
    frames = frames_from_run(run, db, plan=plan)
    state_dir = out_dir / "state"
    state_dir.mkdir(parents=True, exist_ok=True)
    for old in state_dir.glob("state.json*"):
        old.unlink()  # the demo's own state from an earlier demo run, never a user's
    channel = f"cmcan-demo-{os.getpid()}"
    log.info("streaming %d frames through the daemon on the in-process bus %s", len(frames), channel)
    received, sent, processed, outputs = stream(frames, cfg, state_dir, channel)
    failures = run.meta["scheduled_failures"]
    transitions, report, checks, rh, rp = analyse(received, db, cfg, run.start_epoch_s, failures, outputs)
    baseline = baseline_states(received, db, cfg, run.start_epoch_s, outputs)
    judge_prognosis(report, prognosis_at(received, db, cfg, run.start_epoch_s, outputs))
    if cfg.prognosis.enabled:
        judge_default_eol(frames, cfg, run.start_epoch_s, report, (rh, rp))
    for f in report:
        if f["kind"] in ("wear", "misposition") and "prognosis" in f:
            checks[
                f"hours to end of life {PROGNOSIS_BEFORE_H:g} h before the {f['component']} {f['kind']} failure "
                f"within {PROGNOSIS_WITHIN:.0%}"
            ] = f["prognosis"]["ok"]
    res = DemoResult(
        s.name,
        f"virtual:{channel}",
        cfg.source,
        frames_kind(cfg),
        sent,
        processed,
        time.monotonic() - t0,
        transitions,
        report,
        rh,
        rp,
        checks,
        windows_of(cfg),
        baseline,
    )
    learning = res.learning_h
    first_fail = min((f["fail_h"] for f in failures), default=float("inf"))
    res.checks[f"the machine learned its own baseline before {HEALTHY_UNTIL_H:g} h"] = bool(
        learning is not None and learning[1] < min(HEALTHY_UNTIL_H, first_fail) and baseline[-1][1] == "monitoring"
    )
    res.checks["every frame sent was processed"] = processed == sent
    res.prognosis = prognosis_at(received, db, cfg, run.start_epoch_s, outputs)  # the figure's (a few ms)
    res.end_of_life = end_of_life(cfg) if cfg.prognosis.enabled else {}
    if plot:
        from cmcan.plots import plot_demo

        plot_demo(res, cfg.thresholds, out_dir / "demo.png", title_of(res))
    return res
