"""``cmcan run`` and ``cmcan check``: every configuration problem is named, with a sysexits code,
before the bus is touched."""

import json
import shutil
import signal
import sys
from pathlib import Path

import pytest
import yaml

from cmcan.cli.errors import EX_CANTCREAT, EX_CONFIG, EX_NOINPUT, EX_UNAVAILABLE
from tests.conftest import ROOT, run_cli
from tests.daemon_proc import DaemonProc, virtual_config
from tests.helpers import systemd_verify


def config_copy(tmp_path: Path, **changes) -> Path:
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    for dotted, value in changes.items():
        node = raw
        keys = dotted.split(".")
        for k in keys[:-1]:
            node = node[k]
        if value is None:
            del node[keys[-1]]
        else:
            node[keys[-1]] = value
    p = tmp_path / "machine.yaml"
    p.write_text(yaml.safe_dump(raw))
    return p


def run_and_check(tmp_path, cfg, *extra):
    state = tmp_path / "state"
    state.mkdir(exist_ok=True)
    run = run_cli("run", "--config", str(cfg), "--state-dir", str(state), *extra, timeout=60)
    check = run_cli("check", "--config", str(cfg), "--channel-check", "--json", *extra, timeout=60)
    return run, check


def test_check_passes_on_the_shipped_configuration():
    res = run_cli("check", "--json")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    assert (
        doc["ok"]
        and doc["motor_disp_cc"] == 44.0
        and set(doc["envelope"]) == {"pump_speed_rpm", "pump_disp_cc", "dp_bar", "temp_c"}
    )


def test_missing_configuration_file(tmp_path):
    res = run_cli("run", "--config", str(tmp_path / "none.yaml"))
    assert res.returncode == EX_NOINPUT and "none.yaml: configuration file not found" in res.stderr


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"thresholds.low_pct": 120}, "thresholds.low_pct: expected a number in [50, 100] %, got 120"),
        ({"signals.pump_speed_rpm": None}, "signals.pump_speed_rpm: missing"),
        ({"gating.windw_s": 1.0}, "gating.windw_s: unknown field (did you mean 'window_s'?)"),
        ({"signals.temp_c": {"message": "OIL_STATUS", "signal": "oil_temp"}}, "signals.temp_c.signal"),
        ({"signals.temp_c": {"message": "OIL", "signal": "oil_temp_c"}}, "signals.temp_c.message: no message 'OIL'"),
        ({"drive.motor_disp_cc": 55.0}, "trained for a motor displacement of 44 cm3/rev, the configuration says 55"),
        ({"dbc": "/nonexistent/x.dbc"}, "/nonexistent/x.dbc: DBC file not found"),
        ({"model": "/nonexistent/m.onnx"}, "/nonexistent/m.onnx: model file not found"),
        ({"bus.interface": "socketcann"}, "unknown python-can interface 'socketcann'"),
    ],
)
def test_invalid_configuration_is_named_and_exits_78(tmp_path, change, needle):
    cfg = config_copy(tmp_path, **change)
    run, check = run_and_check(tmp_path, cfg)
    assert run.returncode == EX_CONFIG, run.stderr
    assert needle in run.stderr and str(cfg) in run.stderr
    doc = json.loads(check.stdout)
    assert check.returncode == EX_CONFIG and not doc["ok"] and needle in doc["error"]


def test_a_dbc_that_does_not_parse(tmp_path):
    bad = tmp_path / "bad.dbc"
    bad.write_text('VERSION ""\nBO_ 256 X: 8 Y\n SG_ a : 0|8@1+ (1,0) [0|1] "" Y\n BO_ garbage\n')
    run, _ = run_and_check(tmp_path, config_copy(tmp_path, dbc=str(bad)))
    assert run.returncode == EX_CONFIG and "bad.dbc: not a valid DBC" in run.stderr


def test_a_missing_can_channel_is_refused_before_opening(tmp_path):
    cfg = config_copy(tmp_path, **{"bus.channel": "can9"})
    run, check = run_and_check(tmp_path, cfg)
    assert run.returncode == EX_UNAVAILABLE
    assert "no network interface 'can9'" in run.stderr and "ip link set can9 up type can bitrate 250000" in run.stderr
    assert check.returncode == EX_UNAVAILABLE


def test_a_bad_channel_name(tmp_path):
    run, _ = run_and_check(tmp_path, config_copy(tmp_path, **{"bus.channel": "can0; rm -rf /"}))
    assert run.returncode == EX_CONFIG and "is not a network interface name" in run.stderr


def test_an_unwritable_state_directory(tmp_path):
    cfg = config_copy(tmp_path, **{"bus.interface": "virtual"})
    res = run_cli("run", "--config", str(cfg), "--state-dir", str(tmp_path / "missing"))
    assert res.returncode == EX_CANTCREAT and "state directory does not exist" in res.stderr
    assert "(--state-dir)" in res.stderr and "state.directory in" not in res.stderr  # named by who gave it


@pytest.mark.parametrize("unit_name", ["cmcan.service", "cmcan@.service"])
def test_systemd_unit_verifies(unit_name):
    if shutil.which("systemd-analyze") is None:
        pytest.fail("systemd-analyze is not installed (the CI installs the systemd package)")

    # the entry point beside this interpreter (a venv not on PATH), else on PATH
    beside = Path(sys.executable).parent / "cmcan"
    exe = str(beside) if beside.exists() else shutil.which("cmcan")
    assert exe, "the cmcan entry point must be installed"
    unit = (ROOT / "systemd" / unit_name).read_text().replace("/usr/local/bin/cmcan", exe)
    for key in (
        "Type=notify",
        "WatchdogSec=",
        "Restart=on-failure",
        "DynamicUser=yes",
        "StateDirectory=cmcan",
        "ProtectSystem=strict",
        "RestrictAddressFamilies=AF_CAN AF_UNIX\n",
        "NoNewPrivileges=yes",
        "CapabilityBoundingSet=\n",
        "PrivateUsers=yes",
        "MemoryDenyWriteExecute=yes",
        "ExecReload=/bin/kill -HUP $MAINPID",
        "IPAddressDeny=any",
    ):
        assert key in unit
    systemd_verify(unit, unit_name.replace("@", "@left-travel"))  # a template verifies as an instance


def test_the_per_drive_template_is_the_single_unit_but_for_its_instance():
    """cmcan@.service differs from cmcan.service only where the instance enters (its configuration,
    state directory, description): a hardening added to one and not the other fails here."""

    def settings(name: str) -> list[str]:
        lines = (ROOT / "systemd" / name).read_text().splitlines()
        return [x for x in lines if x.strip() and not x.startswith("#") and not x.startswith(PER_INSTANCE)]

    assert settings("cmcan@.service") == settings("cmcan.service")
    template = (ROOT / "systemd" / "cmcan@.service").read_text()
    assert "--config /etc/cmcan/drives/%i.yaml --state-dir /var/lib/cmcan/%i" in template
    assert "StateDirectory=cmcan/%i" in template


PER_INSTANCE = ("Description=", "ExecStart=", "StateDirectory=")


def test_systemd_security_exposure_is_at_most_1_3():
    """systemd's own rating of the unit's sandbox (1.6 before issue 17; lower is better)."""
    import re
    import subprocess

    if shutil.which("systemd-analyze") is None:
        pytest.fail("systemd-analyze is not installed (the CI installs the systemd package)")
    res = subprocess.run(
        ["systemd-analyze", "security", "--offline=yes", str(ROOT / "systemd" / "cmcan.service")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    m = re.search(r"Overall exposure level for cmcan.service: (\d+\.\d+)", res.stdout + res.stderr)
    assert m, res.stdout + res.stderr
    assert float(m.group(1)) <= 1.3, res.stdout


def test_the_daemon_runs_with_memory_deny_write_execute(tmp_path):
    """The unit sets MemoryDenyWriteExecute=yes; the kernel's own switch for it (PR_SET_MDWE, Linux
    6.3+) shows the daemon (onnxruntime included: the model runs at start) needs no W+X memory."""
    import ctypes
    import signal
    import sys

    from tests.daemon_proc import DaemonProc, virtual_config

    if ctypes.CDLL(None, use_errno=True).prctl(66, 0, 0, 0, 0) < 0:  # PR_GET_MDWE
        pytest.skip("this kernel has no PR_SET_MDWE (Linux < 6.3)")
    launcher = tmp_path / "mdwe.py"
    launcher.write_text(
        "import ctypes, os, sys\n"
        "assert ctypes.CDLL(None).prctl(65, 1, 0, 0, 0) == 0  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN\n"
        "os.execv(sys.executable, [sys.executable, '-m', 'cmcan', *sys.argv[1:]])\n"
    )
    d = DaemonProc(tmp_path, virtual_config(tmp_path), launcher=[sys.executable, str(launcher)])
    d.signal(signal.SIGTERM)
    assert d.wait() == 0, d.stderr()


def fake_sys_class_net(root: Path, *present: str) -> Path:
    """A /sys/class/net with the given CAN links (type 280, classic MTU)."""
    for name in present:
        (root / name).mkdir(parents=True)
        (root / name / "type").write_text("280\n")
        (root / name / "mtu").write_text("16\n")
    root.mkdir(exist_ok=True)
    return root


def test_an_extra_channel_absent_at_the_start_is_a_warning_for_run_and_an_error_for_check(tmp_path, caplog):
    """A second USB CAN adapter that enumerates after the service started: `cmcan run` (the flag)
    warns, naming the channel, its field and the link it expects, and starts; `cmcan check` (no flag)
    still reports it, exit 69. The first channel and a name that can never exist stay errors."""
    import logging
    from dataclasses import replace

    from cmcan import config as cfgmod
    from cmcan.cli.errors import exit_code
    from cmcan.daemon.preflight import check_channel
    from cmcan.errors import CmcanError

    base = cfgmod.load(str(config_copy(tmp_path)))
    cfg = replace(
        base,
        bus=replace(base.bus, interface="socketcan", channel="can0"),
        channels=replace(base.channels, extra=(cfgmod.ChannelConfig("can1", bitrate=500000),)),
    )
    net = fake_sys_class_net(tmp_path / "net", "can0")
    with pytest.raises(CmcanError) as err:
        check_channel(cfg, net)
    assert exit_code(err.value) == EX_UNAVAILABLE and "channels.extra[0].channel: no network interface 'can1'" in str(
        err.value
    )
    caplog.set_level(logging.WARNING, logger="cmcan.preflight")
    assert check_channel(cfg, net, extras_may_be_absent=True) == ["can1"]
    (warning,) = [r for r in caplog.records if r.name == "cmcan.preflight"]
    assert warning.levelno == logging.WARNING
    msg = warning.getMessage()
    assert str(cfg.source) in msg and "channels.extra[0].channel: no network interface 'can1' yet" in msg
    assert "opening it when it appears" in msg and "ip link set can1 up type can bitrate 500000" in msg

    caplog.clear()
    fake_sys_class_net(net, "can1")  # it appeared
    assert check_channel(cfg, net, extras_may_be_absent=True) == [] and not caplog.records
    assert check_channel(cfg, net) == []

    only_extra = fake_sys_class_net(tmp_path / "net2", "can1")  # the first channel absent: refused either way
    for flag in (False, True):
        with pytest.raises(CmcanError) as err:
            check_channel(cfg, only_extra, extras_may_be_absent=flag)
        assert exit_code(err.value) == EX_UNAVAILABLE and "bus.channel: no network interface 'can0'" in str(err.value)

    bad = replace(cfg, channels=replace(cfg.channels, extra=(cfgmod.ChannelConfig("can1; rm"),)))
    with pytest.raises(CmcanError) as err:
        check_channel(bad, net, extras_may_be_absent=True)
    assert exit_code(err.value) == EX_CONFIG and "is not a network interface name" in str(err.value)


def held_by(lock: Path) -> int | None:
    try:
        return int(lock.read_text().strip() or 0)
    except (OSError, ValueError):
        return None


# The daemon with a pause right after it takes the state lock: the window a reset can land in held open.
SLOW_LOCK = """\
import runpy, sys, time
from cmcan.service import statefile
acquire = statefile.StateLock.acquire
def slow(self):
    held = acquire(self)
    time.sleep(1.0)
    return held
statefile.StateLock.acquire = slow
sys.argv = ["cmcan", *sys.argv[1:]]
runpy.run_module("cmcan", run_name="__main__")
"""


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGTERM])
def test_a_signal_right_after_the_lock_appears_is_the_daemons(tmp_path, sig):
    """`cmcan baseline reset` sends SIGHUP to the lock's holder as soon as the lock names it: the daemon
    then still builds its monitor, and SIGHUP's default action would end it (a clean stop to systemd).
    Its handlers are in place before the lock: SIGHUP is a reload once it runs, SIGTERM a stop."""
    launcher = tmp_path / "slow_lock.py"
    launcher.write_text(SLOW_LOCK)
    d = DaemonProc(tmp_path, virtual_config(tmp_path), wait_ready=False, launcher=[sys.executable, str(launcher)])
    lock = tmp_path / "state" / "cmcan.lock"
    try:
        assert d.wait_for(lambda: held_by(lock) == d.proc.pid or d.proc.poll() is not None, 120)
        d.signal(sig)  # within the second after the lock
        assert d.wait_for(lambda: d.count("READY=1") >= 1 or d.proc.poll() is not None, 120)
        if sig == signal.SIGHUP:
            assert d.wait_for(lambda: "reloaded" in d.stderr() or d.proc.poll() is not None)
            assert d.proc.poll() is None, d.stderr()  # alive, reloaded
            d.signal(signal.SIGTERM)
    finally:
        code = d.wait()
    err = d.stderr()
    assert code == 0, err
    assert f"received {signal.Signals(sig).name} while starting" in err  # the signal came in that window
    assert "Traceback" not in err
