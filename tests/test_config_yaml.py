"""Every YAML file cmcan reads goes through one bounded loader (``cmcan.yamlsafe``): an alias bomb,
deep nesting, a recursive alias, a huge or endless file are refused with one line naming the file,
never exit 70, a MemoryError or a RecursionError; and the bound is exact, not a guess."""

from __future__ import annotations

import os
import signal
import tracemalloc

import pytest
import yaml
from hypothesis import event, given, settings
from hypothesis import strategies as st

from cmcan import yamlsafe
from cmcan.cli.errors import EX_CONFIG, EX_DATAERR
from cmcan.config import load as load_config
from cmcan.errors import Kind
from cmcan.schema import SchemaError, load_yaml
from tests.conftest import ROOT, run_cli
from tests.daemon_proc import DaemonProc, virtual_config
from tests.test_bad_inputs import refused

RIG_CYCLES = str(ROOT / "examples" / "zema-rig" / "data" / "cycles.csv")
RIG_POINTS = str(ROOT / "examples" / "zema-rig" / "points.yaml")
GAP = ("--out", "{d}/g", "--no-plots")


def bomb(levels: int = 9, width: int = 10) -> str:
    """The billion laughs: ``width ** levels`` scalars once expanded, in under 1 kB."""
    lines = ["a0: &a0 [" + ", ".join(["lol"] * width) + "]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]" for i in range(1, levels)]
    return "\n".join(lines) + "\n"


def nested(depth: int) -> str:
    return "a: " + "[" * depth + "1" + "]" * depth + "\n"


def expanded_nodes(value, memo=None) -> int:
    """Nodes of a constructed value walked as a validator walks it (aliases expanded)."""
    if isinstance(value, dict):
        return 1 + sum(expanded_nodes(k) + expanded_nodes(v) for k, v in value.items())
    if isinstance(value, list):
        return 1 + sum(expanded_nodes(v) for v in value)
    return 1


def test_an_alias_bomb_is_refused_while_its_text_is_read(tmp_path):
    """Refused at the line where the expanded size passes the budget: the value is never built, so
    memory stays at what the text costs (the expanded value would be 10^9 nodes)."""
    p = tmp_path / "bomb.yaml"
    p.write_text(bomb())
    tracemalloc.start()
    try:
        with pytest.raises(SchemaError) as err:
            load_yaml(p)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    msg = str(err.value)
    assert msg.startswith(f"{p}: line 5, ") and f"more than {yamlsafe.MAX_NODES} nodes" in msg, msg
    assert err.value.kind == Kind.CONFIG
    assert peak < 2 << 20, peak  # a few hundred kB: the parser's events, never the expansion
    # a_k expands to 11...1 (k + 2 ones) nodes: a4 (111 111) is the first over the budget, on line 5
    with pytest.raises(yamlsafe.YamlError, match="alias bomb"):
        yamlsafe.loads(bomb(levels=5), "b.yaml")
    assert yamlsafe.measure(bomb(levels=4), "b.yaml")[0] == 1 + 4 + sum(int("1" * (k + 2)) for k in range(4))


def test_aliases_of_long_strings_count_by_their_characters():
    text = "s: &s " + "x" * 200_000 + "\nl: [" + ", ".join(["*s"] * 30) + "]\n"
    with pytest.raises(yamlsafe.YamlError, match=f"more than {yamlsafe.MAX_CHARS} characters"):
        yamlsafe.loads(text, "long.yaml")


def test_merge_keys_are_aliases_and_count_as_such():
    ok = "base: &b {x: 1, y: 2}\nm: {<<: *b, z: 3}\n"
    assert yamlsafe.loads(ok, "m.yaml") == {"base": {"x": 1, "y": 2}, "m": {"x": 1, "y": 2, "z": 3}}
    lines = ["m0: &m0 {k: [" + ", ".join(["v"] * 10) + "]}"]
    lines += [f"m{i}: &m{i} {{<<: [" + ", ".join([f"*m{i - 1}"] * 10) + f"], k{i}: 1}}" for i in range(1, 9)]
    with pytest.raises(yamlsafe.YamlError, match="alias bomb"):
        yamlsafe.loads("\n".join(lines) + "\n", "merge.yaml")


@pytest.mark.parametrize("depth", [yamlsafe.MAX_DEPTH, 10_000, 300_000])
def test_deep_nesting_is_refused_not_a_recursion_error(depth):
    with pytest.raises(yamlsafe.YamlError, match="nest"):
        yamlsafe.loads(nested(depth), "deep.yaml")
    assert yamlsafe.loads(nested(yamlsafe.MAX_DEPTH - 2), "ok.yaml")["a"] is not None


def test_the_pure_python_parser_is_bounded_too(monkeypatch):
    """Where PyYAML was built without libyaml the same bounds hold (its parser is not recursive)."""
    monkeypatch.setattr(yamlsafe, "_Loader", yaml.SafeLoader)
    for text, match in ((nested(5000), "nested more than"), (bomb(), "alias bomb"), ("&a [1, *a]", "its own node")):
        with pytest.raises(yamlsafe.YamlError, match=match):
            yamlsafe.measure(text, "p.yaml")


def test_a_recursive_alias_is_refused():
    for text in ("&a [1, *a]", "a: &x {b: *x}", "a: &x [1]\nb: &x [*x]"):
        with pytest.raises(yamlsafe.YamlError, match="inside its own node"):
            yamlsafe.loads(text, "r.yaml")


@pytest.mark.parametrize(
    "text, match",
    [
        ("a: " + "9" * 5000, "line 1, column 4: cannot read '9999"),
        ("a: 2001-13-45", "cannot read '2001-13-45' as a timestamp"),
        ("a: !!timestamp x", "cannot read 'x' as a timestamp"),
        ("a: !!float x", "as a float"),
        ("a: !!python/object:os.system x", "invalid YAML"),
        ("a: *nothing", "names no anchor"),
        ("a: 1\n---\nb: 2\n", "another document"),
    ],
)
def test_values_pyyaml_cannot_build_are_errors_with_their_line(text, match):
    with pytest.raises(yamlsafe.YamlError, match=match):
        yamlsafe.loads(text, "v.yaml")


def test_files_that_are_not_regular_files_or_too_large_are_refused_without_reading_them(tmp_path):
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)  # nobody writes to it: a blocking read would never return
    with pytest.raises(yamlsafe.YamlError, match="not a regular file"):
        yamlsafe.load_file(fifo)
    with pytest.raises(yamlsafe.YamlError, match="not a regular file"):
        yamlsafe.load_file("/dev/zero")  # endless: a plain read would fill memory
    big = tmp_path / "big.yaml"
    with open(big, "wb") as f:
        f.truncate(yamlsafe.MAX_BYTES + 1)  # sparse: costs nothing to make
    with pytest.raises(yamlsafe.YamlError, match="more than any YAML file cmcan reads"):
        yamlsafe.load_file(big)
    with pytest.raises(yamlsafe.YamlError) as err:
        yamlsafe.load_file(tmp_path / "none.yaml")
    assert err.value.kind == Kind.NO_INPUT


# A YAML document with shared parts: safe_dump writes anchors and aliases for them.
_leaf = st.one_of(st.integers(-5, 5), st.text("ab", max_size=3), st.booleans())
_tree = st.recursive(
    _leaf,
    lambda kids: st.one_of(st.lists(kids, max_size=4), st.dictionaries(st.text("kxy", max_size=2), kids, max_size=3)),
)


@settings(max_examples=150, deadline=None)
@given(st.lists(_tree, min_size=1, max_size=4), st.lists(st.integers(0, 3), max_size=6))
def test_the_measured_size_is_the_size_of_the_value_walked(parts, picks):
    """The budget is exact: the node count from the events equals the count of a walk of the value
    (aliases expanded), and the depth equals the value's nesting."""
    doc = {"parts": parts, "again": [parts[i % len(parts)] for i in picks]}  # shared objects: aliases
    text = yaml.safe_dump(doc)
    event("aliases" if "*id" in text else "no aliases")
    nodes, _chars, _depth = yamlsafe.measure(text, "h.yaml")
    value = yamlsafe.loads(text, "h.yaml")
    assert value == doc
    assert nodes == expanded_nodes(value)


# -- every reader of YAML, through the command line -----------------------------------------------------


@pytest.fixture(scope="module")
def hostile(tmp_path_factory):
    d = tmp_path_factory.mktemp("hostile")
    (d / "bomb.yaml").write_text(bomb())
    (d / "deep.yaml").write_text(nested(100_000))
    return d


@pytest.mark.parametrize(
    "name, why, args, code",
    [
        ("bomb.yaml", "alias bomb", ("check", "--config", "{f}"), EX_CONFIG),
        ("deep.yaml", "nest", ("check", "--config", "{f}"), EX_CONFIG),
        ("bomb.yaml", "alias bomb", ("simulate", "{f}", "--out", "{d}/sim.csv"), EX_DATAERR),
        ("bomb.yaml", "alias bomb", ("uplink", "--status", "--config", "{f}"), EX_CONFIG),
        ("bomb.yaml", "alias bomb", ("gap", "diagnose", RIG_CYCLES, "--points", "{f}", *GAP), None),
        ("deep.yaml", "nest", ("gap", "diagnose", RIG_CYCLES, "--points", RIG_POINTS, "--drive", "{f}", *GAP), None),
    ],
    ids=["config", "config-deep", "scenario", "uplink", "points-spec", "drive"],
)
def test_every_yaml_reader_refuses_them_with_one_line(hostile, tmp_path, name, why, args, code):
    f = hostile / name
    r = run_cli(*[a.format(f=f, d=tmp_path) for a in args])
    assert r.returncode in ((code,) if code else (EX_CONFIG, EX_DATAERR)), r.stderr
    refused(r, r.returncode, name, why)
    assert list(tmp_path.iterdir()) == []


def test_config_load_refuses_them_as_configuration_errors(hostile):
    for name in ("bomb.yaml", "deep.yaml"):
        with pytest.raises(SchemaError) as err:
            load_config(hostile / name)
        assert err.value.kind == Kind.CONFIG and str(err.value).startswith(f"{hostile / name}: ")


def test_a_reload_onto_a_bomb_or_deep_nesting_keeps_the_daemon_running(tmp_path):
    """SIGHUP with an alias bomb, then deep nesting in the file: each reload fails with one line naming
    the file; the daemon runs on with its configuration and stops on SIGTERM (no traceback)."""
    cfg = virtual_config(tmp_path)
    good = cfg.read_text()
    d = DaemonProc(tmp_path, cfg)
    try:
        for text, why in ((good + bomb().replace("a0:", "zz0:"), "alias bomb"), (good + nested(50_000), "nest")):
            cfg.write_text(text)
            n = d.stderr().count("reload failed")
            d.signal(signal.SIGHUP)
            assert d.wait_for(lambda n=n: d.stderr().count("reload failed") > n), d.stderr()
            assert why in d.stderr() and str(cfg) in d.stderr()
            assert d.proc.poll() is None
    finally:
        d.signal(signal.SIGTERM)
        code = d.wait()
    assert code == 0 and "Traceback" not in d.stderr() and "MemoryError" not in d.stderr()
