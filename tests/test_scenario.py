"""Scenario files: shipped ones load; mistakes get errors that name the file, field and range."""

from pathlib import Path

import pytest
import yaml

from cmcan.schema import SchemaError
from cmcan.sim import scenario as scn
from tests.conftest import small_scenario

SHIPPED = sorted(scn.shipped_dir().glob("*.yaml"))


def write(tmp_path: Path, data) -> Path:
    p = tmp_path / "scn.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_scenarios_load(path):
    s = scn.load(path)
    assert s.name == path.stem


def test_paper_scenarios_are_shipped():
    names = {p.stem for p in SHIPPED}
    assert {
        "single_set_healthy",
        "single_set_leakage",
        "two_set_train",
        "two_set_validation",
        "run_to_failure",
        "training_healthy",
        "healthy_mixed_100h",
    } <= names


def error_of(tmp_path, data) -> SchemaError:
    p = write(tmp_path, data)
    with pytest.raises(SchemaError) as exc:
        scn.load(p)
    assert str(p) in str(exc.value)
    return exc.value


def test_out_of_range_names_file_field_and_range(tmp_path):
    d = small_scenario(duty={"kind": "constant", "pump_speed_rpm": 9000, "pump_disp_pct": 80, "dp_bar": 300})
    err = error_of(tmp_path, d)
    assert err.path == "duty.pump_speed_rpm"
    assert "[0, 3600] rpm" in str(err) and "9000" in str(err)


def test_mistyped_field_is_named_with_a_suggestion(tmp_path):
    d = small_scenario()
    d["duty"] = {"kind": "constant", "pump_sped_rpm": 2000, "pump_disp_pct": 80, "dp_bar": 300}
    err = error_of(tmp_path, d)
    assert err.path == "duty.pump_sped_rpm"
    assert "did you mean 'pump_speed_rpm'" in str(err)


def test_wrong_type(tmp_path):
    err = error_of(tmp_path, small_scenario(duration_h="ten"))
    assert err.path == "duration_h" and "expected a number" in str(err)


def test_unknown_duty_kind_lists_the_choices(tmp_path):
    err = error_of(tmp_path, small_scenario(duty={"kind": "tractor"}))
    assert err.path == "duty.kind"
    assert "'wheel_loader'" in str(err) and "'tractor'" in str(err)


def test_missing_required_field(tmp_path):
    d = small_scenario()
    del d["seed"]
    err = error_of(tmp_path, d)
    assert err.path == "seed" and "missing" in str(err)


def test_event_field_errors_carry_the_list_index(tmp_path):
    d = small_scenario(
        events=[
            {"type": "leakage", "start_h": 0.01, "extra_lpm": 5},
            {"type": "wear", "component": "gearbox", "start_h": 0.0, "fail_h": 0.01},
        ]
    )
    err = error_of(tmp_path, d)
    assert err.path == "events[1].component" and "'pump', 'motor'" in str(err)


def test_wear_must_fail_after_it_starts(tmp_path):
    d = small_scenario(events=[{"type": "wear", "component": "pump", "start_h": 0.01, "fail_h": 0.005}])
    err = error_of(tmp_path, d)
    assert err.path == "events[0].fail_h"


def test_event_after_the_end_of_the_run(tmp_path):
    err = error_of(tmp_path, small_scenario(events=[{"type": "replace", "component": "pump", "at_h": 5}]))
    assert err.path == "events[0]" and "after the end" in str(err)


def test_table_times_must_increase(tmp_path):
    pts = [
        {"t_s": 0, "pump_speed_rpm": 1000, "pump_disp_pct": 50, "dp_bar": 100},
        {"t_s": 0, "pump_speed_rpm": 1000, "pump_disp_pct": 50, "dp_bar": 100},
    ]
    err = error_of(tmp_path, small_scenario(duty={"kind": "table", "points": pts}))
    assert err.path == "duty.points"


def test_invalid_yaml_names_the_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("name: x\nseed: [1,\n")
    with pytest.raises(SchemaError) as exc:
        scn.load(p)
    assert "bad.yaml" in str(exc.value) and "line" in str(exc.value)


def test_missing_file(tmp_path):
    with pytest.raises(SchemaError, match="file not found"):
        scn.load(tmp_path / "nope.yaml")


def test_loss_terms_switch_off_and_set():
    d = small_scenario(losses={"pump": {"laminar": {"enabled": False}, "turbulent": {"ct": 2e-5}}})
    s = scn.from_dict(d)
    assert s.params.pump.laminar_cs == 0.0
    assert s.params.pump.turbulent_ct == 2e-5
    assert s.params.motor.laminar_cs > 0.0  # untouched terms keep the reference defaults
