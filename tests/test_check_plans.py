"""``cmcan check`` on the baseline and prognosis sections: what the baseline will learn, when it ends
and where its guard's allowance comes from, what end of life means; and the two sections' nonsense
refused with exit 78 naming the field: bins where no tick is ever evaluated, an end of life the
warning would come after."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from cmcan.cli import main
from cmcan.cli.errors import EX_CONFIG
from tests.conftest import ROOT


def config(tmp_path: Path, **sections) -> str:
    raw = yaml.safe_load((ROOT / "config" / "cmcan.yaml").read_text())
    raw["dbc"] = str(ROOT / "dbc" / "cmcan.dbc")
    raw["state"]["directory"] = str(tmp_path / "state")
    raw.update(sections)
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(raw))
    return str(p)


def check(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["check", *args])
    got = capsys.readouterr()
    return code, got.out, got.err


BASELINE = {"enabled": True, "edges": {"dp_bar": [50, 200, 400]}, "min_hours": 3.0}
PROGNOSIS = {"enabled": True, "end_of_life": {"kind": "ratio_pct", "value": 92.0}, "imminent_h": 30.0}


def test_check_prints_the_learning_plan_and_the_end_of_life(tmp_path, capsys):
    cfg = config(tmp_path, baseline=BASELINE, prognosis=PROGNOSIS)
    code, out, err = check(capsys, "--config", cfg)
    assert code == 0, err
    lines = [ln.strip() for ln in out.splitlines()]
    learn = next(ln for ln in lines if ln.startswith("baseline  learns"))
    assert "3x2x2 bins" in learn and "dp_bar 50..400" in learn and "3 operating hours" in learn
    assert "judged meanwhile at 95 / 105 %" in learn
    guard = next(ln for ln in lines if ln.startswith("baseline  suspect beyond"))
    assert "2 % of the nominal flow" in guard  # the shipped model records no unit spread
    eol = next(ln for ln in lines if ln.startswith("prognosis end of life"))
    assert "the CM ratio at 92 %" in eol and "110 %" in eol and "within 30 h" in eol
    code, out, _ = check(capsys, "--config", cfg, "--json")
    doc = json.loads(out)
    assert doc["baseline"]["bins"] == "3x2x2" and doc["baseline"]["edges"]["dp_bar"] == [50.0, 200.0, 400.0]
    assert doc["baseline"]["bins_needed"] >= 1 and doc["baseline"]["suspect_lpm"] > 0
    assert doc["prognosis"]["imminent_h"] == 30.0


def test_check_says_when_either_is_off(tmp_path, capsys):
    code, out, _ = check(capsys, "--config", config(tmp_path))
    assert code == 0
    assert "baseline  off" in out and "prognosis off" in out
    code, out, _ = check(capsys, "--config", config(tmp_path), "--json")
    doc = json.loads(out)
    assert doc["baseline"] is None and doc["prognosis"] is None


@pytest.mark.parametrize(
    ("sections", "field"),
    [
        # bins wholly above the model's pressure envelope: no tick there is evaluated
        ({"baseline": {"enabled": True, "edges": {"dp_bar": [700, 800, 900]}}}, "baseline.edges.dp_bar"),
        ({"baseline": {"enabled": True, "edges": {"temp_c": [-40, -30]}}}, "baseline.edges.temp_c"),
        # an end of life at 99 %: the 98 % warning would come after it
        (
            {"prognosis": {"enabled": True, "end_of_life": {"kind": "ratio_pct", "value": 99.0}}},
            "prognosis.end_of_life.value",
        ),
        (
            {"prognosis": {"enabled": True, "end_of_life": {"kind": "ratio_pct", "value": 98.0}}},
            "prognosis.end_of_life.value",
        ),
    ],
)
def test_nonsense_sections_are_refused_naming_the_field(tmp_path, capsys, sections, field):
    code, _, err = check(capsys, "--config", config(tmp_path, **sections))
    assert code == EX_CONFIG
    assert field in err, err
