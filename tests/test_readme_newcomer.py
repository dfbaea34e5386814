"""What the README tells a newcomer holds: where the installed DBC is and how a copied configuration
points at it, where the demo writes on a first and a second run, what "the paper" is."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from cmcan.cli.demo import DEFAULT_OUT
from tests.conftest import ROOT, run_cli

README = (ROOT / "README.md").read_text()


def test_the_readme_says_where_the_installed_dbc_is_and_how_a_copy_points_at_it(tmp_path):
    step = README.split("3. Configure:")[1].split("4. Service:")[0]
    one_liner = re.search(r"python -c '([^']+)'", step.replace("\n", " "))
    assert one_liner, step
    code = re.sub(r"\s+", " ", one_liner.group(1))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    printed = res.stdout.strip()
    assert printed.endswith("cmcan.dbc") and Path(printed).read_text() == (ROOT / "dbc" / "cmcan.dbc").read_text()
    # copy both to /etc/cmcan as the README says (here a temporary folder) and set dbc: cmcan.can.dbc
    assert "set `dbc: cmcan.dbc`" in step and "a relative path is read from the configuration file's folder" in step
    etc = tmp_path / "etc" / "cmcan"
    etc.mkdir(parents=True)
    conf = (ROOT / "config" / "cmcan.yaml").read_text()
    assert re.search(r"^dbc: \S+", conf, re.M)
    (etc / "cmcan.yaml").write_text(re.sub(r"^dbc: \S+", "dbc: cmcan.dbc", conf, flags=re.M))
    (etc / "cmcan.dbc").write_text((ROOT / "dbc" / "cmcan.dbc").read_text())
    res = run_cli("check", "--config", str(etc / "cmcan.yaml"), cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert re.search(rf"^\s+dbc\s+{re.escape(str(etc / 'cmcan.dbc'))}$", res.stdout, re.M), res.stdout


def test_the_readme_says_where_the_demo_writes_the_first_time_and_the_next():
    quick = README.split("## Quick start")[1].split("## Background")[0]
    assert re.search(r"^cmcan demo\s+#", quick, re.M)  # the one command, without options
    assert f"`{DEFAULT_OUT}/demo.png`" in quick and f"`{DEFAULT_OUT}-2/`" in quick and "--force" in quick


def test_the_readme_says_what_the_paper_is():
    background = README.split("## Background")[1].split("\n## ")[0]
    assert '"The paper"' in background and "gray-box" in background
    # every figure the docs give is cmcan's own; a reference, once known, belongs here
    assert "not recorded in this repository" in background and "not the paper's" in background
