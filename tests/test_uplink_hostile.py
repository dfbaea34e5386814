"""The uplink against hostile or unlucky inputs: identifiers MQTT cannot carry are refused at load,
naming the field; a locked outbox or a full disk is a restartable exit, not one that stops the unit for
good; a second uplink on one outbox exits 75 naming the lock instead of fighting the first for the
broker session (real processes, a real mosquitto)."""

from __future__ import annotations

import json
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cmcan.cli.errors import EX_CANTCREAT, EX_CONFIG, EX_IOERR, EX_OK, EX_SOFTWARE, EX_TEMPFAIL, EXIT_CODES
from cmcan.config import load as load_config
from cmcan.schema import SchemaError
from cmcan.uplink.config import MQTT_MAX_BYTES, mqtt_string_problem, publish_topic_problem
from cmcan.uplink.outbox import Outbox
from cmcan.uplink.records import Entry
from cmcan.uplink.setup import OutboxLock, SetupError
from cmcan.uplink.writer import OutboxWriter
from tests.conftest import ROOT, run_cli
from tests.test_bad_inputs import refused
from tests.uplink_support import Broker, Subscriber, closed_port, needs_mosquitto, uplink_config

T0 = 1_700_000_000.0


@pytest.fixture
def state(tmp_path):
    d = tmp_path / "state"
    d.mkdir()
    return d


def fill(state: Path, n: int) -> None:
    w = OutboxWriter(str(state / "outbox.sqlite"), 10**9, 1e9).start()
    for i in range(n):
        w.submit(Entry("event", T0 + i, {"i": i}))
    w.close()


# -- names and identifiers ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "over, field, why",
    [
        ({"machine_id": "wl-0042\n"}, "uplink.machine_id", "expected 1-64 letters"),
        ({"mqtt": {"topic_prefix": "cmcan\n"}}, "uplink.mqtt.topic_prefix", "expected segments"),
        ({"mqtt": {"topic_prefix": "site/+/x"}}, "uplink.mqtt.topic_prefix", "expected segments"),
        ({"mqtt": {"topic_prefix": "$SYS"}}, "uplink.mqtt.topic_prefix", "expected segments"),
        ({"mqtt": {"client_id": "gw\x00evil"}}, "uplink.mqtt.client_id", "NUL"),
        ({"mqtt": {"username": "gw\x00"}}, "uplink.mqtt.username", "NUL"),
        ({"mqtt": {"client_id": "gw\nx"}}, "uplink.mqtt.client_id", "U+000A"),
        ({"mqtt": {"username": "gw\x7f"}}, "uplink.mqtt.username", "U+007F"),
        ({"mqtt": {"client_id": "gw\ufffe"}}, "uplink.mqtt.client_id", "U+FFFE"),
        ({"mqtt": {"username": "x" * (MQTT_MAX_BYTES + 1)}}, "uplink.mqtt.username", "more than MQTT's 65535"),
        ({"mqtt": {"client_id": "ü" * 40_000}}, "uplink.mqtt.client_id", "80000 bytes long in UTF-8"),
        ({"mqtt": {"host": "broker\x00.example"}}, "uplink.mqtt.host", "NUL"),
        ({"mqtt": {"host": "broker.example\n"}}, "uplink.mqtt.host", "expected a host name"),
        ({"mqtt": {"host": "tcp://broker"}}, "uplink.mqtt.host", "expected a host name"),
        ({"outbox": {"file": "out\x00box"}}, "uplink.outbox.file", "NUL"),
        ({"mqtt": {"tls": {"enabled": True, "ca_file": "ca\x00.pem"}}}, "uplink.mqtt.tls.ca_file", "NUL"),
    ],
)
def test_strings_mqtt_cannot_carry_are_refused_at_load(tmp_path, state, over, field, why):
    cfg = uplink_config(tmp_path / "c.yaml", state, 1883, **over)
    with pytest.raises(SchemaError) as err:
        load_config(cfg)
    assert str(err.value).startswith(f"{cfg}: {field}: ") and why in str(err.value), str(err.value)
    assert len(str(err.value)) < 400  # a 65 kB value is quoted cut short


def test_the_command_line_says_it_in_one_line_with_exit_78(tmp_path, state):
    for over, field in (({"mqtt": {"client_id": "gw\x00"}}, "uplink.mqtt.client_id"), ({"machine_id": "m\n"}, "")):
        cfg = uplink_config(tmp_path / "c.yaml", state, 1883, **over)
        refused(run_cli("uplink", "--config", str(cfg), "--check"), EX_CONFIG, str(cfg), field or "machine_id")
    refused(run_cli("check", "--config", str(cfg)), EX_CONFIG, "uplink.machine_id")


def test_the_mqtt_string_rules():
    assert mqtt_string_problem("cmcan-Bagger-Süd-7") is None  # UTF-8 is fine
    assert "surrogate" in mqtt_string_problem("a\ud800")
    assert publish_topic_problem("a/b/#") and publish_topic_problem("a/+/c") and publish_topic_problem("")
    assert publish_topic_problem("cmcan/m1/event") is None


@needs_mosquitto
def test_a_unicode_client_id_and_user_name_connect_to_a_real_broker(tmp_path, state):
    """What is refused is what MQTT forbids, not everything beyond ASCII."""
    broker = Broker(tmp_path).start()
    try:
        cfg = uplink_config(tmp_path / "c.yaml", state, broker.port, mqtt={"client_id": "cmcan-Süd-7", "username": "ü"})
        r = run_cli("uplink", "--config", str(cfg), "--check")
        assert r.returncode == EX_OK and "as cmcan-Süd-7" in r.stdout, r.stderr
    finally:
        broker.kill()


# -- a transient outbox problem is restartable ---------------------------------------------------------


def unit_keys(name: str) -> dict[str, list[str]]:
    keys: dict[str, list[str]] = {}
    for line in (ROOT / "systemd" / name).read_text().splitlines():
        if "=" in line and not line.startswith("#"):
            k, v = line.split("=", 1)
            keys.setdefault(k, []).append(v)
    return keys


# What a restart of the uplink can cure: a corrupt outbox (kept aside, the restart begins a new one), an
# I/O error, a lock held or a full disk (temporary), a crash.
UPLINK_RESTARTABLE = {65, EX_IOERR, EX_TEMPFAIL, EX_SOFTWARE}


def test_the_uplink_unit_restarts_what_a_restart_can_cure_and_nothing_else():
    keys = unit_keys("cmcan-uplink.service")
    prevent = {int(x) for v in keys["RestartPreventExitStatus"] for x in v.split()}
    assert keys["Restart"] == ["on-failure"]
    for code in set(EXIT_CODES.values()):
        assert (code in prevent) == (code not in UPLINK_RESTARTABLE), code


def test_an_outbox_locked_by_another_process_is_a_temporary_failure(tmp_path, state):
    fill(state, 3)
    holder = sqlite3.connect(state / "outbox.sqlite", isolation_level=None)
    holder.execute("PRAGMA locking_mode=EXCLUSIVE")
    holder.execute("BEGIN EXCLUSIVE")  # held until closed: nobody else may read or write
    try:
        with closed_port() as port:
            cfg = uplink_config(tmp_path / "c.yaml", state, port)
            r = run_cli("uplink", "--config", str(cfg), "--check")
    finally:
        holder.close()
    refused(r, EX_TEMPFAIL, "outbox.sqlite", "another process holds a lock on it")
    assert Outbox(state / "outbox.sqlite").usage().entries == 3  # nothing lost


def in_full_tmpfs(tmp_path: Path, state: Path, argv: list[str], before: str = "") -> subprocess.CompletedProcess:
    """``argv`` with ``state`` on a 256 kB tmpfs filled to the last byte, in a user and mount namespace
    of its own (no root needed where unprivileged user namespaces are allowed)."""
    if shutil.which("unshare") is None:
        pytest.skip("unshare (util-linux) is not installed")
    probe = subprocess.run(["unshare", "-rm", "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no user namespaces here: {probe.stderr.decode().strip()}")
    script = (
        f'mount -t tmpfs -o size=256k none "{state}" && {before} '
        f'(dd if=/dev/zero of="{state}/fill" bs=4k 2>/dev/null; true) && exec "$@"'
    )
    return subprocess.run(
        ["unshare", "-rm", "sh", "-c", script, "sh", *argv], capture_output=True, text=True, timeout=120, cwd=ROOT
    )


@pytest.mark.parametrize("existing", [False, True], ids=["new-outbox", "existing-outbox"])
def test_a_full_disk_at_start_is_a_temporary_failure(tmp_path, state, existing):
    """The unit restarts the uplink later (by then the daemon has pruned or an operator made room);
    before, exit 73 stopped it for good."""
    with closed_port() as port:
        cfg = uplink_config(tmp_path / "c.yaml", state, port)
        before = ""
        if existing:  # an outbox and its lock from an earlier run, then the disk filled up
            seed = tmp_path / "seed"
            seed.mkdir()
            fill(seed, 20)
            before = f'cp "{seed}/outbox.sqlite" "{state}/" && echo 1234 > "{state}/outbox.sqlite.lock" &&'
        r = in_full_tmpfs(tmp_path, state, [sys.executable, "-m", "cmcan", "uplink", "--config", str(cfg), "--check"],
                          before)  # fmt: skip
    refused(r, EX_TEMPFAIL, str(state), "cannot take the outbox lock: No space left on device" if not existing
            else "(the file system is full)")  # fmt: skip


# -- one uplink per outbox -------------------------------------------------------------------------------


@needs_mosquitto
def test_a_second_uplink_on_one_outbox_exits_75_and_the_first_keeps_its_session(tmp_path, state):
    """Before: both ran with one client id and took the session from each other every 1-2 s, and
    subscribers saw the machine go offline and online over and over."""
    broker = Broker(tmp_path).start()
    sub = Subscriber(broker.port, "cmcan/wl-0042/status").start()
    cfg = uplink_config(tmp_path / "c.yaml", state, broker.port)
    cmd = [sys.executable, "-m", "cmcan", "uplink", "--config", str(cfg)]
    first = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        sub.wait_for(lambda m: any(x.payload["state"] == "online" for x in m), 30, "online")
        second = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT)
        refused(second, EX_TEMPFAIL, "outbox.sqlite.lock", f"pid {first.pid} holds the lock", "one uplink per outbox")
        check = run_cli("uplink", "--config", str(cfg), "--check")  # the same client id: refused as well
        refused(check, EX_TEMPFAIL, f"pid {first.pid}")
        fill(state, 5)  # the first one goes on publishing, on the session it had
        sub_data = Subscriber(broker.port, "cmcan/wl-0042/event", client_id="data-sub").start()
        sub_data.wait_for(lambda m: len(m) >= 5, 30, "5 events")
        time.sleep(3)  # the flapping came every 1-2 s: none in 3 s
        states = [x.payload["state"] for x in sub.snapshot()]
        assert states == ["online"], states
        assert first.poll() is None
        sub_data.stop()
    finally:
        first.terminate()
        first.wait(15)
        sub.stop()
        broker.kill()
    assert first.returncode == 0
    OutboxLock(state / "outbox.sqlite").acquire().release()  # the lock went with its holder


def test_status_is_a_query_that_creates_nothing(tmp_path, state):
    cfg = uplink_config(tmp_path / "c.yaml", state, 1883)
    r = run_cli("uplink", "--status", "--config", str(cfg))
    assert r.returncode == EX_OK, r.stderr
    assert json.loads(r.stdout)["entries"] == 0 and list(state.iterdir()) == []


# -- the outbox lock is opened as the state directory's files are ------------------------------------------


@pytest.mark.parametrize("kind", ["link to a file", "dangling link", "fifo"])
def test_an_outbox_lock_that_is_a_link_or_a_fifo_is_refused_and_nothing_is_written_through_it(tmp_path, state, kind):
    """Whoever can write the state directory must not get the uplink to create or write any other file
    the uplink's user may open (before: the lock was opened following links, made at the link's target)."""
    import os

    lock = state / "outbox.sqlite.lock"
    victim = tmp_path / "victim"
    if kind == "link to a file":
        victim.write_text("keep me\n")
        lock.symlink_to(victim)
    elif kind == "dangling link":
        lock.symlink_to(victim)
    else:
        os.mkfifo(lock)
    with pytest.raises(SetupError) as err:
        OutboxLock(state / "outbox.sqlite").acquire()
    assert err.value.problem == "cantcreat" and str(lock) in str(err.value), str(err.value)
    assert ("symbolic link" if "link" in kind else "not a regular file") in str(err.value)
    if kind == "link to a file":
        assert victim.read_text() == "keep me\n"
    else:
        assert not victim.exists()
    cfg = uplink_config(tmp_path / "c.yaml", state, 1883)  # refused before any connection
    refused(run_cli("uplink", "--config", str(cfg), "--check"), EX_CANTCREAT, str(lock))
    assert not victim.exists() or victim.read_text() == "keep me\n"
