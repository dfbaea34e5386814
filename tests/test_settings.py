"""Settings declared once: the YAML section, the values the core takes and the configuration
reference are derived from one declaration (:func:`cmcan.schema.setting`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from cmcan import config as cfgmod
from cmcan.monitor.prognosis import PrognosisParams
from cmcan.schema import Num, SchemaError, Str, load_yaml, reference, section, setting, settings_of, values_of

DOC = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


@dataclasses.dataclass(frozen=True)
class Toy:
    given: float = 1.0  # not a setting: given at assembly
    span_h: float = setting(Num(0, 10, "h", default=2.0), "a span")
    kind: str = setting(Str(default="a", choices=("a", "b")), "a kind", "nested.kind")


def test_a_declaration_gives_the_section_its_values_and_its_reference():
    spec = section(Toy, {"enabled": Num(default=0)})
    assert set(spec.fields) == {"enabled", "span_h", "nested"}
    checked = spec.check({"nested": {"kind": "b"}}, "toy.yaml", "toy")
    assert values_of(Toy, checked) == {"span_h": 2.0, "kind": "b"}
    assert Toy(**values_of(Toy, checked)) == Toy(1.0, 2.0, "b")
    with pytest.raises(SchemaError, match=r"toy\.yaml: toy\.span_h: expected a number in \[0, 10\] h, got 11"):
        spec.check({"span_h": 11}, "toy.yaml", "toy")
    with pytest.raises(SchemaError, match=r"toy\.nested\.kinds: unknown field \(did you mean 'kind'\?\)"):
        spec.check({"nested": {"kinds": "b"}}, "toy.yaml", "toy")
    rows = reference(Toy, "toy")
    assert rows[2:] == [
        "| `toy.span_h` | a number in [0, 10] h | 2 | a span |",
        "| `toy.nested.kind` | one of 'a', 'b' | `a` | a kind |",
    ]


def test_the_prognosis_section_is_its_parameters():
    """Every setting of the YAML section is a field the core takes, with the declaration's default,
    and a value given in the YAML reaches the core unchanged."""
    declared = {path for _, path, _ in settings_of(PrognosisParams)}
    assert declared == {
        "end_of_life.kind",
        "end_of_life.value",
        "end_of_life.high_pct",
        "imminent_h",
        "ref_dp_bar",
        "ref_temp_c",
        "estimate_every_h",
        "max_gap_h",
    }
    for f in dataclasses.fields(PrognosisParams):
        if "setting" in f.metadata:
            assert f.default == f.metadata["setting"].spec.default, f.name
    path = cfgmod.default_config_path()
    raw = load_yaml(path)
    section_ = {"enabled": True, "imminent_h": 30.0, "ref_dp_bar": 400.0, "end_of_life": {"kind": "leak_lpm"}}
    cfg = cfgmod.from_dict({**raw, "prognosis": section_}, str(path), path.parent)
    p = cfg.prognosis.params
    assert (p.imminent_h, p.dp_ref_bar, p.eol_kind, p.eol_value) == (30.0, 400.0, "leak_lpm", 90.0)
    assert (p.low_pct, p.high_pct) == (cfg.thresholds.low_pct, cfg.thresholds.high_pct)


def test_the_configuration_reference_is_the_declarations():
    text = DOC.read_text(encoding="utf-8")
    block = text.split("<!-- settings:begin -->\n", 1)[1].split("<!-- settings:end -->", 1)[0]
    want = "\n".join(cfgmod.reference_rows()) + "\n"
    assert block == want, "docs/configuration.md is out of date; its table should read:\n" + want


def test_the_baseline_section_reaches_its_parameters():
    """A baseline setting given in the YAML reaches the core's parameters without a copy by hand."""
    from cmcan.assemble import baseline_params, load_model_for

    path = cfgmod.default_config_path()
    section_ = {"enabled": True, "min_points": 7, "min_hours": 0.5, "edges": {"dp_bar": [20, 300, 560]}}
    cfg = cfgmod.from_dict({**load_yaml(path), "baseline": section_}, str(path), path.parent)
    p = baseline_params(cfg, load_model_for(cfg))
    assert p is not None and (p.min_points, p.min_hours, p.coverage_pct) == (7, 0.5, 20.0)
    assert p.edges[1] == (20.0, 300.0, 560.0)
    with pytest.raises(SchemaError, match=r"baseline\.edges\.dp_bar: bin edges must rise"):
        cfgmod.from_dict({**load_yaml(path), "baseline": {"edges": {"dp_bar": [300, 20]}}}, str(path), path.parent)
