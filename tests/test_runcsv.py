"""Run CSVs (cmcan.io.runcsv): the time series cmcan train, evaluate and gap read, with the same CSV
vocabulary as operating-point tables (separators, BOM, missing values, errors naming line and column)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.cli.errors import EX_DATAERR
from cmcan.errors import Kind
from cmcan.io.runcsv import RunCsvError, read_run_csv, write_run_csv
from tests.conftest import ROOT, run_cli
from tests.test_bad_inputs import refused

RIG = ROOT / "examples" / "zema-rig"
REQUIRED = ("time_s", "dp_bar", "temp_c", "flow_lpm")


def rig_series(cycles: int = 40) -> list[list[str]]:
    """A 1 Hz time series from the shipped rig data: each of the first healthy cycles' means held for
    60 s with a little deterministic noise (the rig's pump speed and displacement are constants)."""
    with open(RIG / "data" / "cycles.csv", newline="", encoding="utf-8") as f:
        cyc = [r for r in csv.DictReader(f) if r["pump_leak"] == "0"][:cycles]
    rng = np.random.default_rng(0)
    rows = [[*REQUIRED, "pump_leak"]]
    for i, r in enumerate(cyc):
        for k in range(60):
            e = rng.normal(0.0, 1.0, 3)
            rows.append(
                [
                    f"{i * 60 + k:.1f}",
                    f"{float(r['ps1_bar']) + 0.3 * e[0]:.4f}",
                    f"{float(r['ts1_c']) + 0.02 * e[1]:.4f}",
                    f"{float(r['fs1_lpm']) + 0.005 * e[2]:.5f}",
                    r["pump_leak"],
                ]
            )
    return rows


def write(path, rows, sep=",", newline="\n", bom=False):
    text = newline.join(sep.join(r) for r in rows) + newline
    path.write_bytes(("\ufeff" if bom else "").encode() + text.encode())
    return path


def small() -> list[list[str]]:
    return rig_series(1)[:6]


@pytest.mark.parametrize(
    ("sep", "newline", "bom"), [(",", "\n", True), (";", "\n", False), ("\t", "\r\n", True), (";", "\r\n", True)]
)
def test_separators_bom_and_crlf_read_the_same(tmp_path, sep, newline, bom):
    rows = rig_series(3)
    want = read_run_csv(write(tmp_path / "plain.csv", rows), REQUIRED)
    got = read_run_csv(write(tmp_path / "v.csv", rows, sep, newline, bom), REQUIRED)
    assert list(got) == list(want) == [*REQUIRED, "pump_leak"]
    for k in want:
        assert got[k].tolist() == want[k].tolist()


def test_an_unused_text_column_is_ignored(tmp_path):
    rows = [[*r, "operator" if i == 0 else "anna"] for i, r in enumerate(small())]
    rows[3][-1] = "42"  # a column with text is left out whole, whatever else it holds
    cols = read_run_csv(write(tmp_path / "t.csv", rows), REQUIRED)
    assert list(cols) == [*REQUIRED, "pump_leak"]
    assert cols["dp_bar"].tolist() == [float(r[1]) for r in rows[1:]]


@pytest.mark.parametrize("cell", ["", "nan", "NA", "n/a", "#N/A", " null "])
def test_a_missing_value_in_a_column_cmcan_reads_skips_that_row(tmp_path, cell, caplog):
    rows = small()
    rows[2][1] = cell  # line 3
    rows[4][4] = ""  # a column cmcan does not require: NaN, the row stays
    with caplog.at_level("WARNING", logger="cmcan.io"):
        cols = read_run_csv(write(tmp_path / "b.csv", rows), REQUIRED)
    assert cols["time_s"].tolist() == [0.0, 2.0, 3.0, 4.0]
    assert cols.skipped_lines == (3,)
    assert "b.csv: 1 of 5 rows left out: a value cmcan reads is missing (lines 3)" in caplog.text
    assert np.isnan(cols["pump_leak"]).tolist() == [False, False, True, False]


def test_no_complete_row_is_an_error(tmp_path):
    rows = small()
    for r in rows[1:]:
        r[2] = ""
    with pytest.raises(RunCsvError, match=r"b.csv: no row has a value in every column .* 'temp_c' is missing in 5"):
        read_run_csv(write(tmp_path / "b.csv", rows), REQUIRED)


@pytest.mark.parametrize(
    ("cell", "why"),
    [
        ("abc", "is not a number"),
        ("156,4", r"is not a number \(decimal comma\? cmcan reads '.' decimals\)"),
        ("inf", "is not a number"),
        ("1e999", "is not a finite number"),
    ],
)
def test_text_in_a_column_cmcan_reads_is_named(tmp_path, cell, why):
    rows = small()
    rows[4][1] = cell
    with pytest.raises(RunCsvError, match=rf"t.csv: line 5: column 'dp_bar': '{cell}' {why}$") as exc:
        read_run_csv(write(tmp_path / "t.csv", rows, ";"), REQUIRED)
    assert exc.value.kind is Kind.DATA


@pytest.mark.parametrize("extra", [-1, 2])
def test_a_ragged_row_is_named(tmp_path, extra):
    rows = small()
    rows[3] = rows[3][:extra] if extra < 0 else [*rows[3], *["1"] * extra]
    with pytest.raises(RunCsvError, match=rf"r.csv: line 4: {len(rows[3])} cells, but the header \(line 1\) has 5"):
        read_run_csv(write(tmp_path / "r.csv", rows), REQUIRED)


def test_duplicated_names(tmp_path):
    rows = small()
    rows[0][2] = "dp_bar"
    with pytest.raises(RunCsvError, match=r"d.csv: column 'dp_bar' appears twice \(columns 2 and 3\)"):
        read_run_csv(write(tmp_path / "d.csv", rows), ("time_s", "dp_bar"))
    # a name given twice that cmcan does not require is left out (which one would be meant?)
    cols = read_run_csv(write(tmp_path / "d.csv", rows), ("time_s", "flow_lpm"))
    assert list(cols) == ["time_s", "flow_lpm", "pump_leak"]


def test_header_errors(tmp_path):
    p = write(tmp_path / "h.csv", [["time_s", "dp_bar"], ["0", "1"]], bom=True)
    with pytest.raises(RunCsvError, match=r"h.csv: missing column\(s\) temp_c, flow_lpm; the file has time_s, dp_bar$"):
        read_run_csv(p, REQUIRED)
    (tmp_path / "e.csv").write_text("")
    with pytest.raises(RunCsvError, match=r"e\.csv: empty file"):
        read_run_csv(tmp_path / "e.csv", REQUIRED)
    with pytest.raises(RunCsvError, match=r"none\.csv: file not found") as exc:
        read_run_csv(tmp_path / "none.csv", REQUIRED)
    assert exc.value.kind is Kind.NO_INPUT
    (tmp_path / "l.csv").write_bytes("time_s,temp_\xb0c\n0,1\n".encode("latin-1"))
    with pytest.raises(RunCsvError, match=r"l.csv: not a text CSV file \(not UTF-8\)"):
        read_run_csv(tmp_path / "l.csv")
    cols = read_run_csv(write(tmp_path / "only.csv", [list(REQUIRED)]), REQUIRED)
    assert list(cols) == list(REQUIRED) and all(len(v) == 0 for v in cols.values())


@settings(max_examples=40, deadline=None)
@given(
    data=st.lists(
        st.lists(st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False), min_size=3, max_size=3),
        min_size=1,
        max_size=30,
    ),
    sep=st.sampled_from([",", ";", "\t"]),
)
def test_numpy_and_the_cell_by_cell_path_agree(tmp_path_factory, data, sep):
    """A clean file is read by numpy's loadtxt; a text column sends it down the cell-by-cell path:
    both give the same numbers."""
    d = tmp_path_factory.mktemp("agree")
    rows = [["a", "b", "c"], *([repr(x) for x in r] for r in data)]
    fast = read_run_csv(write(d / "fast.csv", rows, sep), ("a", "b"))
    slow = read_run_csv(write(d / "slow.csv", [[*r, "note" if i == 0 else "x"] for i, r in enumerate(rows)], sep))
    assert list(fast) == list(slow) == ["a", "b", "c"]
    for k in fast:
        assert fast[k].tolist() == slow[k].tolist() == [r[ord(k) - ord("a")] for r in data]


def test_what_simulate_writes_reads_back(tmp_path):
    cols = {"time_s": np.arange(5) * 0.1, "dp_bar": np.linspace(100, 200, 5), "true_failed": np.zeros(5)}
    write_run_csv(tmp_path / "r.csv", cols)
    back = read_run_csv(tmp_path / "r.csv", ("time_s", "dp_bar"))
    assert list(back) == list(cols) and back.skipped_lines == ()
    np.testing.assert_allclose(back["dp_bar"], cols["dp_bar"])


# -- through the command line -------------------------------------------------------------------


def train(tmp_path, data, name):
    return run_cli("train", str(data), "--config", str(RIG / "cmcan.yaml"), "--out", str(tmp_path / name), "--json")


def test_train_reads_a_spreadsheet_export_like_the_plain_file(tmp_path):
    """BOM, ';', CRLF, a text column and reordered columns: the same model as from the plain file; a
    few blank cells lose those samples only."""
    rows = rig_series()
    plain = train(tmp_path, write(tmp_path / "plain.csv", rows), "a.onnx")
    assert plain.returncode == 0, plain.stderr
    export = [[r[3], r[0], "operator" if i == 0 else "anna", r[2], r[1]] for i, r in enumerate(rows)]
    res = train(tmp_path, write(tmp_path / "export.csv", export, ";", "\r\n", bom=True), "b.onnx")
    assert res.returncode == 0, res.stderr
    a, b = json.loads(plain.stdout), json.loads(res.stdout)
    assert a["physics"] == b["physics"] and a["residual_stats"] == b["residual_stats"]
    for i in range(5, len(rows), 100):
        rows[i][1] = ""
    res = train(tmp_path, write(tmp_path / "blanks.csv", rows), "c.onnx")
    assert res.returncode == 0, res.stderr
    c = json.loads(res.stdout)
    assert c["gates"]["passed"] == c["gates"]["points"] >= a["gates"]["points"] - 1
    assert abs(c["residual_stats"]["rmse"] / a["residual_stats"]["rmse"] - 1) < 0.05


def test_train_refuses_text_where_it_reads_numbers(tmp_path):
    rows = rig_series(2)
    rows[77][2] = "47,3"
    res = train(tmp_path, write(tmp_path / "bad.csv", rows, ";"), "m.onnx")
    refused(res, EX_DATAERR, "bad.csv", "line 78", "column 'temp_c'", "'47,3'", "decimal comma")
    assert not (tmp_path / "m.onnx").exists()


def test_gap_diagnose_reads_the_same_files(tmp_path):
    rows = [[*r[:1], "pump_speed_rpm", "pump_disp_cc", *r[1:4], "operator"] for r in rig_series()[:1]]
    rows += [[r[0], "1450", "4.6", *r[1:4], "anna"] for r in rig_series()[1:]]
    for i in range(5, len(rows), 97):
        rows[i][3] = ""
    p = write(tmp_path / "g.csv", rows, ";", "\r\n", bom=True)
    args = ("--config", str(RIG / "cmcan.yaml"), "--drive", str(RIG / "drive.yaml"), "--quantity", "flow_lpm")
    res = run_cli("gap", "diagnose", str(p), *args, "--out", str(tmp_path / "g"), "--no-plots", "--json")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "g" / "report.json").exists()
    rows[200][5] = "6.6 l/min"
    p = write(tmp_path / "bad.csv", rows, ";")
    res = run_cli("gap", "diagnose", str(p), *args, "--out", str(tmp_path / "b"), "--no-plots")
    refused(res, EX_DATAERR, "bad.csv", "line 201", "column 'flow_lpm'", "'6.6 l/min' is not a number")


def test_a_time_that_does_not_increase_is_named_by_its_line_after_left_out_rows(tmp_path):
    from cmcan.model.features import DataError, series_from_csv

    rows = small()
    rows[2][1] = ""  # line 3 left out
    rows[5][0] = rows[4][0]  # line 6 repeats line 5's time
    with pytest.raises(DataError, match=r"b.csv: time_s must increase from row to row \(line 6 does not\)"):
        series_from_csv(write(tmp_path / "b.csv", rows), "flow_lpm", {"pump_speed_rpm": 1450.0, "pump_disp_cc": 4.6})


def test_a_blank_line_does_not_shift_the_line_named(tmp_path):
    """numpy's fast read skips blank lines: a file with one is numbered by its lines all the same."""
    from cmcan.model.features import DataError, series_from_csv

    rows = small()
    rows[5][0] = rows[4][0]  # the 5th data row repeats the 4th's time: line 7 once a blank line is in
    text = ",".join(rows[0]) + "\n\n" + "\n".join(",".join(r) for r in rows[1:]) + "\n"
    (tmp_path / "b.csv").write_text(text)
    with pytest.raises(DataError, match=r"b.csv: time_s must increase from row to row \(line 7 does not\)"):
        series_from_csv(tmp_path / "b.csv", "flow_lpm", {"pump_speed_rpm": 1450.0, "pump_disp_cc": 4.6})
    plain = read_run_csv(write(tmp_path / "p.csv", small()), REQUIRED)
    assert list(plain.lines) == [2, 3, 4, 5, 6]


@settings(max_examples=60, deadline=None)
@given(
    values=st.lists(
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True),
            st.floats(-1e6, 1e6),
            st.integers(-(10**9), 10**9).map(lambda i: i / 10**4 + 0.00005),  # halfway at the 4th decimal
            st.sampled_from([0.0, -0.0, 5e-5, -5e-5, 1e-300, 2.0**52, -(2.0**53) + 1]),
        ),
        min_size=0,
        max_size=120,
    ),
    native=st.booleans(),
)
def test_run_csv_rows_are_numpys_savetxt_to_the_byte(tmp_path_factory, values, native):
    """The run CSV's rows (by the C formatter where built) are what ``np.savetxt`` with ``%.<d>f``
    writes, whatever the values: ties at the last decimal, -0, NaN, infinities, beyond 2^52."""
    import io
    from unittest import mock

    from cmcan.io import native as native_mod
    from cmcan.io import runcsv

    x = np.array(values, dtype=np.float64)
    cols = {"time_s": x, "operating_h": x[::-1].copy(), "true_failed": np.round(x), "dp_bar": x * 3}
    path = tmp_path_factory.mktemp("rc") / "r.csv"
    with mock.patch.object(native_mod, "LIB", native_mod.LIB if native else None):
        write_run_csv(path, cols)
    buf = io.StringIO()
    fmt = [f"%.{runcsv._DECIMALS.get(k, runcsv._DEFAULT_DECIMALS)}f" for k in cols]
    np.savetxt(buf, np.column_stack(list(cols.values())) if len(x) else np.empty((0, 4)), fmt=fmt, delimiter=",")
    assert path.read_text() == ",".join(cols) + "\n" + buf.getvalue()
