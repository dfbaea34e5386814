"""Layers only point down: each module imports only from its own layer or the ones below.

Checked on the source with ``ast`` (imports inside functions included), so a shortcut that crosses a
layer fails here rather than in review.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "cmcan"

# Lowest first. A module's layer is that of its longest listed prefix.
LAYERS: list[tuple[str, ...]] = [
    (
        "cmcan",
        "cmcan.roles",
        "cmcan.frame",
        "cmcan.errors",
        "cmcan.oil",
        "cmcan.schema",
        "cmcan.yamlsafe",
        "cmcan.codec",
        "cmcan.checksums",
        "cmcan.j1939",
    ),
    ("cmcan.monitor",),  # the pure core
    (
        "cmcan.model",
        "cmcan.sim",
        "cmcan.io",
        "cmcan.dbc",
        "cmcan.statefile",
        "cmcan.sdnotify",
        "cmcan.ratelog",
        "cmcan.plots",
        # the uplink's settings, records and outbox file, used by the configuration and the daemon
        "cmcan.uplink.config",
        "cmcan.uplink.records",
        "cmcan.uplink.outbox",
        "cmcan.uplink.setup",
    ),
    ("cmcan.gap", "cmcan.config"),
    ("cmcan.assemble", "cmcan.preflight"),
    (
        "cmcan.daemon",
        "cmcan.replay",
        "cmcan.columnar",
        "cmcan.demo",
        "cmcan.rebuild_default",
        "cmcan.uplink",
        "cmcan.fleet",
    ),
    ("cmcan.cli", "cmcan.__main__"),
]


def module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def layer_of(name: str) -> int:
    best, best_len = None, -1
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (name == p or name.startswith(p + ".")) and len(p) > best_len:
                best, best_len = i, len(p)
    assert best is not None, f"{name} is in no layer: add it to LAYERS"
    return best


def imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append(node.module)
            out += [f"{node.module}.{a.name}" for a in node.names]
    return [n for n in out if n == "cmcan" or n.startswith("cmcan.")]


MODULES = sorted(PKG.rglob("*.py"))


def _existing(name: str) -> str:
    """``from cmcan.x import y`` names module ``cmcan.x.y`` only when that module exists."""
    parts = name.split(".")
    while parts:
        cand = PKG.parent.joinpath(*parts)
        if cand.with_suffix(".py").exists() or (cand / "__init__.py").exists():
            return ".".join(parts)
        parts.pop()
    return name


@pytest.mark.parametrize("path", MODULES, ids=lambda p: module_name(p))
def test_imports_point_down(path):
    me = module_name(path)
    mine = layer_of(me)
    for imported in imports(path):
        target = _existing(imported)
        assert layer_of(target) <= mine, f"{me} (layer {mine}) imports {target} (layer {layer_of(target)})"


@pytest.mark.parametrize("path", sorted((PKG / "monitor").glob("*.py")), ids=lambda p: p.stem)
def test_the_core_imports_nothing_of_configuration_cli_io_model_or_sim(path):
    forbidden = ("cmcan.config", "cmcan.cli", "cmcan.io", "cmcan.model", "cmcan.sim", "cmcan.assemble")
    for imported in imports(path):
        assert not imported.startswith(forbidden), f"{path.name} imports {imported}"


@pytest.mark.parametrize("path", [p for p in MODULES if "cli" not in p.relative_to(PKG).parts[:1]], ids=module_name)
def test_nothing_below_the_cli_imports_the_cli(path):
    if module_name(path) == "cmcan.__main__":
        return
    for imported in imports(path):
        assert not imported.startswith("cmcan.cli"), f"{module_name(path)} imports {imported}"


def test_no_raw_configuration_dict_outside_the_configuration_module():
    for path in MODULES:
        if path.name == "config.py":
            continue
        text = path.read_text(encoding="utf-8")
        assert "cfg.raw" not in text and "config.raw" not in text, path
