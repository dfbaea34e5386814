"""`cmcan fleet query` is read-only over the data set's views: every statement that would write a file,
read one outside the data set or reach for the network is refused (exit 77) and leaves nothing behind;
times print in full; the report works on a data set whose every log was quarantined."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytest.importorskip("pyarrow")
pytest.importorskip("duckdb")

from cmcan.cli import main
from cmcan.fleet import dataset as ds
from cmcan.fleet.task import LogJob, Options, process_log
from tests.chromium import chromium_path, open_page
from tests.conftest import ROOT, run_cli
from tests.helpers import sim_frames, write_log

SECRET = "s3cr3t-token-4711"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    d = tmp_path_factory.mktemp("q")
    _run, frames = sim_frames("single_set_healthy", duration_h=0.03)
    log = write_log(d / "m1_a.log", frames)
    root = ds.open_dataset(d / "ds", create=True)
    assert process_log(LogJob("m1", str(log)), Options(dataset=str(root)))["status"] == "done"
    (d / "secret.txt").write_text(SECRET + "\n")
    return root, d


def cli(capsys, *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    out = capsys.readouterr()
    return code, out.out, out.err


ATTACKS = [
    "COPY logs TO '{d}/out.csv'",
    "COPY (SELECT * FROM timeline) TO '{d}/out.parquet' (FORMAT parquet)",
    "ATTACH '{d}/evil.db' AS evil",
    "SELECT * FROM read_text('{d}/secret.txt')",
    "SELECT * FROM read_csv('{d}/secret.txt')",
    "SELECT * FROM glob('{d}/*')",
    "INSTALL httpfs",
    "LOAD httpfs",
    "SELECT * FROM read_parquet('https://example.com/x.parquet')",
    "SET enable_external_access = true",
    "SET temp_directory = '{d}/spill'",
    "EXPORT DATABASE '{d}/export'",
    "CREATE TABLE t AS SELECT * FROM logs",
    "SELECT 1; COPY logs TO '{d}/out2.csv'",
    "PRAGMA database_list",
    "CALL pragma_version()",
]


@pytest.mark.parametrize("attack", ATTACKS)
def test_a_statement_reaching_outside_the_views_is_refused(dataset, capsys, attack):
    root, d = dataset
    before = sorted(p.name for p in d.rglob("*"))
    code, out, err = cli(capsys, "fleet", "query", str(root), attack.format(d=d))
    assert code == 77, (out, err)
    assert "query refused" in err and SECRET not in out + err
    assert sorted(p.name for p in d.rglob("*")) == before  # nothing written anywhere near


def test_a_file_named_as_a_table_is_no_table(dataset, capsys):
    root, d = dataset
    code, out, err = cli(capsys, "fleet", "query", str(root), f"SELECT * FROM '{d}/secret.txt'")
    assert code == 65 and "does not exist" in err and SECRET not in out + err


def test_refusals_through_the_real_command_line(dataset, tmp_path):
    root, d = dataset
    r = run_cli("fleet", "query", str(root), f"COPY logs TO '{tmp_path}/x.csv'", cwd=tmp_path)
    assert r.returncode == 77 and "statement type COPY" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("fleet", "query", str(root), f"SELECT * FROM read_text('{d}/secret.txt')", cwd=tmp_path)
    assert r.returncode == 77 and "disabled by configuration" in r.stderr and SECRET not in r.stdout + r.stderr
    assert list(tmp_path.iterdir()) == []


def test_what_the_views_allow_still_runs(dataset, capsys):
    root, _d = dataset
    code, out, err = cli(
        capsys,
        *("fleet", "query", str(root)),
        "WITH w AS (SELECT machine, sum(ticks) AS n FROM timeline GROUP BY 1) "
        "SELECT w.machine, w.n, l.evaluated, m.fit FROM w JOIN logs l USING (machine) JOIN machines m USING (machine)",
    )
    assert code == 0, err
    assert out.splitlines()[2].split()[0] == "m1"
    code, out, _ = cli(capsys, "fleet", "query", str(root), "EXPLAIN SELECT count(*) FROM logs")
    assert code == 0 and "physical_plan" in out
    code, _, err = cli(capsys, "fleet", "query", str(root), "SELECT nope FROM logs")
    assert code == 65 and "query failed" in err


def test_times_print_in_full(dataset, capsys):
    root, _d = dataset
    sql = "SELECT min(time_s) AS t, max(time_s) - min(time_s) AS span_s, first(first_time_s) AS f FROM timeline, logs"
    code, out, _ = cli(capsys, "fleet", "query", str(root), sql)
    assert code == 0
    row = out.splitlines()[2].split()
    assert re.fullmatch(r"17672256\d\d\.\d{6}", row[0]) and re.fullmatch(r"17672256\d\d\.\d{6}", row[2])
    assert "e+" not in out
    code, out, _ = cli(
        capsys, "fleet", "query", str(root), "SELECT time_s FROM timeline ORDER BY 1 LIMIT 2", "--format", "csv"
    )
    assert [float(x) for x in out.splitlines()[1:]] == [1767225600.0, 1767225601.0]


def test_the_report_of_a_data_set_whose_every_log_was_quarantined(tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    bad = tmp_path / "m9_bad.log"
    bad.write_text("(1767225600.000000) can0 7FF#00\n" * 20)  # no input message of the configuration
    assert process_log(LogJob("m9", str(bad)), Options(dataset=str(root)))["status"] == "quarantined"
    out = tmp_path / "r.html"
    r = run_cli("fleet", "report", str(root), "--out", str(out))
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    assert "Quarantine (1)" in text and "m9_bad.log" in text and "wrong DBC or configuration" in text
    r = run_cli("fleet", "query", str(root), "SELECT count(*), sum(count_frames_total) FROM logs", "--format", "csv")
    assert r.returncode == 0 and r.stdout.splitlines() == ["count_star(),sum(count_frames_total)", "0,"]
    if chromium_path() is None:
        pytest.skip("needs Debian's chromium package (.ci/run installs it) for the page itself")
    shot = ROOT / "tests" / "artifacts" / "fleet-report-all-quarantined.png"
    page = open_page(
        out.as_uri(),
        shot,
        {
            "quarantine": "document.getElementById('quarantine').innerText",
            "rows": "Array.from(document.querySelectorAll('table')).pop().innerText",
            "cards": "Array.from(document.querySelectorAll('.card')).map(c => c.innerText.replace('\\n', ' '))",
        },
        height=900,
    )
    assert page.errors == []
    assert page.values["quarantine"] == "Quarantine (1)" and "m9_bad.log" in page.values["rows"]
    assert "0 machines" in page.values["cards"] and "1 quarantined" in page.values["cards"]


def test_an_empty_data_set_reports_and_queries(tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    r = run_cli("fleet", "report", str(root), "--out", str(tmp_path / "r.html"))
    assert r.returncode == 0 and "No log failed." in Path(tmp_path / "r.html").read_text()
