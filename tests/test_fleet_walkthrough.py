"""docs/fleet.md's walk from the type model to the service plan runs as written: its shell block, in
an empty folder, with ``cmcan`` the command line of this checkout; then what it left is what the page
says: the leaking unit left out of the type model, every healthy machine out of learning within 50
operating hours on the default learning settings, every machine in the plan, the report written."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys

import pytest

from tests.conftest import ROOT

pytest.importorskip("distributed")
pytest.importorskip("duckdb")
pytestmark = pytest.mark.slow


def walkthrough() -> str:
    text = (ROOT / "docs" / "fleet.md").read_text(encoding="utf-8")
    block = text.split("<!-- walkthrough:begin -->", 1)[1].split("<!-- walkthrough:end -->", 1)[0]
    (body,) = re.findall(r"```sh\n(.*?)```", block, flags=re.S)
    return body


def test_the_docs_walk_from_the_type_model_to_the_plan_runs_as_written(tmp_path):
    script = f'set -euo pipefail\ncmcan() {{ "{sys.executable}" -m cmcan "$@"; }}\n' + walkthrough()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run(["bash", "-c", script], cwd=tmp_path, capture_output=True, text=True, env=env, timeout=1500)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    truth = json.loads((tmp_path / "fleet" / "truth.json").read_text())
    leaking = [m["machine"] for m in truth["machines"] if m["unit"]["arriving_leak_lpm"] > 0]
    assert len(leaking) == 1
    assert "left out of the type" in r.stdout and leaking[0] in r.stdout  # fleet train named it
    assert "baseline  learns" in r.stdout and "prognosis end of life" in r.stdout  # cmcan check
    plan = subprocess.run(
        [sys.executable, "-m", "cmcan", "fleet", "plan", "fleet-plan-ds", "--json"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    # the default learning settings end on a time-lapse logger's logs: every healthy machine monitors
    # on its own baseline within 50 operating hours (the hour of its first monitoring row)
    sql = (
        "SELECT t.machine, min(ml.offset_h + t.log_time_h) FROM timeline t JOIN machine_logs ml "
        "USING (machine, log_hash) WHERE t.baseline_state = 2 GROUP BY 1 ORDER BY 1"
    )
    q = subprocess.run(
        [sys.executable, "-m", "cmcan", "fleet", "query", "fleet-plan-ds", sql, "--format", "csv"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    monitoring_from_h = {m: float(h) for m, h in (line.split(",") for line in q.stdout.splitlines()[1:])}
    print("monitoring from (operating h):", monitoring_from_h)
    healthy = [m["machine"] for m in truth["machines"] if not m["degrading"] and m["machine"] not in leaking]
    assert healthy and all(monitoring_from_h.get(m, math.inf) <= 50.0 for m in healthy), monitoring_from_h
    rows = {m["machine"]: m for m in json.loads(plan.stdout)["machines"]}
    assert set(rows) == {m["machine"] for m in truth["machines"]}
    leak = rows[leaking[0]]
    assert "baseline_suspect" in leak["flags"] or leak["warning_level"] == "low", leak
    assert (tmp_path / "fleet-report.html").stat().st_size > 10_000
