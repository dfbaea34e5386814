"""``cmcan uplink`` as a real process: bad inputs get one clear line and a sysexits code; TLS with
client certificates and username/password against a real mosquitto; retry when the broker is away."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cmcan.uplink.outbox import Outbox
from cmcan.uplink.records import Entry
from cmcan.uplink.writer import OutboxWriter
from tests.conftest import run_cli
from tests.helpers import systemd_verify
from tests.uplink_support import (
    Broker,
    Subscriber,
    closed_port,
    free_port,
    make_certs,
    needs_mosquitto,
    needs_openssl,
    uplink_config,
)

T0 = 1_700_000_000.0


def fill(state: Path, n: int) -> None:
    w = OutboxWriter(str(state / "outbox.sqlite"), 10**9, 1e9).start()
    for i in range(n):
        w.submit(Entry("event" if i % 5 == 0 else "summary", T0 + i, {"i": i}))
    w.close()


@pytest.fixture
def state(tmp_path):
    d = tmp_path / "state"
    d.mkdir()
    return d


# -- bad inputs ------------------------------------------------------------------------------------


def test_configuration_errors_name_the_field(tmp_path, state):
    from cmcan import config as cfgmod
    from cmcan.schema import SchemaError

    cases = [
        ({"machine_id": None}, "uplink.machine_id: missing"),
        ({"machine_id": "wl/42"}, "uplink.machine_id: expected 1-64 letters"),
        ({"mqtt": {"hots": "x"}}, "uplink.mqtt.hots: unknown field (did you mean 'host'?)"),
        ({"mqtt": {"port": 70000}}, "uplink.mqtt.port: expected an integer in [1, 65535]"),
        ({"mqtt": {"topic_prefix": "a/#"}}, "uplink.mqtt.topic_prefix: expected segments"),
        ({"mqtt": {"reconnect_min_s": 9, "reconnect_max_s": 2}}, "uplink.mqtt.reconnect_min_s: must not exceed"),
        ({"mqtt": {"tls": {"cert_file": "c.pem"}}}, "uplink.mqtt.tls.cert_file: cert_file and key_file go together"),
        ({"mqtt": {"tls": {"ca_file": "ca.pem"}}}, "uplink.mqtt.tls.enabled: certificate files are given"),
        ({"mqtt": {"password_file": "pw"}}, "uplink.mqtt.password_file: needs mqtt.username"),
        ({"mqtt": {"protocol": "4"}}, "uplink.mqtt.protocol: expected one of '3.1.1', '5'"),
        ({"outbox": {"max_mb": 0}}, "uplink.outbox.max_mb: expected a number in [0.1, 1000000] MiB"),
    ]
    for over, expected in cases:
        cfg = uplink_config(tmp_path / "c.yaml", state, 1883, **over)
        with pytest.raises(SchemaError) as err:
            cfgmod.load(cfg)
        assert str(err.value) == f"{cfg}: {expected}" or str(err.value).startswith(f"{cfg}: {expected}"), err.value
    # The command line says it in one line with the configuration's exit code.
    cfg = uplink_config(tmp_path / "c.yaml", state, 1883, machine_id=None)
    r = run_cli("uplink", "--config", str(cfg), "--check")
    assert r.returncode == 78 and r.stderr.strip() == f"cmcan uplink: {cfg}: uplink.machine_id: missing; every " + (
        "machine needs its own id in the topics and payloads when enabled"
    )


def test_disabled_missing_files_and_usage(tmp_path, state):
    cfg = uplink_config(tmp_path / "c.yaml", state, 1883, enabled=False)
    r = run_cli("uplink", "--config", str(cfg))
    assert r.returncode == 78 and "uplink.enabled: the uplink is disabled" in r.stderr
    r = run_cli("uplink", "--config", str(tmp_path / "none.yaml"))
    assert r.returncode == 66 and "configuration file not found" in r.stderr
    cfg = uplink_config(tmp_path / "c.yaml", tmp_path / "no-such-dir", 1883)
    r = run_cli("uplink", "--config", str(cfg), "--check")
    assert r.returncode == 73 and "no-such-dir: state directory does not exist" in r.stderr
    cfg = uplink_config(tmp_path / "c.yaml", state, 1883, mqtt={"username": "u", "password_file": "pw.txt"})
    r = run_cli("uplink", "--config", str(cfg), "--check")
    assert r.returncode == 66 and f"uplink.mqtt.password_file: {tmp_path / 'pw.txt'}: file not found" in r.stderr
    r = run_cli("uplink", "--config", str(cfg), "--timeout", "3")
    assert r.returncode == 64 and "--timeout goes with --drain" in r.stderr


def test_a_corrupt_outbox_is_kept_aside_reported_and_noted_in_the_new_one(tmp_path, state):
    (state / "outbox.sqlite").write_bytes(b"\x00garbage" * 500)
    cfg = uplink_config(tmp_path / "c.yaml", state, free_port())
    r = run_cli("uplink", "--config", str(cfg), "--check")
    assert r.returncode == 65
    assert "corrupt outbox" in r.stderr and "kept as outbox.sqlite.corrupt-1" in r.stderr
    assert (state / "outbox.sqlite.corrupt-1").read_bytes().startswith(b"\x00garbage")
    r = run_cli("uplink", "--config", str(cfg), "--status")
    assert r.returncode == 0 and json.loads(r.stdout)["by_kind"] == {"dropped": 1}
    note = json.loads(Outbox(state / "outbox.sqlite").fetch_after(0, 1)[0].body)
    assert note["reason"] == "corrupt_outbox" and note["kept_as"] == "outbox.sqlite.corrupt-1"


@pytest.mark.slow
def test_unreachable_broker_fails_the_check_and_drain_times_out_keeping_entries(tmp_path, state):
    fill(state, 7)
    with closed_port() as port:  # nothing listens there, and nothing else can take it meanwhile
        cfg = uplink_config(tmp_path / "c.yaml", state, port)
        r = run_cli("uplink", "--config", str(cfg), "--check")
        assert r.returncode == 69 and f"127.0.0.1:{port}: connection refused" in r.stderr
        cfg = uplink_config(tmp_path / "c.yaml", state, 1883, mqtt={"host": "no-such-host.invalid"})
        r = run_cli("uplink", "--config", str(cfg), "--check")
        assert r.returncode == 69 and "cannot resolve no-such-host.invalid" in r.stderr
        cfg = uplink_config(tmp_path / "c.yaml", state, port)
        r = run_cli("uplink", "--config", str(cfg), "--drain", "--timeout", "1.5")
    assert r.returncode == 75 and "outbox not empty after 1.5 s" in r.stderr and "connection refused" in r.stderr
    assert "retrying in" in r.stderr  # not fatal at run time: retried with back-off
    assert Outbox(state / "outbox.sqlite").usage().entries == 7


# -- against a real broker ---------------------------------------------------------------------------


@needs_mosquitto
def test_a_missing_broker_is_retried_until_it_comes(tmp_path, state):
    fill(state, 30)
    port = free_port()
    # Retries 4 s apart: the subscriber is surely subscribed before the uplink's retry that succeeds.
    cfg = uplink_config(tmp_path / "c.yaml", state, port, mqtt={"reconnect_min_s": 4.0, "reconnect_max_s": 4.0})
    proc = subprocess.Popen(
        [sys.executable, "-m", "cmcan", "uplink", "--config", str(cfg), "--drain", "--timeout", "60"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # the broker comes only after the uplink has tried against nothing (its start may take a
        # while on a slow machine: waiting a fixed time would race it)
        first = ""
        deadline = time.monotonic() + 60
        while "retrying in" not in first and time.monotonic() < deadline:
            line = proc.stderr.readline()
            if not line:
                break
            first += line
        assert "connection refused" in first and "retrying in" in first, first
        assert proc.poll() is None
        broker = Broker(tmp_path, port=port).start()
        sub = Subscriber(port, "cmcan/#").start()
        assert proc.wait(60) == 0, first + proc.stderr.read()
        sub.wait_for(lambda m: len([x for x in m if x.payload.get("kind") in ("event", "summary")]) >= 30, 30, "all")
        err = first + proc.stderr.read()
        assert "published" in err, err
    finally:
        proc.kill()
    sub.stop()
    broker.kill()
    assert Outbox(state / "outbox.sqlite").usage().entries == 0


@needs_mosquitto
def test_sigterm_says_offline_and_stops(tmp_path, state):
    broker = Broker(tmp_path).start()
    sub = Subscriber(broker.port, "cmcan/wl-0042/status").start()
    cfg = uplink_config(tmp_path / "c.yaml", state, broker.port)
    proc = subprocess.Popen(
        [sys.executable, "-m", "cmcan", "uplink", "--config", str(cfg)], stderr=subprocess.PIPE, text=True
    )
    try:
        sub.wait_for(lambda m: any(x.payload["state"] == "online" for x in m), 20, "online")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        sub.wait_for(lambda m: m[-1].payload["state"] == "offline", 5, "offline")
        assert sub.snapshot()[-1].payload["reason"] == "shutdown"
        assert "received SIGTERM, stopping" in proc.stderr.read()
    finally:
        proc.kill()
        sub.stop()
        broker.kill()


@pytest.mark.slow
@needs_mosquitto
@needs_openssl
def test_tls_with_client_certificates(tmp_path, state):
    c = make_certs(tmp_path)
    broker = Broker(
        tmp_path,
        conf=[
            "allow_anonymous true",
            f"cafile {c['ca.crt']}",
            f"certfile {c['server.crt']}",
            f"keyfile {c['server.key']}",
            "require_certificate true",
        ],
    ).start()
    tls = {"ca_certs": str(c["ca.crt"]), "certfile": str(c["client.crt"]), "keyfile": str(c["client.key"])}
    sub = Subscriber(broker.port, "cmcan/#", client_id="tls-sub", tls=tls)
    sub.start()
    good = {"enabled": True, "ca_file": str(c["ca.crt"]), "cert_file": "client.crt", "key_file": "client.key"}
    try:
        fill(state, 25)
        cfg = uplink_config(tmp_path / "c.yaml", state, broker.port, mqtt={"host": "localhost", "tls": good})
        r = run_cli("uplink", "--config", str(cfg), "--check")  # relative paths: from the config's folder
        assert r.returncode == 0 and "ok: connected to localhost" in r.stdout, r.stderr
        r = run_cli("uplink", "--config", str(cfg), "--drain", "--timeout", "30")
        assert r.returncode == 0, r.stderr
        sub.wait_for(lambda m: len(sub.data()) >= 25, 10, "25 entries over TLS")
        assert [m.payload["seq"] for m in sub.data()] == list(range(1, 26))

        def check(tls_over: dict, host: str = "localhost") -> subprocess.CompletedProcess[str]:
            cfg = uplink_config(
                tmp_path / "bad.yaml", state, broker.port, mqtt={"host": host, "tls": {**good, **tls_over}}
            )
            return run_cli("uplink", "--config", str(cfg), "--check")

        r = check({"ca_file": str(c["other-ca.crt"])})
        assert r.returncode == 78 and "the broker's certificate is not trusted" in r.stderr, r.stderr
        r = check({"cert_file": None, "key_file": None})
        assert r.returncode == 69 and "does it require a client certificate" in r.stderr, r.stderr
        r = check({"cert_file": str(c["client.crt"]), "key_file": str(c["server.key"])})
        assert r.returncode == 78 and "not a usable client certificate and key (key values mismatch)" in r.stderr
        (tmp_path / "junk.pem").write_text("-----BEGIN CERTIFICATE-----\nnot base64\n-----END CERTIFICATE-----\n")
        r = check({"ca_file": str(tmp_path / "junk.pem")})
        assert r.returncode == 78 and "uplink.mqtt.tls.ca_file" in r.stderr and "not a PEM CA certificate" in r.stderr
        r = check({"cert_file": str(tmp_path / "missing.crt")})
        assert r.returncode == 66 and "uplink.mqtt.tls.cert_file" in r.stderr and "file not found" in r.stderr
        r = check({}, host="127.0.0.1")  # the certificate names 127.0.0.1 too
        assert r.returncode == 0, r.stderr
    finally:
        sub.stop()
        broker.kill()


@needs_mosquitto
def test_username_and_password(tmp_path, state):
    pwfile = tmp_path / "passwd"
    pwfile.write_text("")
    passwd = shutil.which("mosquitto_passwd")
    if passwd is None:
        pytest.skip("mosquitto_passwd is not installed (it comes with Debian's mosquitto package)")
    subprocess.run([passwd, "-b", str(pwfile), "gw", "s3cret"], check=True)
    if os.geteuid() == 0:
        os.chmod(pwfile, 0o644)
    broker = Broker(tmp_path, conf=["allow_anonymous false", f"password_file {pwfile}"]).start()
    (tmp_path / "pw-good").write_text("s3cret\n")
    (tmp_path / "pw-bad").write_text("guess\n")
    try:
        for pw, code, text in (("pw-good", 0, "ok: connected"), ("pw-bad", 78, "broker refused the connection")):
            cfg = uplink_config(tmp_path / "c.yaml", state, broker.port, mqtt={"username": "gw", "password_file": pw})
            r = run_cli("uplink", "--config", str(cfg), "--check")
            assert r.returncode == code and text in (r.stdout + r.stderr), r.stderr
    finally:
        broker.kill()


# -- the systemd unit --------------------------------------------------------------------------------


def test_uplink_unit_verifies_and_keeps_the_bus_and_the_network_apart():

    if shutil.which("systemd-analyze") is None:
        pytest.fail("systemd-analyze is not installed (the CI installs the systemd package)")
    root = Path(__file__).resolve().parents[1] / "systemd"
    beside = Path(sys.executable).with_name("cmcan")
    exe = shutil.which("cmcan") or (str(beside) if beside.exists() else None)
    assert exe, "the cmcan entry point must be installed"
    daemon = (root / "cmcan.service").read_text()
    uplink = (root / "cmcan-uplink.service").read_text()
    assert "IPAddressDeny=any" in daemon and "AF_INET" not in daemon  # the CAN daemon: no IP at all
    families = next(x for x in uplink.splitlines() if x.startswith("RestrictAddressFamilies="))
    assert "AF_INET" in families and "AF_CAN" not in families and "AF_NETLINK" not in families
    for key in ("Type=notify", "WatchdogSec=", "DynamicUser=yes", "User=cmcan", "StateDirectory=cmcan",
                "MemoryDenyWriteExecute=yes", "CapabilityBoundingSet=\n", "RestrictNamespaces=yes"):  # fmt: skip
        assert key in uplink, key
    systemd_verify(uplink.replace("/usr/local/bin/cmcan", exe), "cmcan-uplink.service")


@needs_mosquitto
def test_the_uplink_runs_with_memory_deny_write_execute(tmp_path, state):
    """The unit sets MemoryDenyWriteExecute=yes; the kernel's own switch for it (PR_SET_MDWE, Linux
    6.3+) shows the uplink, TLS library and all, needs no writable executable memory."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(66, 0, 0, 0, 0) < 0:  # PR_GET_MDWE
        pytest.skip("this kernel has no PR_SET_MDWE (Linux < 6.3)")
    fill(state, 10)
    broker = Broker(tmp_path).start()
    cfg = uplink_config(tmp_path / "c.yaml", state, broker.port)
    launcher = (
        "import ctypes, os, sys\n"
        "assert ctypes.CDLL(None).prctl(65, 1, 0, 0, 0) == 0  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN\n"
        "os.execv(sys.executable, [sys.executable, '-m', 'cmcan', 'uplink', *sys.argv[1:]])\n"
    )
    try:
        r = subprocess.run(
            [sys.executable, "-c", launcher, "--config", str(cfg), "--drain", "--timeout", "30"],
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        broker.kill()
    assert r.returncode == 0, r.stderr
    assert Outbox(state / "outbox.sqlite").usage().entries == 0


def test_ready_watchdog_and_status_while_the_broker_is_missing(tmp_path, state):
    from tests.test_daemon import notify_socket, read_notifications

    fill(state, 3)
    sock, path = notify_socket(tmp_path)
    cfg = uplink_config(tmp_path / "c.yaml", state, free_port())
    env = {**os.environ, "NOTIFY_SOCKET": path, "WATCHDOG_USEC": "400000"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "cmcan", "uplink", "--config", str(cfg)], env=env, stderr=subprocess.PIPE, text=True
    )
    try:

        def refused(g: list[str]) -> bool:
            return any("STATUS=not connected" in x and "connection refused" in x for x in g)

        got = read_notifications(sock, lambda g: sum("WATCHDOG=1" in x for x in g) >= 3 and refused(g), 30)
        assert any("READY=1" in g for g in got), got
        assert sum("WATCHDOG=1" in g for g in got) >= 3  # the loop lives on while it retries
        assert any("STATUS=not connected" in g and "connection refused" in g and "backlog 3 entries" in g for g in got)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        proc.kill()
        sock.close()
