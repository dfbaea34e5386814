"""Benchmark: ``cmcan fleet ingest`` end to end against a local mosquitto.

Summaries of ``--machines`` machines (the uplink's payloads, about 1.9 kB each, stamped with the
time they are published: the open day, as a live fleet's) are published with QoS 1 at ``--rate`` per
second (0: as fast as the broker takes them), ``--messages`` of them or for ``--minutes``; the ingest
runs as a real process and commits them into a fresh data set. Printed, plainly and as JSON: the
publish rate, the ingest's rate (messages committed per second, from the first publish to the last
commit), its CPU time per message (user + system, from /proc), and its resident memory (VmRSS,
sampled every second: first, peak, last, every minute, and the growth from the end of the first
minute to the end, which is what "flat" means). The ingest's and the broker's CPU time per message
give what two cores of nothing else would carry (the rates measured on a shared machine are lower:
the bench runs at idle priority beside other work). Then the fold that closes the day (its rows into the
machine/day partitions) is timed on the data set the run left.

    python bench/bench_ingest.py [--machines 100] [--messages 20000] [--rate 0] [--batch 1000]
    python bench/bench_ingest.py --machines 10000 --rate 2000 --minutes 30     # memory over 30 min
    python bench/bench_ingest.py --machines 1000 --backlog     # the ingest's rate alone

``--backlog``: the messages are published while the ingest is stopped (the broker keeps them in its
session), then the ingest is started and timed until the last is committed: its own rate, without
the publisher (a Python process as busy as the ingest) on the same two cores.
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
from cmcan.fleet import uplinkstore as store
from cmcan.uplink.records import dumps, envelope


def summary_body(i: int, t0_s: float) -> str:
    stat = {"n": 4725, "mean": 99.8038, "std": 0.0273, "min": 99.7414, "max": 99.8799}
    counters = {k: i for k in ("frames_total", "accepted", "unknown_id", "bad_length", "late", "ticks", "evaluated")}
    return dumps(
        {
            "window": {"start_s": t0_s, "every_s": 60.0, "ticks_sampled": 600, "closed_by": "period"},
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


class Committed:
    """The rows of the batch records as they appear (a record folded and removed meanwhile was
    counted when it appeared, or its fold's rows are the same rows: batches are counted alone)."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.keys: set[str] = set()
        self.rows = 0
        self.batches = 0

    def poll(self) -> None:
        for p in store.record_paths(self.out):
            if p.stem in self.keys:
                continue
            try:
                row = ds.read_record(p)
            except ds.Damaged:  # removed under us (a fold's sources after their grace): its fold holds them
                continue
            self.keys.add(p.stem)
            if (row.get("kind") or store.BATCH) == store.BATCH:
                self.rows += int(row["rows"])
                self.batches += 1


def day_close(out: Path) -> dict[str, float]:
    """The fold at the close of the day (every record not folded yet), as the ingest runs it then."""
    records, problems = store.read_records(out)
    assert not problems, problems
    sources = store.unfolded(records)
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    rec = store.fold(out, sources, store.key_of(time.time_ns()), time.time() + 86400 + store.DAY_GRACE_S)
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    files = sum(f["machine"] is not None for f in rec.files) if rec else 0
    rows = int(rec.row["rows"]) if rec else 0
    return {
        "rows": rows,
        "sources": len(sources),
        "partition_files": files,
        "seconds": round(wall, 2),
        "cpu_us_per_row": round(cpu / max(rows, 1) * 1e6, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=100)
    ap.add_argument("--messages", type=int, default=20000)
    ap.add_argument("--minutes", type=float, default=0.0, help="publish for this long instead of --messages")
    ap.add_argument("--rate", type=float, default=0.0, help="messages per second (0: as fast as possible)")
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--batch-wait-s", type=float, default=0.5)
    ap.add_argument("--fold-every", type=int, default=None)
    ap.add_argument("--backlog", action="store_true", help="publish first, then start the ingest and time it")
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
    if a.fold_every is not None:
        cmd += ["--fold-every", str(a.fold_every)]
    log = open(work / "ingest.log", "wb")  # noqa: SIM115 - open for the ingest's life

    def start() -> subprocess.Popen[bytes]:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
        while (work / "ingest.log").read_text().count("subscribed to") < (2 if a.backlog and ingest else 1):
            time.sleep(0.05)
        return proc

    ingest: subprocess.Popen[bytes] | None = None
    ingest = start()
    if a.backlog:  # its session (and subscription) made, the ingest goes away while the messages come
        ingest.terminate()
        ingest.wait(30)
    cpu0 = cpu_s(ingest.pid) if not a.backlog else 0.0
    broker_cpu0 = cpu_s(broker.pid)
    t_start = time.time()
    bodies = [summary_body(i, t_start) for i in range(50)]
    pub = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-publisher")
    pub.max_inflight_messages_set(1000)
    pub.max_queued_messages_set(0)
    pub.connect("127.0.0.1", port)
    pub.loop_start()
    done = Committed(out)
    rss: list[tuple[float, int]] = []  # (seconds since the first publish, VmRSS kB)
    last_poll = 0.0

    def poll() -> None:
        nonlocal last_poll
        last_poll = time.monotonic()
        done.poll()
        if ingest.poll() is None:
            t = time.monotonic() - t0
            if a.minutes and rss and int(t // 60) > int(rss[-1][0] // 60):
                print(f"{int(t // 60)} min: {done.rows} committed, RSS {rss[-1][1] / 1024:.1f} MB", file=sys.stderr)
            rss.append((t, rss_kb(ingest.pid)))

    t0 = time.monotonic()
    until = t0 + a.minutes * 60.0 if a.minutes else None
    infos = []
    i = 0
    while (i < a.messages) if until is None else (time.monotonic() < until):
        m = f"m{i % a.machines:06d}"
        seq = i // a.machines + 1
        payload = envelope(m, "5eed", seq, "summary", time.time(), False, bodies[i % len(bodies)])
        infos.append(pub.publish(f"cmcan/{m}/summary", payload, qos=1))
        i += 1
        if a.rate > 0:
            ahead = i / a.rate - (time.monotonic() - t0)
            if ahead > 0:
                time.sleep(ahead)
        if i % 2000 == 0:
            for info in infos:  # the broker has them (PUBACK): the publisher's memory stays bounded
                info.wait_for_publish(60)
            infos.clear()
        if time.monotonic() - last_poll >= 1.0:  # the records, and the ingest's memory every second
            poll()
    for info in infos:
        info.wait_for_publish(60)
    n = i
    t_pub = time.monotonic() - t0
    if a.backlog:
        t0 = time.monotonic()
        ingest = start()
        cpu0 = cpu_s(ingest.pid)  # (its start: imports, the ids read back)
        broker_cpu0 = cpu_s(broker.pid)
    while done.rows < n:
        time.sleep(0.2)
        poll()
    t_all = time.monotonic() - t0
    cpu = cpu_s(ingest.pid) - cpu0
    broker_cpu = cpu_s(broker.pid) - broker_cpu0
    ingest_us, broker_us = cpu / n * 1e6, broker_cpu / n * 1e6
    # what two cores of nothing else carry: the ingest's loop is one thread (its folds run beside it)
    capacity = min(1e6 / ingest_us, 2e6 / (ingest_us + broker_us))
    pub.disconnect()
    pub.loop_stop()
    ingest.terminate()
    ingest.wait(120)
    broker.terminate()
    broker.wait(10)
    close = day_close(out)
    mb = [round(kb / 1024, 1) for _t, kb in rss]
    every_minute = [round(kb / 1024, 1) for k, (t, kb) in enumerate(rss) if k == 0 or t // 60 > rss[k - 1][0] // 60]
    # from the first sample after a minute (pyarrow loaded, the first batches and folds done) to the
    # last; a run shorter than two minutes has no such figure
    after_1 = next((round(kb / 1024, 1) for t, kb in rss if t >= 60.0), None) if rss and rss[-1][0] >= 120 else None
    result = {
        "messages": n,
        "machines": a.machines,
        "mode": "backlog" if a.backlog else "live",
        "batch": a.batch,
        "publish_per_s": round(n / t_pub),
        "ingested_per_s": round(n / t_all),
        "seconds": round(t_all, 1),
        "ingest_cpu_s": round(cpu, 1),
        "ingest_cpu_us_per_message": round(ingest_us),
        "broker_cpu_us_per_message": round(broker_us),
        "capacity_per_s_on_two_idle_cores": round(capacity),
        "batches": done.batches,
        "rss_mb": {"first": mb[0], "peak": max(mb), "last": mb[-1]} if mb else None,
        "rss_mb_every_minute": every_minute,
        "rss_growth_mb_after_minute_1": round(mb[-1] - after_1, 1) if mb and after_1 is not None else None,
        "day_close_fold": close,
    }
    print(
        f"{n} summaries of {a.machines} machines: {result['ingested_per_s']} messages/s ingested end to end "
        f"(published {result['publish_per_s']}/s), {result['ingest_cpu_us_per_message']} us CPU a message "
        f"(the broker {result['broker_cpu_us_per_message']}: two idle cores carry about "
        f"{result['capacity_per_s_on_two_idle_cores']}/s); "
        f"RSS {result['rss_mb']} MB, growth after the first minute {result['rss_growth_mb_after_minute_1']} MB; "
        f"the day's close: {close['rows']} rows into {close['partition_files']} files in {close['seconds']} s"
    )
    print(json.dumps(result, indent=1))
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
