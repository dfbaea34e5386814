"""The monitor on the example J1939 machine: matching on PGN whatever the sender's address, input
health, DM1 and its transport, occurrence counts across restarts, several channels, CAN FD."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan import config as cfgmod
from cmcan.assemble import assemble, bus_plan, dbc_for
from cmcan.can import checksums, codec
from cmcan.can.frame import Frame
from cmcan.can.j1939 import dm1, ids, transport
from cmcan.io.candump import iter_frames, write_candump, write_frames
from cmcan.monitor.diagnostics import Dm1Params, Dm1Producer
from cmcan.monitor.gating import Gate
from cmcan.monitor.totals import Totals
from cmcan.monitor.warnings import Level, Reason
from cmcan.replay import replay
from cmcan.sim import scenario as scn
from cmcan.sim.frames import Frames, frames_from_run, with_source_address
from cmcan.sim.run import simulate
from tests.conftest import ROOT, run_cli
from tests.helpers import monitor, timeline
from tests.test_j1939 import pretty

J1939_YAML = ROOT / "config" / "j1939-example.yaml"
SA = 0x8C
LEAK_AT_S = 12.0


def j1939_cfg(**sections) -> cfgmod.Config:
    """The example J1939 machine with windows short enough for a test of a few tens of seconds."""
    cfg = cfgmod.load(J1939_YAML)
    cfg = replace(
        cfg,
        filter=replace(cfg.filter, samples=20, min_samples=10),
        thresholds=replace(cfg.thresholds, debounce_s=2.0),
    )
    return replace(cfg, **sections)


def leak_scenario(seconds: float, leak_lpm: float = 15.0) -> scn.Scenario:
    events = [{"type": "leakage", "start_h": LEAK_AT_S / 3600, "extra_lpm": leak_lpm, "ref_dp_bar": 300}]
    return scn.from_dict(
        {
            "name": "j1939-test",
            "seed": 5,
            "duration_h": seconds / 3600,
            "start_epoch_s": 1767225600.0,
            "oil": {"model": "prescribed", "temp_c": 50.0},
            "duty": {"kind": "constant", "pump_speed_rpm": 2000, "pump_disp_pct": 70, "dp_bar": 300},
            "events": events if leak_lpm else [],
        }
    )


def machine_frames(cfg: cfgmod.Config, seconds: float, leak_lpm: float = 15.0) -> tuple[Frames, object]:
    db = dbc_for(cfg)
    plan = bus_plan(cfg, db)
    run = simulate(leak_scenario(seconds, leak_lpm), db, plan.mapping)
    return frames_from_run(run, db, plan=plan), plan


@pytest.fixture(scope="module")
def leak():
    cfg = j1939_cfg()
    frames, plan = machine_frames(cfg, 40.0)
    return cfg, frames, plan


def run_monitor(cfg, frames: list[Frame], totals=None):
    """The streaming core over the frames: the monitor (its timeline kept) and what it emitted."""
    mon = monitor(cfg, totals=totals)
    out: list[Frame] = []
    for f in frames:
        out += mon.feed(f)
    out += mon.flush()
    return mon, out


def dm1s(out: list[Frame]) -> list[tuple[float, dm1.Lamps, list[dm1.Dtc]]]:
    r = transport.BamReceiver()
    got = []
    for f in out:
        if ids.pgn(f.arbitration_id) == dm1.PGN_DM1:
            got.append((f.timestamp_s, *dm1.decode(f.data)))
        elif (done := r.feed(f.arbitration_id, f.data)) is not None and done[1] == dm1.PGN_DM1:
            got.append((f.timestamp_s, *dm1.decode(done[2])))
    return got


def test_the_example_machine_evaluates_warns_and_sends_from_its_own_address(leak):
    cfg, frames, _ = leak
    mon, out = run_monitor(cfg, frames.to_frames())
    c = mon.counters
    assert c["accepted"] == len(frames) and c["unknown_id"] == c["checksum"] == c["counter_jump"] == 0
    assert c["evaluated"] > 100
    assert [h["to"] for h in mon.totals.history] == ["low"]
    assert all(f.extended and ids.source_address(f.arbitration_id) == SA for f in out)
    ratio = [f for f in out if ids.pgn(f.arbitration_id) == 0xFF20]
    assert ratio and all(ids.priority(f.arbitration_id) == 6 for f in ratio)
    # J1939: bits no signal occupies go out as 1 (CM_RATIO's bits 50-51)
    assert all(f.data[6] & 0x0C == 0x0C for f in ratio)


def test_a_controller_that_claims_another_address_still_decodes(leak):
    cfg, frames, plan = leak
    db = dbc_for(cfg)
    moved = frames
    for name in ("HST_PUMP", "HST_MOTOR", "HST_LOOP_PRESSURE", "VF"):
        moved = with_source_address(moved, db, plan, name, 0x04, frames.timestamp_s[0] + 20.0)
    assert (ids.source_address(moved.arbitration_id) == 0x04).sum() > len(frames) / 3
    base, _ = run_monitor(cfg, frames.to_frames())
    mon, _ = run_monitor(cfg, moved.to_frames())
    assert mon.counters["accepted"] == len(frames) and mon.counters["checksum"] == 0
    assert [tk.gate for tk in timeline(mon)] == [tk.gate for tk in timeline(base)]
    assert [tk.ratio_filt_pct for tk in timeline(mon)] == [tk.ratio_filt_pct for tk in timeline(base)]
    # A machine that names its sender's address ignores the frames from another one: stale, then a fault
    only3 = {n: replace(cfg.message(n), source_addresses=(3,), source_addresses_set=True) for n in plan.counter}
    narrow, _ = run_monitor(replace(cfg, messages=only3), moved.to_frames())
    assert narrow.counters["unknown_id"] > 0
    assert narrow.totals.history[-1]["to"] == "fault" and narrow.totals.history[-1]["reason"] == "input_stale"


def test_dm1_follows_the_warning_and_an_independent_decoder_agrees(leak, tmp_path):
    cfg, frames, _ = leak
    mon, out = run_monitor(cfg, frames.to_frames())
    msgs = dm1s(out)
    t_low = mon.totals.history[0]["t_s"]
    before = [m for m in msgs if m[0] < t_low]
    after = [m for m in msgs if m[0] >= t_low]
    assert before and all(not d and lamps.amber_warning == dm1.Lamp.OFF for _, lamps, d in before)
    _, lamps, dtcs = after[0]
    assert lamps.amber_warning == dm1.Lamp.ON and [(d.spn, d.occurrence) for d in dtcs] == [(520192, 1)]
    assert dtcs[0].fmi in (17, 18)
    assert after[0][0] - t_low < 0.2  # sent at once on the change, not at the next second
    # once a second otherwise (the tick grid, in frame time)
    periodic = np.array([t for t, *_ in msgs])
    assert np.median(np.diff(periodic)) == pytest.approx(1.0, abs=1e-6)
    # pretty-j1939 reads the same lamp, SPN, FMI and count from the frames cmcan emitted
    seen = [m for m in pretty([f for f in out if ids.pgn(f.arbitration_id) == dm1.PGN_DM1], tmp_path)]
    last = seen[-1]
    assert last["Amber Warning Lamp Status"] == "On"
    assert last["DTC 1"] == f"SPN 520192 (Unknown), FMI {msgs[-1][2][0].fmi}, OC 1"
    assert seen[0]["Amber Warning Lamp Status"] == "Off" and "DTC 1" not in seen[0]


def freeze_counter(frames: Frames, cfg, plan, message: str, from_s: float) -> Frames:
    """The sender's task hangs: ``message`` keeps its counter from ``from_s`` on (checksums still right)."""
    db = dbc_for(cfg)
    msg = db.get_message_by_name(message)
    same = ids.pgn(frames.arbitration_id) == ids.pgn(msg.frame_id)  # whatever address it sends from
    rows = same & frames.is_extended() & (frames.timestamp_s >= from_s)
    data = frames.data.copy()
    data[rows, 7] = (data[rows, 7] & 0xF0) | 5
    sig, algorithm = plan.checksum[message]
    data[rows] = checksums.seal(algorithm, 8, codec.layout(msg, sig), frames.arbitration_id[rows], data[rows])
    return replace(frames, data=data)


def test_a_frozen_counter_is_a_fault_and_two_dtcs_go_over_bam(leak, tmp_path):
    cfg, frames, plan = leak
    t0 = float(frames.timestamp_s[0])
    frozen = freeze_counter(frames, cfg, plan, "HST_MOTOR", t0 + 25.0)
    mon, out = run_monitor(cfg, frozen.to_frames())
    assert mon.counters["counter_frozen"] > 900
    hist = [(h["to"], h["reason"]) for h in mon.totals.history]
    assert hist == [("low", "ratio_low"), ("fault", "input_implausible")]
    t_fault = mon.totals.history[1]["t_s"]
    assert t_fault - (t0 + 25.0) == pytest.approx(cfg.thresholds.fault_after_s, abs=0.25)
    # the BAM: TP.CM then the packets 100 ms apart, priority 7, to all
    cms = [f for f in out if ids.pgn(f.arbitration_id) == transport.PGN_TP_CM]
    assert cms and all(f.timestamp_s >= t_fault for f in cms)
    first = out.index(cms[0])
    dts = [f for f in out[first:] if ids.pgn(f.arbitration_id) == transport.PGN_TP_DT][:2]
    assert [round(f.timestamp_s - cms[0].timestamp_s, 6) for f in dts] == [0.1, 0.2]
    assert [ids.priority(f.arbitration_id) for f in (cms[0], *dts)] == [7, 7, 7]
    assert all(out[i].timestamp_s <= out[i + 1].timestamp_s for i in range(len(out) - 1))
    _, lamps, dtcs = next(m for m in dm1s(out) if m[0] >= t_fault)
    assert lamps.amber_warning == dm1.Lamp.ON
    assert [(d.spn, d.fmi, d.occurrence) for d in dtcs][1:] == [(520193, 2, 1)]
    got = [m for m in pretty([cms[0], *dts], tmp_path) if m.get("PGN") == "DM1(65226)"]
    assert got[0]["DTC 2"] == "SPN 520193 (Unknown), FMI 2, OC 1"
    assert got[0]["DTC 1"].startswith("SPN 520192 (Unknown), FMI 1")


def test_a_missing_message_is_stale_after_its_timeout_fmi_9(leak):
    cfg, frames, _ = leak
    t0 = float(frames.timestamp_s[0])
    vf = frames.arbitration_id == dbc_for(cfg).get_message_by_name("VF").frame_id
    cut = frames.select(~(vf & (frames.timestamp_s > t0 + 5.0)))
    mon, out = run_monitor(cfg, cut.to_frames())
    assert mon.totals.history[0]["reason"] == "input_stale"
    assert mon.snapshot()["inputs"]["VF"]["timeout"] == 1
    assert mon.counters["timeout"] == 1  # the monitor's total, as in its summaries and state
    last = dm1s(out)[-1]
    assert [(d.spn, d.fmi) for d in last[2]] == [(520193, 9)]
    assert last[1].amber_warning == dm1.Lamp.OFF  # a fault alone lights no lamp


def p(**kw):
    base = {
        "spn": 520192,
        "input_spn": 520193,
        "low_severe_pct": 96.0,
        "high_severe_pct": 104.0,
        "hysteresis_pct": 0.5,
        "every_ticks": 10,
        "source": SA,
    }
    return Dm1Params(**{**base, **kw})


def test_occurrence_counts_and_severity_survive_a_restart():
    totals = Totals()
    d = Dm1Producer(p(), totals)
    d.step(1, 0.1, Level.LOW, Reason.NONE, 97.0)
    d.step(2, 0.2, Level.OK, Reason.NONE, 99.0)
    d.step(3, 0.3, Level.LOW, Reason.NONE, 97.0)
    d.step(4, 0.4, Level.LOW, Reason.NONE, 95.0)  # below the second threshold: FMI 18
    assert totals.dtc_occurrences == {"520192:17": 2, "520192:18": 1} and totals.dtc_active == ["520192:18"]
    back = Totals.from_dict(json.loads(json.dumps(totals.to_dict())))
    again = Dm1Producer(p(), back)
    frames = again.step(10, 1.0, Level.LOW, Reason.NONE, None)  # nothing evaluated yet after the restart
    assert back.dtc_occurrences == {"520192:17": 2, "520192:18": 1}  # not counted again
    assert dm1.decode(frames[0].data)[1] == [dm1.Dtc(520192, 18, 1)]
    again.step(11, 1.1, Level.LOW, Reason.NONE, 96.2)  # within the hysteresis: still moderately severe
    assert back.dtc_active == ["520192:18"]
    again.step(12, 1.2, Level.LOW, Reason.NONE, 96.6)
    assert back.dtc_active == ["520192:17"] and back.dtc_occurrences["520192:17"] == 3


def test_occurrence_counts_saturate_and_bad_state_is_refused():
    totals = Totals(dtc_occurrences={"520193:9": 126})
    d = Dm1Producer(p(), totals)
    d.step(1, 0.1, Level.OK, Reason.INPUT_STALE, None)
    assert totals.dtc_occurrences["520193:9"] == 126
    from cmcan.monitor.totals import StateError

    doc = Totals().to_dict()
    for bad in ({"dtc_occurrences": {"520192:17": 200}}, {"dtc_occurrences": {"x": 1}}, {"dtc_active": ["1:99"]}):
        with pytest.raises(StateError):
            Totals.from_dict({**doc, **bad})
    old = {k: v for k, v in doc.items() if not k.startswith("dtc_")}  # a state file from before DM1
    assert Totals.from_dict(old).dtc_occurrences == {}


def test_a_change_during_a_bam_waits_for_its_last_packet():
    d = Dm1Producer(p(), Totals())
    first = d.step(10, 1.0, Level.LOW, Reason.INPUT_STALE, 97.0)  # two DTCs: BAM until 1.2 s
    assert len(first) == 3 and first[-1].timestamp_s == pytest.approx(1.2)
    assert d.step(11, 1.1, Level.LOW, Reason.NONE, 97.0) == []  # the fault cleared during the BAM
    assert d.step(12, 1.2, Level.LOW, Reason.NONE, 97.0) == []
    late = d.step(13, 1.3, Level.LOW, Reason.NONE, 97.0)
    assert len(late) == 1 and dm1.decode(late[0].data)[1] == [dm1.Dtc(520192, 17, 1)]


# -- several channels, log channel names, CAN FD -----------------------------------------------------------


def two_channel_cfg(cfg: cfgmod.Config) -> cfgmod.Config:
    extra = (cfgmod.ChannelConfig("can1", 500000, False),)
    msgs = {
        **cfg.messages,
        "VF": cfgmod.MessageConfig(channel="can1"),
        "HST_MOTOR": replace(cfg.message("HST_MOTOR"), channel="can1"),
    }
    return replace(cfg, channels=replace(cfg.channels, extra=extra), messages=msgs)


def test_inputs_split_over_two_channels_replay_as_two_buses(leak, tmp_path):
    cfg, frames, _ = leak
    two = two_channel_cfg(cfg)
    db = dbc_for(two)
    plan = bus_plan(two, db)
    split = frames_from_run(simulate(leak_scenario(40.0), db, plan.mapping), db, plan=plan)
    assert set(split.channels("can0")) == {"can0", "can1"}
    log = tmp_path / "two.log"
    write_candump(
        log, split.timestamp_s, split.arbitration_id, split.dlc, split.data, split.channels("can0"), split.is_extended()
    )
    assert {f.channel for f in iter_frames(log)} == {"can0", "can1"}
    base, base_out = run_monitor(cfg, frames.to_frames())
    mon, out = run_monitor(two, list(iter_frames(log)))
    assert mon.counters["accepted"] == len(split)
    assert [tk.ratio_filt_pct for tk in timeline(mon)] == [tk.ratio_filt_pct for tk in timeline(base)]
    assert [(f.arbitration_id, f.data) for f in out] == [(f.arbitration_id, f.data) for f in base_out]
    # the same log with the single-channel configuration: every log channel is read as its one channel
    one, _ = run_monitor(cfg, list(iter_frames(log)))
    assert one.counters["accepted"] == len(split) and one.channels_seen() == {"can0": "can0", "can1": "can0"}
    # ... unless the aliases name which log channel it is: the others are on no configured channel
    only0 = assemble(cfg, log_aliases={"can0": "can0"}).monitor
    replay(only0, iter_frames(log))
    assert only0.counters["unknown_channel"] == sum(c == "can1" for c in split.channels("can0"))
    # a two-channel configuration renamed for the bench (vcan0/vcan1) reads the log through aliases
    renamed = cfgmod.rename_channels(two, {"can0": "vcan0", "can1": "vcan1"})
    mon2 = monitor(renamed, log_aliases={"can0": "vcan0", "can1": "vcan1"})
    replay(mon2, iter_frames(log))
    assert mon2.counters["accepted"] == len(split)


def test_a_log_from_another_channel_name_replays_on_a_single_channel_config(leak):
    cfg, frames, _ = leak
    mon, _ = run_monitor(cfgmod.with_overrides(cfg, channel="vcan0"), frames.to_frames("can3"))
    assert mon.counters["accepted"] == len(frames)


def test_can_fd_frames_are_inputs_only_on_an_fd_bus(leak):
    cfg, frames, _ = leak
    fd_frames = [f._replace(fd=True) for f in frames.to_frames()]
    classic, _ = run_monitor(cfg, fd_frames)
    assert classic.counters["bad_fd"] == len(frames) and classic.counters["accepted"] == 0
    fd_cfg = replace(cfg, frames=replace(cfg.frames, fd=True))
    fd_mon, _ = run_monitor(fd_cfg, fd_frames)
    plain, _ = run_monitor(cfg, frames.to_frames())
    assert fd_mon.counters["accepted"] == len(frames)
    assert [tk.ratio_filt_pct for tk in timeline(fd_mon)] == [tk.ratio_filt_pct for tk in timeline(plain)]


def test_replay_cli_on_a_j1939_log_writes_extended_frames_with_channels(leak, tmp_path):
    _, frames, _ = leak
    log = tmp_path / "in.log"
    write_frames(log, frames.to_frames())
    emit = tmp_path / "out.log"
    r = run_cli("replay", str(log), "--config", str(J1939_YAML), "--emit", str(emit), "--json")
    assert r.returncode == 0, r.stderr
    lines = emit.read_text().splitlines()
    assert lines and all(" can0 " in x and len(x.split()[2].split("#")[0]) == 8 for x in lines)
    summary = json.loads(r.stdout)
    assert summary["final"]["inputs"]["HST_PUMP"]["checksum"] == 0


def test_cli_channel_map_names_which_log_channel_is_which(leak, tmp_path):
    _, frames, _ = leak
    log = tmp_path / "in.log"
    write_frames(log, frames.to_frames("can1"))
    r = run_cli("replay", str(log), "--config", str(J1939_YAML), "--channel-map", "can9=can0", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["final"]["counters"]["unknown_channel"] == len(frames)
    r = run_cli("replay", str(log), "--config", str(J1939_YAML), "--channel-map", "can1=can0", "--json")
    assert json.loads(r.stdout)["final"]["counters"]["accepted"] == len(frames)
    r = run_cli("replay", str(log), "--config", str(J1939_YAML), "--channel-map", "can1")
    assert r.returncode == 64 and "--channel-map" in r.stderr


def write_variant(tmp_path: Path, edit) -> Path:
    import yaml

    raw = yaml.safe_load(J1939_YAML.read_text())
    raw["dbc"] = str(ROOT / "dbc" / "j1939-example.dbc")
    edit(raw)
    path = tmp_path / "variant.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


@pytest.mark.parametrize(
    ("edit", "field", "text"),
    [
        (lambda r: (r.pop("j1939"), r.pop("frames")), "signals.pump_speed_rpm.message", "29-bit identifiers are off"),
        (lambda r: r["frames"].update(extended_ids=False), "frames.extended_ids", "J1939 needs 29-bit"),
        (lambda r: r["j1939"].update(enabled=False), "j1939.dm1.enabled", "set j1939.enabled"),
        (lambda r: r["messages"].update(VF={"channel": "can7"}), "messages.VF.channel", "not a configured channel"),
        (lambda r: r["messages"].update(CM_RATIO={}), "messages.CM_RATIO", "not an input message"),
        (lambda r: r["messages"].pop("HST_PUMP"), "messages.HST_PUMP.checksum", "name its algorithm"),
        (
            lambda r: r["messages"].update(VF={"checksum": "crc8_sae_j1850"}),
            "messages.VF.checksum",
            "no checksum signal",
        ),
        (
            lambda r: r["messages"]["HST_MOTOR"].update(counter="motor_speed"),
            "messages.HST_MOTOR.counter",
            "carries motor_speed_rpm",
        ),
        (
            lambda r: (
                r["messages"]["VF"].update(counter="nope")
                if "VF" in r["messages"]
                else r["messages"].update(VF={"counter": "nope"})
            ),
            "messages.VF.counter",
            "no signal 'nope'",
        ),
        (lambda r: r["j1939"].update(source_addresses=[140]), "j1939.source_addresses", "own address"),
        (lambda r: r["j1939"]["dm1"].update(low_severe_pct=99.0), "j1939.dm1.low_severe_pct", "below thresholds"),
        (lambda r: r["j1939"]["dm1"].update(spn=1638), "j1939.dm1.spn", "520192"),
        (lambda r: r.update(channels={"outputs": "can1"}), "channels.outputs", "not a configured channel"),
    ],
)
def test_check_refuses_what_cannot_be_evaluated(tmp_path, edit, field, text):
    path = write_variant(tmp_path, edit)
    r = run_cli("check", "--config", str(path))
    assert r.returncode == 78, r.stdout + r.stderr
    assert f"{path}: {field}:" in r.stderr and text in r.stderr, r.stderr


def test_check_refuses_source_addresses_on_an_11_bit_machine(tmp_path):
    import yaml

    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    raw["messages"] = {"PUMP_STATUS": {"source_addresses": [3]}}
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(raw))
    r = run_cli("check", "--config", str(path))
    assert r.returncode == 78 and "messages.PUMP_STATUS.source_addresses: source addresses are J1939's" in r.stderr


def test_training_and_diagnosis_read_j1939_logs_by_the_same_matching(leak, tmp_path):
    from cmcan.assemble import frame_matcher
    from cmcan.model.features import DataError, load_operating_points

    cfg, frames, _ = leak
    log = tmp_path / "j.log"
    write_frames(log, frames.to_frames())
    db = dbc_for(cfg)
    op = load_operating_points(log, cfg.gate_limits, db, cfg.signals, cfg.rate_hz, match=frame_matcher(cfg, db))
    mon, _ = run_monitor(cfg, frames.to_frames())
    assert op.steady.sum() == pytest.approx(mon.counters["evaluated"], rel=0.05)
    with pytest.raises(DataError, match="no frames for"):  # by identifier alone, 29-bit frames are not read
        load_operating_points(log, cfg.gate_limits, db, cfg.signals, cfg.rate_hz)


SEEN_DM1: set[str] = set()


@given(
    st.lists(
        st.tuples(
            st.sampled_from([Level.OK, Level.LOW, Level.HIGH]),
            st.sampled_from([Reason.NONE] * 3 + [Reason.INPUT_STALE, Reason.INPUT_IMPLAUSIBLE]),
            st.one_of(st.none(), st.floats(90.0, 110.0)),
            st.integers(1, 4),  # ticks on: the warning state holds that long
        ),
        min_size=1,
        max_size=30,
    )
)
@settings(max_examples=150, deadline=None)
def check_dm1_producer(steps):
    totals = Totals()
    d = Dm1Producer(p(), totals)
    k = 0
    prev_keys: list[str] = []
    counts: dict[str, int] = {}
    session_end = -1.0
    for cond, fault, ratio, hold in steps:
        for _ in range(hold):
            k += 1
            t = k * 0.1
            frames = d.step(k, t, cond, fault, ratio)
            keys = [f"{s}:{f}" for s, f in d.dtcs(cond, fault)]
            for key in keys:
                if key not in prev_keys:
                    counts[key] = counts.get(key, 0) + 1
            prev_keys = keys
            assert totals.dtc_active == keys and totals.dtc_occurrences == counts
            if not frames:
                if k % 10 == 0:
                    SEEN_DM1.add("periodic deferred by a BAM")
                continue
            assert frames[0].timestamp_s == t > session_end  # one BAM at a time
            if len(frames) == 1:
                lamps, dtcs = dm1.decode(frames[0].data)
                assert len(frames[0].data) == 8 and len(keys) <= 1
                SEEN_DM1.add("single frame" if keys else "no DTC")
            else:
                assert len(keys) == 2 and len(frames) == 3
                r = transport.BamReceiver()
                payload = [r.feed(f.arbitration_id, f.data) for f in frames][-1][2]
                lamps, dtcs = dm1.decode(payload)
                session_end = frames[-1].timestamp_s
                SEEN_DM1.add("BAM")
            assert [f"{x.spn}:{x.fmi}" for x in dtcs] == keys
            assert [x.occurrence for x in dtcs] == [counts[key] for key in keys]
            assert lamps.amber_warning == (dm1.Lamp.ON if cond != Level.OK else dm1.Lamp.OFF)
            if any(key.endswith((":18", ":16")) for key in keys):
                SEEN_DM1.add("moderately severe")


def test_dm1_producer_keeps_its_rules_and_reaches_every_case():
    SEEN_DM1.clear()
    check_dm1_producer()
    assert {"no DTC", "single frame", "BAM", "moderately severe", "periodic deferred by a BAM"} <= SEEN_DM1, SEEN_DM1


def test_a_wrong_checksum_is_refused_and_makes_the_point_implausible(leak):
    cfg, frames, _ = leak
    db = dbc_for(cfg)
    t0 = float(frames.timestamp_s[0])
    pump = (frames.arbitration_id == db.get_message_by_name("HST_PUMP").frame_id) & (
        np.abs(frames.timestamp_s - (t0 + 8.0)) < 0.5
    )
    data = frames.data.copy()
    data[pump, 2] ^= 0x01  # one bit of the displacement, checksum left as it was
    mon, _ = run_monitor(cfg, replace(frames, data=data).to_frames())
    assert mon.counters["checksum"] == int(pump.sum()) == mon.snapshot()["inputs"]["HST_PUMP"]["checksum"]
    gates = {round(tk.t_s - t0, 1): tk.gate for tk in timeline(mon)}
    assert gates[8.0] == Gate.IMPLAUSIBLE_INPUT and gates[10.0] != Gate.IMPLAUSIBLE_INPUT
