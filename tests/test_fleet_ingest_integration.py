"""``cmcan fleet ingest`` end to end against a real mosquitto: 20 gateways, each a real ``cmcan uplink``
process publishing its outbox (written by the monitor from a simulated run, as the daemon writes it),
the ingest as a real process killed with SIGKILL twice mid-run and the broker restarted once;
afterwards every published id is in the data set exactly once, the hostile messages are in the
quarantine with their reasons, no file lies outside a commit, and the plan from the uplink equals
the plan from the same machines' logs.

The gateways' runs are prepared in two processes at once (a run is cheap to simulate; its two
replays, into the log-derived data set and through the monitor into the outbox, are not), and the
uplinks are started together. ``CMCAN_INGEST_GATEWAYS`` sets another number of gateways."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest

pytest.importorskip("pyarrow")

from cmcan.fleet import dataset as ds
from cmcan.fleet import uplinkstore as store
from cmcan.fleet.uplinkrows import UPLINK_QUARANTINE, UPLINK_TABLES
from cmcan.uplink.outbox import open_outbox
from tests.uplink_support import Broker, needs_mosquitto

pytestmark = [needs_mosquitto, pytest.mark.slow]

GATEWAYS = int(os.environ.get("CMCAN_INGEST_GATEWAYS", "20"))
LEAKS_LPM = (0.0, 6.0, 12.0)  # by turns: healthy, a warning that clears, a warning at the end
SUMMARY_EVERY_S = 10.0  # the uplink's shortest period: some 36 summaries from each 6 min log


def gateway_config(d: Path, machine: str, port: int) -> Path:
    """A gateway's configuration: the reference drive, its uplink to the broker on ``port``."""
    from tests.uplink_support import uplink_config

    state = d / machine
    state.mkdir(exist_ok=True)
    path = uplink_config(d / f"{machine}.yaml", state, port, machine_id=machine, summary_every_s=SUMMARY_EVERY_S,
                         mqtt={"reconnect_min_s": 0.1, "reconnect_max_s": 0.5})  # fmt: skip
    with open(path, "a") as f:
        f.write("baseline: {enabled: true}\nprognosis: {enabled: true}\n")
    return path


def prepare_gateway(d: Path, machine: str, i: int, logs_root: Path) -> int:
    """A machine's simulated log, replayed into the log-derived data set by ``fleet replay``'s task and
    through the monitor with the daemon's uplink feed into its gateway's outbox; the outbox's size.
    (The broker's port is not known yet: the configuration is written again before the uplink starts.)"""
    from cmcan import config as cfgmod
    from cmcan.daemon.preflight import prepare
    from cmcan.fleet.task import LogJob, Options, process_log
    from cmcan.replay import replay_file
    from cmcan.uplink.feed import UplinkFeed
    from tests.helpers import sim_frames, write_log

    leak = LEAKS_LPM[i % len(LEAKS_LPM)]
    events = [{"type": "leakage", "component": "loop", "start_h": 0.01, "extra_lpm": leak, "ref_dp_bar": 300}]
    _run, frames = sim_frames("single_set_leakage", duration_h=0.1, events=events if leak else [], seed=i)
    log = write_log(d / f"{machine}.log", frames)
    path = gateway_config(d, machine, 1)
    assert process_log(LogJob(machine, str(log), config=str(path)), Options(dataset=str(logs_root)))["status"] == "done"
    cfg = cfgmod.load(path)
    mon = prepare(cfg).parts.monitor
    feed = UplinkFeed.open(cfg.uplink, mon)
    mon.listeners.append(feed)
    replay_file(str(log), mon)
    feed.close()  # the last period's summary, as the daemon writes it at shutdown
    box = open_outbox(cfg.uplink.outbox.path, durable=False)
    n = box.count()
    box.close()
    return n


def start_uplink(config: Path, log: Path) -> subprocess.Popen[bytes]:
    """The real ``cmcan uplink``, until its outbox is empty and acknowledged (exit 0)."""
    with open(log, "ab") as f:
        return subprocess.Popen(
            [sys.executable, "-m", "cmcan", "-v", "uplink", "--config", str(config), "--drain", "--timeout", "300"],
            stdout=f, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip


def start_ingest(port: int, out: Path, log: Path) -> subprocess.Popen[bytes]:
    with open(log, "ab") as f:
        return subprocess.Popen(
            [sys.executable, "-m", "cmcan", "fleet", "ingest", "--broker", f"mqtt://127.0.0.1:{port}",
             "--out", str(out), "--batch", "10", "--batch-wait-s", "0.1", "--fold-every", "4"],
            stdout=f, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip


def wait(pred, timeout_s: float, what: str, log: Path | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.05)
    raise AssertionError(f"{what} not within {timeout_s} s\n{log.read_text() if log else ''}")


def subscribed_times(log: Path) -> int:
    return log.read_text().count("subscribed to") if log.exists() else 0


def rows(root: Path) -> dict[str, list[dict]]:
    import pyarrow.parquet as pq

    out: dict[str, list[dict]] = {}
    for table, files in store.committed_files(root)[0].items():
        for machine, p in files:  # a flat file's rows carry their machine (the quarantine's its own)
            got = pq.read_table(p).to_pylist()
            out.setdefault(table, []).extend(got if machine is None else ({**r, "machine": machine} for r in got))
    return out


def outbox_left(root: Path, machines: list[str]) -> int:
    return sum(open_outbox(root / m / "outbox.sqlite", durable=False).count() for m in machines)


def test_nothing_lost_nothing_doubled_through_kills_and_a_broker_restart(tmp_path):
    machines = [f"gw-{i:02d}" for i in range(GATEWAYS)]
    logs_root = ds.open_dataset(tmp_path / "logs-ds", create=True)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("fork")) as pool:
        sizes = pool.map(prepare_gateway, [tmp_path] * GATEWAYS, machines, range(GATEWAYS), [logs_root] * GATEWAYS)
        published = dict(zip(machines, sizes, strict=True))
    conf = ["allow_anonymous true", "persistence true", f"persistence_location {tmp_path}/", "max_queued_messages 0"]
    broker = Broker(tmp_path, conf=conf).start()
    out, log = tmp_path / "ds", tmp_path / "ingest.log"
    uplinks: dict[str, subprocess.Popen[bytes]] = {}
    ingest = start_ingest(broker.port, out, log)
    try:
        wait(lambda: subscribed_times(log) >= 1, 30, "the ingest's subscription", log)
        # hostile messages from a misbehaving client, beside the gateways
        import paho.mqtt.client as mqtt
        from paho.mqtt.enums import CallbackAPIVersion

        bad = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="hostile")
        bad.connect("127.0.0.1", broker.port)
        bad.loop_start()
        for tp, body in (("cmcan/gw-00/summary", b"{not json"), ("cmcan/../summary", b"{}"),
                         ("cmcan/gw-00/event", b"[" * 50_000), ("cmcan/gw-00/summary", b"x" * 10_000_000),
                         ("cmcan/gw-00/summary", b'{"schema": 99, "kind": "summary"}')):  # fmt: skip
            bad.publish(tp, body, qos=1).wait_for_publish(10)
        bad.disconnect()
        bad.loop_stop()
        for m in machines:  # all at once: they start (and publish) side by side
            uplinks[m] = start_uplink(gateway_config(tmp_path, m, broker.port), tmp_path / f"{m}-uplink.log")

        def commits() -> int:
            return len(store.record_paths(out))

        for kill in range(2):  # SIGKILL twice while batches are being committed
            n = commits()
            wait(lambda n=n: commits() >= n + 2, 60, f"commits before kill {kill + 1}", log)
            ingest.send_signal(signal.SIGKILL)
            ingest.wait(10)
            if kill == 0:  # the broker restarted (its persistence keeps the ingest's session and queue)
                broker.kill(signal.SIGTERM)
                broker.start()
            ingest = start_ingest(broker.port, out, log)
        for m, proc in uplinks.items():
            rc = proc.wait(300)
            assert rc == 0, (m, rc, (tmp_path / f"{m}-uplink.log").read_text()[-3000:])
        assert outbox_left(tmp_path, machines) == 0, "the gateways' outboxes did not drain"
        total = sum(published.values())
        wait(lambda: sum(len(r) for t, r in rows(out).items() if t in UPLINK_TABLES[:3]) >= total, 60,
             "every entry in the data set", log)  # fmt: skip
        ingest.send_signal(signal.SIGTERM)
        assert ingest.wait(20) == 0, log.read_text()
    finally:
        if ingest.poll() is None:
            ingest.kill()
        for proc in uplinks.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
        broker.kill()

    text = log.read_text()
    assert text.count("connected to") >= 3 and "Traceback" not in text, text
    got = rows(out)
    entries = [r for t in ("uplink_summaries", "uplink_events", "uplink_dropped") for r in got.get(t, [])]
    ids = [(r["machine"], r["id"]) for r in entries]
    assert len(ids) == len(set(ids)) == sum(published.values())  # every id once: nothing lost, nothing doubled
    for m in machines:
        assert sorted(r["seq"] for r in entries if r["machine"] == m) == list(range(1, published[m] + 1))
    assert {r["to_level"] for r in got["uplink_events"] if r["type"] == "level_change"} == {"low", "ok"}
    assert {r["machine"] for r in got["uplink_status"]} == set(machines)
    reasons = sorted(r["reason"].split(" (")[0] for r in got[UPLINK_QUARANTINE])
    for want in ("payload is not JSON", "machine id", "payload nested too deep", "payload of 10000000 bytes",
                 "schema 99 is newer"):  # fmt: skip
        assert sum(r.startswith(want) for r in reasons) == 1, (want, reasons)
    # no file outside a commit, no staging left behind
    records, problems = store.read_records(out)
    assert not problems
    listed = {store.place_of(out, f) for r in records for f in r.files} | set(store.record_paths(out))
    on_disk = {p for p in out.rglob("*.parquet")}
    assert on_disk == listed
    assert not list((out / ds.STAGING).glob("ingest-*"))
    assert json.loads((out / "_dataset.json").read_text())["format"] == ds.FORMAT

    # the plan from the gateways' uplink is the plan from the same machines' logs
    from cmcan.fleet.plan import build

    now = time.time()
    from_logs = {r.machine: r for r in build(logs_root, None, now)}
    from_uplink = {r.machine: r for r in build(out, None, now)}
    assert sorted(from_logs) == sorted(from_uplink) == machines
    for m in machines:
        a, b = from_logs[m], from_uplink[m]
        assert (b.source, a.source) == ("uplink", "logs")
        keys = ("warning_level", "baseline_state", "prognosis_state", "direction", "group", "to_eol_h")
        assert {k: getattr(b, k) for k in keys} == {k: getattr(a, k) for k in keys}, m
        assert b.operating_h == pytest.approx(a.operating_h, abs=SUMMARY_EVERY_S / 3600.0)
    assert GATEWAYS < 3 or {r.warning_level for r in from_logs.values()} == {"ok", "low"}
