"""Operating-point tables (cmcan.io.points): columns, constants, row filters and their errors."""

import csv
import io

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st

from cmcan.cli.errors import EX_DATAERR, EX_NOINPUT
from cmcan.io.points import MISSING_CELLS, Condition, PointsError, PointSpec, cell_value, read_points
from tests.conftest import ROOT, run_cli
from tests.test_bad_inputs import refused

DECIMAL_COMMA_HINT = "is not a number (decimal comma? cmcan reads '.' decimals)"

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
    with pytest.raises(PointsError, match=r"t.csv: line 3: column 'fs1': 'x' is not a number$") as exc:
        read_points(p, spec, ROLES)
    assert exc.value.problem == "data"
    spec = PointSpec({"dp_bar": "ps9", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1.0}, source="rig.yaml")
    with pytest.raises(PointsError, match=r"no column 'ps9' \(columns.dp_bar in rig.yaml\); the file has ps1, fs1"):
        read_points(p, spec, ROLES)
    # a column the command line gave is the command line's, not the file's it was merged into
    cli = PointSpec({"dp_bar": "ps8"}, {}, (), "the command line")
    merged = spec.merged(cli)
    with pytest.raises(PointsError, match=r"no column 'ps8' \(columns.dp_bar in the command line\)"):
        read_points(p, merged, ROLES)
    with pytest.raises(PointsError, match=r"no column 'lot' \(where in the command line\)"):
        read_points(
            p,
            PointSpec({"dp_bar": "ps1", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1.0}, source="rig.yaml").merged(
                PointSpec({}, {}, (Condition.parse("lot=3"),), "the command line")
            ),
            ROLES,
        )
    with pytest.raises(PointsError, match=r"no column 'fs9' \(columns.flow_lpm in rig.yaml\)"):
        read_points(
            p,
            PointSpec({"dp_bar": "ps1", "flow_lpm": "fs9"}, {"pump_speed_rpm": 1.0}, source="rig.yaml").merged(
                PointSpec(source="the command line")
            ),
            ROLES,
        )
    with pytest.raises(PointsError, match=r"no column 'PS1' \(columns.dp_bar in rig.yaml\) \(did you mean 'ps1'\?"):
        read_points(
            p, PointSpec({"dp_bar": "PS1", "flow_lpm": "fs1"}, {"pump_speed_rpm": 1.0}, source="rig.yaml"), ROLES
        )
    with pytest.raises(PointsError, match="no column or constant for pump_speed_rpm") as exc:
        read_points(p, PointSpec({"dp_bar": "ps1", "flow_lpm": "fs1"}), ROLES)
    assert exc.value.problem == "spec"
    with pytest.raises(PointsError, match="file not found") as exc:
        read_points(tmp_path / "none.csv", PointSpec({}, dict.fromkeys(ROLES, 1.0)), ROLES)
    assert exc.value.problem == "noinput"
    q = table(tmp_path, "ps1,fs1\n150,\n", "empty.csv")
    with pytest.raises(PointsError, match="line 2: column 'fs1' \\(flow_lpm\\) is empty"):
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


# -- what a table may look like, and what it may not (the shared CSV vocabulary) -------------------

RIG_CONFIG = ROOT / "examples" / "zema-rig" / "cmcan.yaml"
RIG_DATA = ROOT / "examples" / "zema-rig" / "data" / "cycles.csv"
RIG_ROLES = ("dp_bar", "temp_c", "flow_lpm")
RIG_SPEC = PointSpec({"dp_bar": "ps1_bar", "temp_c": "ts1_c", "flow_lpm": "fs1_lpm"})


def rig_rows(n: int = 60) -> list[list[str]]:
    """The header and the first ``n`` cycles of the shipped rig data, as cells."""
    with open(RIG_DATA, newline="", encoding="utf-8") as f:
        return list(csv.reader(f))[: n + 1]


def write(path, rows, sep=",", newline="\n", bom=False):
    text = newline.join(sep.join(r) for r in rows) + newline
    path.write_bytes(("\ufeff" if bom else "").encode() + text.encode())
    return path


@pytest.mark.parametrize(
    ("sep", "newline", "bom", "reorder"),
    [(",", "\n", False, False), (";", "\r\n", True, False), ("\t", "\n", True, True), (",", "\r\n", False, True)],
)
def test_separators_bom_crlf_and_column_order_read_the_same(tmp_path, sep, newline, bom, reorder):
    rows = rig_rows()
    want = read_points(write(tmp_path / "plain.csv", rows), RIG_SPEC, RIG_ROLES)
    if reorder:  # columns reversed, and an extra one cmcan does not read
        rows = [[*r[::-1], "x" if i else "note"] for i, r in enumerate(rows)]
    got = read_points(write(tmp_path / "v.csv", rows, sep, newline, bom), RIG_SPEC, RIG_ROLES)
    for r in RIG_ROLES:
        assert got.values[r].tolist() == want.values[r].tolist()
    assert got.rows.tolist() == want.rows.tolist() == list(range(1, 61))


def test_decimal_commas_are_an_error_with_a_hint(tmp_path):
    rows = [[c.replace(".", ",") for c in r] for r in rig_rows()]
    p = write(tmp_path / "comma.csv", rows, ";")
    cell = rows[1][rows[0].index("ps1_bar")]
    for lenient in (False, True):  # a decimal comma is no missing value, however missing values are treated
        with pytest.raises(PointsError) as exc:
            read_points(p, RIG_SPEC, RIG_ROLES, missing_as_nan=lenient)
        assert str(exc.value) == (f"{p}: line 2: column 'ps1_bar': {cell!r} {DECIMAL_COMMA_HINT}")
        assert exc.value.problem == "data"


@pytest.mark.parametrize("cell", ["", "  ", "nan", "NaN", "NA", "n/a", "N/A", "#N/A", "null", "None"])
def test_missing_values_are_nan_when_allowed_and_named_when_not(tmp_path, cell):
    rows = rig_rows(5)
    rows[3][rows[0].index("ts1_c")] = cell
    p = write(tmp_path / "m.csv", rows)
    pts = read_points(p, RIG_SPEC, RIG_ROLES, missing_as_nan=True)
    assert np.isnan(pts.values["temp_c"]).tolist() == [False, False, True, False, False]
    assert pts.cells[2][rows[0].index("ts1_c")] == cell.strip()  # carried on as written
    with pytest.raises(PointsError, match=r"m.csv: line 4: column 'ts1_c' \(temp_c\) (is empty|holds no value)"):
        read_points(p, RIG_SPEC, RIG_ROLES)


@pytest.mark.parametrize(
    ("cell", "why"),
    [
        ("warm", "is not a number"),
        ("1e999", "is not a finite number"),
        ("inf", "is not a number"),
        ("1_000", "is not a number"),
    ],
)
def test_text_in_a_column_cmcan_reads_is_an_error_even_where_missing_values_are_allowed(tmp_path, cell, why):
    rows = rig_rows(5)
    rows[4][rows[0].index("fs1_lpm")] = cell
    p = write(tmp_path / "t.csv", rows)
    with pytest.raises(PointsError, match=rf"t.csv: line 5: column 'fs1_lpm': '{cell}' {why}$"):
        read_points(p, RIG_SPEC, RIG_ROLES, missing_as_nan=True)


def test_text_in_a_column_cmcan_does_not_read_is_ignored(tmp_path):
    rows = rig_rows(5)
    rows[2][rows[0].index("ps2_bar")] = "sensor off"
    rows[3][rows[0].index("ps1_bar")] = "overload"  # a row --where leaves out may hold anything
    spec = PointSpec(RIG_SPEC.columns, where=(Condition.parse(f"cycle!={rows[3][0]}"),))
    pts = read_points(write(tmp_path / "t.csv", rows), spec, RIG_ROLES)
    assert pts.rows.tolist() == [1, 2, 4, 5]


@pytest.mark.parametrize("cut", [3, -2])
def test_a_ragged_row_is_named(tmp_path, cut):
    rows = rig_rows(5)
    rows[3] = rows[3][:cut] if cut > 0 else [*rows[3], "1", "2"]
    p = write(tmp_path / "r.csv", rows, ";")
    n = len(rows[3])
    with pytest.raises(PointsError, match=rf"r.csv: line 4: {n} cells, but the header \(line 1\) has 23 columns"):
        read_points(p, RIG_SPEC, RIG_ROLES, missing_as_nan=True)


def test_a_duplicated_column_name_cmcan_reads_is_an_error(tmp_path):
    rows = rig_rows(5)
    rows[0][rows[0].index("ps2_bar")] = "ps1_bar"
    p = write(tmp_path / "d.csv", rows)
    with pytest.raises(PointsError, match=r"d.csv: column 'ps1_bar' appears twice \(columns 7 and 8\)") as exc:
        read_points(p, RIG_SPEC, RIG_ROLES)
    assert exc.value.problem == "data"
    rows[0][rows[0].index("cooler_pct")] = "ps1_bar"
    with pytest.raises(PointsError, match=r"'ps1_bar' appears 3 times \(columns 2, 7 and 8\)"):
        read_points(write(tmp_path / "d.csv", rows), RIG_SPEC, RIG_ROLES)
    # a where column counts as read
    rows = rig_rows(5)
    rows[0][0] = "pump_leak"
    spec = PointSpec(RIG_SPEC.columns, where=(Condition.parse("pump_leak=0"),))
    with pytest.raises(PointsError, match=r"'pump_leak' appears twice \(columns 1 and 4\)"):
        read_points(write(tmp_path / "d.csv", rows), spec, RIG_ROLES)


def test_a_duplicated_column_name_cmcan_does_not_read_is_ignored(tmp_path):
    rows = rig_rows(5)
    rows[0][rows[0].index("ps3_bar")] = "ps2_bar"
    rows[0][rows[0].index("ts2_c")] = ""
    rows[0][rows[0].index("ts3_c")] = ""
    pts = read_points(write(tmp_path / "d.csv", rows), RIG_SPEC, RIG_ROLES)
    assert len(pts) == 5 and pts.header.count("ps2_bar") == 2 and pts.header.count("") == 2


def test_a_missing_label_meets_no_condition(tmp_path):
    rows = rig_rows(4)
    rows[2][rows[0].index("pump_leak")] = ""
    p = write(tmp_path / "l.csv", rows)
    for cond in ("pump_leak=0", "pump_leak!=1", "pump_leak<1"):
        spec = PointSpec(RIG_SPEC.columns, where=(Condition.parse(cond),))
        assert read_points(p, spec, RIG_ROLES).rows.tolist() == [1, 3, 4], cond


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_a_number_reads_back_as_itself(x):
    for text in (repr(x), f"{x:.6e}", f" {x:.4f} ", f"{x:E}"):
        assert cell_value(text) == float(text)


def _loadtxt(text: str) -> float | None:
    """What numpy's loadtxt (the run CSV's fast path) reads from one cell: a finite number, or None."""
    try:
        v = float(np.loadtxt(io.StringIO(text), delimiter="|", ndmin=1, comments=None)[0])
    except (ValueError, IndexError):
        return None
    return v if np.isfinite(v) else None


CELLS = st.one_of(
    st.text(alphabet=st.sampled_from("0123456789.,eE+-_ naN/#ulIf\u0661"), max_size=10),
    st.floats(allow_nan=False, allow_infinity=False).map(lambda x: f"{x:.5g}"),
    st.floats(0, 1e4).map(lambda x: f"{x:.3f}".replace(".", ",")),
    st.integers(309, 999).map(lambda e: f"-2.5e{e}"),
    st.sampled_from(sorted(MISSING_CELLS)).map(str.upper),
    st.sampled_from(sorted(MISSING_CELLS)).map(lambda m: f" {m} "),
)


@given(CELLS)
def test_a_cell_is_a_number_a_missing_value_or_an_error(text):
    """Whatever a cell holds, the answer is one of three, and the same number numpy's loadtxt (the run
    CSV's fast path) reads from it: neither path accepts what the other refuses."""
    try:
        value = cell_value(text)
    except ValueError as exc:
        assert str(exc) in ("is not a number", "is not a finite number", DECIMAL_COMMA_HINT)
        assert _loadtxt(text) is None
        event(str(exc))
        return
    if value is None:
        assert text.strip().lower() in MISSING_CELLS
        event("missing")
    else:
        assert value == _loadtxt(text)
        event("number")


def test_the_cli_refuses_a_decimal_comma_table_naming_line_and_column(tmp_path):
    rows = [[c.replace(".", ",") for c in r] for r in rig_rows()]
    p = write(tmp_path / "comma.csv", rows, ";")
    for cmd in ("train", "score"):
        res = run_cli(cmd, str(p), "--points", "--config", str(RIG_CONFIG), "--out", str(tmp_path / f"{cmd}.out"))
        refused(res, EX_DATAERR, "comma.csv", "line 2", "'ps1_bar'", "156,3", "decimal comma")
        assert not (tmp_path / f"{cmd}.out").exists()


def test_the_cli_refuses_a_duplicated_column_and_a_ragged_row(tmp_path):
    rows = rig_rows()
    rows[0][rows[0].index("ps2_bar")] = "ps1_bar"
    p = write(tmp_path / "dup.csv", rows)
    res = run_cli("score", str(p), "--points", "--config", str(RIG_CONFIG), "--out", str(tmp_path / "s.csv"))
    refused(res, EX_DATAERR, "dup.csv", "column 'ps1_bar' appears twice (columns 7 and 8)")
    rows = rig_rows()
    rows[10] = rows[10][:-1]
    p = write(tmp_path / "ragged.csv", rows)
    res = run_cli("train", str(p), "--points", "--config", str(RIG_CONFIG), "--out", str(tmp_path / "m.onnx"))
    refused(res, EX_DATAERR, "ragged.csv", "line 11: 22 cells", "23 columns")


def test_the_cli_says_a_missing_table_is_no_input(tmp_path):
    out = tmp_path / "s.csv"
    res = run_cli("score", str(tmp_path / "gone.csv"), "--points", "--config", str(RIG_CONFIG), "--out", str(out))
    refused(res, EX_NOINPUT, "gone.csv", "file not found")


def test_a_tables_other_columns_are_numbers_by_the_same_rule(tmp_path):
    """Label columns (score's --label, --where on the operating points) read cells as the readers do:
    'inf' or '1_000' is no number there either, a text label is NaN."""
    from cmcan.model.features import _floats

    got = _floats(["1.5", "", "n/a", "inf", "1_000", "healthy", " -2e3 "])
    assert np.isnan(got[[1, 2, 3, 4, 5]]).all() and got[0] == 1.5 and got[6] == -2000.0
