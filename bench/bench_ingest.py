"""Benchmark: ``cmcan fleet ingest`` end to end against a local mosquitto.

Summaries of ``--machines`` machines (the uplink's payloads, about 1.9 kB each) are published with QoS 1
at ``--rate`` per second for ``--seconds`` (0: as fast as the broker takes them); the ingest runs as a
real process and commits them into a fresh data set. Printed: the publish rate, the ingest's rate
(messages committed per second of its run, from the first message to the last commit), its CPU
seconds, and its resident memory over the run (first, peak and last sample of VmRSS), so a rise over
a long run shows. The commit records are read as they appear (the rows they hold).

    python bench/bench_ingest.py [--machines 100] [--messages 20000] [--rate 0] [--batch 1000]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from cmcan.fleet import dataset as ds
from cmcan.fleet import ingest as ig
from cmcan.uplink.records import dumps, envelope

T0 = 1767225600.0


def summary_body(i: int) -> str:
    stat = {"n": 4725, "mean": 99.8038, "std": 0.0273, "min": 99.7414, "max": 99.8799}
    counters = {k: i for k in ("frames_total", "accepted", "unknown_id", "bad_length", "late", "ticks", "evaluated")}
    return dumps(
        {
            "window": {"start_s": T0, "every_s": 60.0, "ticks_sampled": 600, "closed_by": "period"},
            "level": "ok",
            "reason": "none",
            "ratio_filt_pct": 99.81,
            "extra_leak_lpm": 0.13,
            "ratio_raw_pct": stat,
            "correction_pct": stat,
            "motor_speed_rpm": stat,
            "gate_ticks": {"evaluating": 4725, "low_speed": 3780, "transient": 495},
            "time_in_level_s": {"ok": 60.0, "low": 0.0, "high": 0.0, "fault": 0.0},
            "time_in_level_total_s": {"ok": 60.0 * i, "low": 0.0, "high": 0.0, "fault": 0.0},
            "evaluated_s": 31.5,
            "evaluated_total_h": i / 60.0,
            "warning_count": 0,
            "fault_count": 0,
            "counters": counters,
            "counters_total": counters,
            "baseline": {"state": "monitoring", "learned_h": 40.0, "coverage_pct": 80.0, "distance_lpm": 0.1},
            "prognosis": {"state": "none", "direction": None, "to_warning_h": None, "to_eol_h": [None, None, None]},
        }
    )


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=100)
    ap.add_argument("--messages", type=int, default=20000)
    ap.add_argument("--rate", type=float, default=0.0, help="messages per second (0: as fast as possible)")
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--batch-wait-s", type=float, default=0.5)
    a = ap.parse_args()
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    work = Path(tempfile.mkdtemp(prefix="bench-ingest-"))
    port = 18000 + os.getpid() % 1000
    (work / "m.conf").write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous true\nmax_queued_messages 0\n"
        + ("user root\n" if os.geteuid() == 0 else "")
    )
    broker = subprocess.Popen([mosquitto, "-c", str(work / "m.conf")], stderr=subprocess.DEVNULL)
    time.sleep(0.5)
    out = work / "ds"
    cmd = [sys.executable, "-m", "cmcan", "fleet", "ingest", "--broker", f"mqtt://127.0.0.1:{port}", "--out", str(out),
           "--batch", str(a.batch), "--batch-wait-s", str(a.batch_wait_s)]  # fmt: skip
    log = open(work / "ingest.log", "wb")  # noqa: SIM115 - open for the ingest's life
    ingest = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
    while "subscribed to" not in (work / "ingest.log").read_text():
        time.sleep(0.05)
    cpu0 = cpu_s(ingest.pid)
    bodies = [summary_body(i) for i in range(50)]
    pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-publisher")
    pub.max_inflight_messages_set(1000)
    pub.max_queued_messages_set(0)
    pub.connect("127.0.0.1", port)
    pub.loop_start()
    seen: set[Path] = set()
    committed = 0
    rss: list[int] = []
    last_sample = 0.0

    def poll() -> None:
        nonlocal committed, last_sample
        for p in ig.commit_records(out):
            if p not in seen:
                seen.add(p)
                committed += int(ds.read_record(p)["rows"])
        if time.monotonic() - last_sample >= 1.0:
            last_sample = time.monotonic()
            rss.append(rss_kb(ingest.pid))

    t0 = time.monotonic()
    infos = []
    for i in range(a.messages):
        m = f"m{i % a.machines:06d}"
        seq = i // a.machines + 1
        payload = envelope(m, "5eed", seq, "summary", T0 + 60.0 * seq, False, bodies[i % len(bodies)])
        infos.append(pub.publish(f"cmcan/{m}/summary", payload, qos=1))
        if a.rate > 0:
            ahead = (i + 1) / a.rate - (time.monotonic() - t0)
            if ahead > 0:
                time.sleep(ahead)
        if i % 2000 == 0:
            poll()
    for info in infos:
        info.wait_for_publish(60)
    t_pub = time.monotonic() - t0
    while committed < a.messages:
        time.sleep(0.2)
        poll()
    t_all = time.monotonic() - t0
    cpu = cpu_s(ingest.pid) - cpu0
    pub.disconnect()
    pub.loop_stop()
    ingest.terminate()
    ingest.wait(30)
    broker.terminate()
    broker.wait(10)
    files = sum(1 for _ in out.rglob("*.parquet"))
    print(
        json.dumps(
            {
                "messages": a.messages,
                "machines": a.machines,
                "batch": a.batch,
                "publish_per_s": round(a.messages / t_pub),
                "ingested_per_s": round(a.messages / t_all),
                "seconds": round(t_all, 1),
                "ingest_cpu_s": round(cpu, 1),
                "ingest_cpu_us_per_message": round(cpu / a.messages * 1e6),
                "batches": len(seen),
                "files": files,
                "rss_mb_every_10_s": [round(x / 1024, 1) for x in rss[::10]],
                "rss_mb": {
                    "first": round(rss[0] / 1024, 1),
                    "peak": round(max(rss) / 1024, 1),
                    "last": round(rss[-1] / 1024, 1),
                }
                if rss
                else None,
            },
            indent=1,
        )
    )
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
