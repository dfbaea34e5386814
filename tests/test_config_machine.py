"""The machine in the configuration: output quantity, nominal size and the gates scaled to it, fixed
inputs, the oil, the points table; each mistake named with its field."""

from __future__ import annotations

import copy
import json

import pytest
import yaml

from cmcan import config as cfgmod
from cmcan.cli.errors import EX_CONFIG
from cmcan.monitor.gating import GateLimits
from cmcan.schema import SchemaError
from tests.conftest import ROOT, run_cli

RIG = ROOT / "examples" / "zema-rig" / "cmcan.yaml"


def raw(path=ROOT / "config" / "cmcan.yaml"):
    return yaml.safe_load(path.read_text())


def build(doc, source="m.yaml"):
    return cfgmod.from_dict(doc, source, ROOT / "config")


def changed(doc, **changes):
    doc = copy.deepcopy(doc)
    for dotted, value in changes.items():
        node = doc
        keys = dotted.split(".")
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        if value is None:
            node.pop(keys[-1], None)
        else:
            node[keys[-1]] = value
    return doc


def test_the_reference_drive_keeps_its_gates():
    cfg = cfgmod.load()
    assert cfg.quantity == "motor_speed_rpm" and cfg.lpm_per_unit == 0.044
    assert cfg.gate_limits == GateLimits()
    assert cfg.oil.nu40_cst == 46.0


def test_the_rig_is_a_flow_machine_with_fixed_inputs():
    cfg = cfgmod.load(RIG)
    assert cfg.quantity == "flow_lpm" and cfg.motor_disp_cc is None and cfg.lpm_per_unit == 1.0
    assert cfg.drive.fixed == {"pump_speed_rpm": 1450.0, "pump_disp_cc": 4.6}
    lim = cfg.gate_limits
    assert lim.output_role == "flow_lpm" and lim.min_pump_disp_cc == pytest.approx(20 * 4.6 / 78)
    assert lim.max_std["flow_lpm"] == 0.2 and lim.window_s == 90.0  # set in the file
    assert dict(cfg.points.constants) == cfg.drive.fixed
    assert dict(cfg.points.columns) == {"dp_bar": "ps1_bar", "temp_c": "ts1_c", "flow_lpm": "fs1_lpm"}
    assert [k for k, _ in cfg.outputs.items(cfg.quantity)] == ["cm_ratio", "cm_flow", "warning"]


def test_absolute_gates_override_the_scaled_ones():
    cfg = build(changed(raw(), **{"gating.min_pump_speed_rpm": 900, "gating.min_flow_lpm": 22.0}))
    assert cfg.gate_limits.min_pump_speed_rpm == 900 and cfg.gate_limits.min_output == pytest.approx(500.0)


def test_a_smaller_machine_gets_smaller_gates():
    cfg = build(changed(raw(), **{"drive.pump_speed_nominal_rpm": 1500, "drive.pump_disp_max_cc": 39}))
    assert cfg.gate_limits.min_pump_speed_rpm == 350.0 and cfg.gate_limits.min_pump_disp_cc == 10.0
    assert cfg.gate_limits.min_output == pytest.approx(75.0)  # a quarter of the nominal flow: a quarter of 300 rpm


def test_oil_by_viscosities():
    cfg = build(changed(raw(), oil={"nu40_cst": 32.0, "nu100_cst": 5.4}))
    assert (cfg.oil.nu40_cst, cfg.oil.nu100_cst) == (32.0, 5.4)
    assert build(changed(raw(), oil={"grade": "ISO VG 68"})).oil.nu40_cst == 68.0


@pytest.mark.parametrize(
    ("changes", "needle"),
    [
        ({"drive.motor_disp_cc": None}, "drive.motor_disp_cc: missing; a motor-speed machine needs V_M"),
        ({"drive.quantity": "torque_nm"}, "drive.quantity: expected one of 'motor_speed_rpm', 'flow_lpm'"),
        ({"drive.quantity": "flow_lpm"}, "drive.motor_disp_cc: only for quantity motor_speed_rpm"),
        ({"drive.fixed.pump_speed_rpm": 1500}, "signals.pump_speed_rpm: also given as a constant in drive.fixed"),
        ({"signals.pump_disp_cc": None}, "signals.pump_disp_cc: missing; every machine must map this role"),
        ({"oil.grade": "VG47"}, "oil.grade: unknown oil grade 'VG47'"),
        ({"oil.nu40_cst": 46.0}, "oil.nu100_cst: give both nu40_cst and nu100_cst"),
        ({"oil": {"nu40_cst": 6.0, "nu100_cst": 46.0}}, "oil.nu100_cst: must be below nu40_cst"),
        ({"gating.min_flow_lpm": 10.0, "gating.min_motor_speed_rpm": 200}, "gating.min_flow_lpm: give min_motor"),
        ({"points.where": ["pump_leak"]}, "points.where[0]: 'pump_leak' is not COLUMN=VALUE"),
        (
            {"points.columns.pump_speed_rpm": "n", "drive.fixed.pump_speed_rpm": 1, "signals.pump_speed_rpm": None},
            "points.columns.pump_speed_rpm: also a constant",
        ),
        ({"points.colums": {}}, "points.colums: unknown field (did you mean 'columns'?)"),
    ],
)
def test_mistakes_are_named(changes, needle):
    with pytest.raises(SchemaError) as err:
        build(changed(raw(), **changes))
    assert needle in str(err.value) and str(err.value).startswith("m.yaml: ")


def test_flow_config_needs_the_flow_signal():
    doc = changed(raw(RIG), **{"signals.flow_lpm": None})
    with pytest.raises(SchemaError, match=r"signals\.flow_lpm: missing"):
        build(doc)


def _rig_copy(tmp_path, **changes):
    doc = changed(raw(RIG), **changes)
    doc["dbc"] = str(RIG.parent / "rig.dbc")
    if doc["model"] != "default":
        doc["model"] = str(RIG.parent / "rig.onnx")
    p = tmp_path / "rig.yaml"
    p.write_text(yaml.safe_dump(doc))
    return p


@pytest.mark.parametrize(
    ("changes", "needle"),
    [
        ({"oil.grade": "VG68"}, "trained for an oil of 46 cSt at 40 C and 6.8 cSt at 100 C"),
        ({"model": "default"}, "predicts motor_speed_rpm, the configuration's drive.quantity is flow_lpm"),
        ({"outputs.cm_flow": {"message": "CM_SPEED"}}, "outputs.cm_flow.message: no message 'CM_SPEED'"),
    ],
)
def test_check_names_a_model_or_output_that_does_not_fit_the_machine(tmp_path, changes, needle):
    cfg = _rig_copy(tmp_path, **changes)
    r = run_cli("check", "--config", str(cfg), "--json")
    doc = json.loads(r.stdout)
    assert r.returncode == EX_CONFIG and needle in doc["error"], doc


# -- relative paths: the file's relative to the file, the command line's to the working directory -----


def _relative_state_config(tmp_path, **changes):
    """A copy of the shipped configuration in ``tmp/x`` with ``state.directory: st`` (and ``tmp/x/st``
    made); the working directory moved to an empty ``tmp/elsewhere`` by the caller."""
    folder = tmp_path / "x"
    (folder / "st").mkdir(parents=True)
    doc = changed(raw(), **{"state.directory": "st", "dbc": str(ROOT / "dbc" / "cmcan.dbc"), **changes})
    p = folder / "r.yaml"
    p.write_text(yaml.safe_dump(doc))
    (tmp_path / "elsewhere").mkdir()
    return p


def test_a_relative_state_directory_is_relative_to_the_configuration_file(tmp_path, monkeypatch):
    """As dbc, model and the TLS files are: under systemd the working directory is /."""
    p = _relative_state_config(tmp_path, **{"uplink.outbox.file": "ob/box.sqlite"})
    monkeypatch.chdir(tmp_path / "elsewhere")
    cfg = cfgmod.load(p)
    assert cfg.state.directory == tmp_path / "x" / "st"
    assert cfg.uplink.outbox.path == tmp_path / "x" / "st" / "ob" / "box.sqlite"  # relative to the state
    # --state-dir is a command line's path: relative to the working directory; the outbox moves with it
    over = cfgmod.with_overrides(cfg, state_dir="mine")
    assert over.state.directory.resolve() == tmp_path / "elsewhere" / "mine"
    assert over.uplink.outbox.path.resolve() == tmp_path / "elsewhere" / "mine" / "ob" / "box.sqlite"
    away = cfgmod.load(_relative_state_config(tmp_path / "b", **{"uplink.outbox.file": "/var/spool/ob.sqlite"}))
    assert cfgmod.with_overrides(away, state_dir="mine").uplink.outbox.path == away.uplink.outbox.path


def test_check_state_finds_a_relative_state_directory_from_anywhere(tmp_path):
    p = _relative_state_config(tmp_path)
    for cwd in (tmp_path / "elsewhere", "/"):
        r = run_cli("check", "--config", str(p), "--state", "--json", cwd=cwd)
        assert r.returncode == 0, r.stdout + r.stderr
        assert json.loads(r.stdout)["state"]["file"] == str(tmp_path / "x" / "st" / "state.json")
