"""Operating-point tables (cmcan.io.points): columns, constants, row filters and their errors."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cmcan.io.points import Condition, PointsError, PointSpec, read_points

ROLES = ("pump_speed_rpm", "dp_bar", "flow_lpm")


def table(tmp_path, text, name="t.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_columns_constants_and_a_filter(tmp_path):
    p = table(tmp_path, "cycle,leak,ps1,fs1\n1,0,150,6.5\n2,1,151,6.4\n3,0,152,6.6\n")
    spec = PointSpec({"dp_bar": "ps1", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1450.0}, (Condition.parse("leak=0"),))
    pts = read_points(p, spec, ROLES)
    assert pts.rows.tolist() == [1, 3] and pts.total_rows == 3
    assert pts.values["dp_bar"].tolist() == [150.0, 152.0]
    assert pts.values["pump_speed_rpm"].tolist() == [1450.0, 1450.0]
    assert pts.measured == {"dp_bar", "flow_lpm"}


def test_semicolon_tables_and_blank_lines(tmp_path):
    p = table(tmp_path, "ps1;fs1\n150;6.5\n\n151;6.4\n")
    pts = read_points(p, PointSpec({"dp_bar": "ps1", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1.0}), ROLES)
    assert pts.values["flow_lpm"].tolist() == [6.5, 6.4]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("a=1", ("a", "==", 1.0)),
        ("a == 1", ("a", "==", 1.0)),
        ("pump_leak!=0", ("pump_leak", "!=", 0.0)),
        ("t_c<=40.5", ("t_c", "<=", 40.5)),
        ("t_c >= -3", ("t_c", ">=", -3.0)),
        ("x<1e3", ("x", "<", 1000.0)),
        ("x>2", ("x", ">", 2.0)),
    ],
)
def test_conditions_parse(text, expected):
    c = Condition.parse(text)
    assert (c.column, c.op, c.value) == expected


@pytest.mark.parametrize("text", ["pump_leak", "=3", "a=", "a=b", "a=>3"])
def test_bad_conditions_are_named(text):
    with pytest.raises(PointsError, match="--where") as exc:
        Condition.parse(text)
    assert exc.value.problem == "spec"


@given(
    op=st.sampled_from(["=", "==", "!=", "<", "<=", ">", ">="]),
    value=st.integers(-5, 5),
    data=st.lists(st.integers(-5, 5), min_size=1, max_size=30),
)
def test_a_condition_keeps_exactly_the_rows_it_should(op, value, data):
    c = Condition.parse(f"col{op}{value}")
    keep = c.holds(np.asarray(data, dtype=float))
    py = {"=": "==", "==": "==", "!=": "!=", "<": "<", "<=": "<=", ">": ">", ">=": ">="}[op]
    assert keep.tolist() == [eval(f"{x} {py} {value}") for x in data]


def test_errors_name_the_file_the_column_and_the_row(tmp_path):
    p = table(tmp_path, "ps1,fs1\n150,6.5\n151,x\n")
    spec = PointSpec({"dp_bar": "ps1", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1.0})
    with pytest.raises(PointsError, match=r"t.csv: row 2: column 'fs1': 'x' is not a number") as exc:
        read_points(p, spec, ROLES)
    assert exc.value.problem == "data"
    spec = PointSpec({"dp_bar": "ps9", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1.0}, source="rig.yaml")
    with pytest.raises(PointsError, match=r"no column 'ps9' \(columns.dp_bar in rig.yaml\); the file has ps1, fs1"):
        read_points(p, spec, ROLES)
    with pytest.raises(PointsError, match="no column or constant for pump_speed_rpm") as exc:
        read_points(p, PointSpec({"dp_bar": "ps1", "flow_lpm": "fs1"}), ROLES)
    assert exc.value.problem == "spec"
    with pytest.raises(PointsError, match="file not found") as exc:
        read_points(tmp_path / "none.csv", PointSpec({}, dict.fromkeys(ROLES, 1.0)), ROLES)
    assert exc.value.problem == "noinput"
    q = table(tmp_path, "ps1,fs1\n150,\n", "empty.csv")
    with pytest.raises(PointsError, match="row 1: column 'fs1' \\(flow_lpm\\) is empty"):
        read_points(q, PointSpec({"dp_bar": "ps1", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1.0}), ROLES)
    spec = PointSpec({"dp_bar": "ps1", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1.0}, (Condition.parse("ps1>500"),))
    with pytest.raises(PointsError, match=r"0 of 2 rows kept \(ps1>500\)"):
        read_points(p, spec, ROLES, min_rows=1)
    # a row the filter leaves out may hold anything
    spec = PointSpec({"dp_bar": "ps1", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1.0}, (Condition.parse("ps1<151"),))
    assert read_points(p, spec, ROLES).values["flow_lpm"].tolist() == [6.5]


def test_spec_files_are_checked(tmp_path):
    good = tmp_path / "s.yaml"
    good.write_text("columns: {dp_bar: ps1}\nconstants: {pump_speed_rpm: 1450}\nwhere: [leak=0]\n")
    spec = PointSpec.load(good)
    assert spec.columns == {"dp_bar": "ps1"} and spec.constants == {"pump_speed_rpm": 1450.0}
    assert [str(c) for c in spec.where] == ["leak=0"]
    for text, msg in [
        ("colums: {}\n", "colums: unknown field"),
        ("constants: {pump_speed_rpm: fast}\n", "constants.pump_speed_rpm: expected a number"),
        ("columns: {dp_bar: ps1}\nconstants: {dp_bar: 3}\n", "dp_bar: given both as a column and as a constant"),
        ("where: [leak]\n", r"where\[0\]"),
        ("- 1\n", "expected a mapping"),
    ]:
        bad = tmp_path / "bad.yaml"
        bad.write_text(text)
        with pytest.raises(PointsError, match=msg) as exc:
            PointSpec.load(bad)
        assert exc.value.problem == "spec" and "bad.yaml" in str(exc.value)


def test_command_line_entries_take_precedence():
    base = PointSpec({"dp_bar": "ps1", "temp_c": "ts1"}, {"pump_speed_rpm": 1450.0}, (Condition.parse("a=0"),))
    cli = PointSpec({"pump_speed_rpm": "n"}, {"temp_c": 40.0}, (Condition.parse("b=1"),))
    m = base.merged(cli)
    assert m.columns == {"dp_bar": "ps1", "pump_speed_rpm": "n"}
    assert m.constants == {"temp_c": 40.0}
    assert [str(c) for c in m.where] == ["a=0", "b=1"]
