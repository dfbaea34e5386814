"""Property tests of the state directory's files as untrusted input (issue 38), with hypothesis.

- Any bytes as ``state.json`` are read without an exception, by the reader and by the daemon's load.
- A real state (every part filled: tests/statefile_support.py) spoiled at any place in one of many
  ways: only the part the spoiling touched is damaged (a number the file may not hold and nesting too
  deep always are; an unknown field never is), every other part is kept exactly, the daemon's load
  keeps the file aside byte for byte and says each damage once, and the monitor built from what is
  kept neither refuses a part again (the file's checks are at least as strict as the core's) nor
  fails on the frames that follow.
- Any bytes as the request file: a request or a refusal naming the file, one journal line.

Each test tallies what it reached (hypothesis ``event`` for the statistics, and a count asserted at the
end): every spoiling, every part damaged and every part kept beside a damaged one.
"""

from __future__ import annotations

import json
import logging
import string
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from cmcan.monitor.totals import Totals
from cmcan.service.statefile import BASELINE_REQUEST_FILE, PARTS, StateStore, examine, read_baseline_request
from tests import statefile_support as sf

SETTINGS = settings(
    max_examples=150,
    deadline=None,
    derandomize=True,  # the tallies below are asserted: the same examples every run
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

PER_SPOILING = settings(SETTINGS, max_examples=20)

# numbers a state file may not hold, as JSON text
REFUSED = ["1" + "0" * 309, str(2**63), "-" + "9" * 400, "1e400", "-1e400", "NaN", "Infinity", "1e300", "1e16"]
SURE = {"refused number", "deep"}  # always damage the part they are in
SPOILINGS = ["refused number", "deep", "wrong type", "any json", "drop", "duplicate", "swap", "scale", "unknown field"]
TOP = [*PARTS, "format"]  # where a spoiling lands: a part's fields, or the format

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner, max_size=4),
    max_leaves=12,
)


def paths(node: Any, at: tuple = ()) -> list[tuple]:
    """Every place in a document: the node itself and all below it."""
    out = [at]
    if isinstance(node, dict):
        for k, v in node.items():
            out += paths(v, (*at, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += paths(v, (*at, i))
    return out


def parent(doc: Any, path: tuple) -> Any:
    for k in path[:-1]:
        doc = doc[k]
    return doc


def part_of_field(field: str) -> str:
    return next((p for p, (fields, _) in PARTS.items() if field in fields), "file")


def spoil(doc: dict, data: st.DataObject, how: str) -> tuple[dict, dict[str, str], str | None]:
    """``doc`` spoiled in place by ``how``: the literal number texts to put in, and the part touched
    (None: nothing a part holds)."""
    literals: dict[str, str] = {}
    if how == "unknown field":
        doc["zz_" + data.draw(st.text(string.ascii_lowercase, max_size=6))] = data.draw(json_values)
        doc["zz_refused"] = "@0@"
        literals["0"] = data.draw(st.sampled_from(REFUSED))
        return doc, literals, None
    top = data.draw(st.sampled_from(TOP))
    fields = PARTS[top][0] if top in PARTS else ("format",)
    field = data.draw(st.sampled_from([f for f in fields if f in doc]))
    where = data.draw(st.sampled_from(paths(doc[field], (field,))))
    node = parent(doc, where)
    key = where[-1]
    if how == "refused number":
        literals["0"] = data.draw(st.sampled_from(REFUSED))
        node[key] = "@0@"
    elif how == "deep":
        node[key] = json.loads("[" * 70 + "]" * 70)
    elif how == "wrong type":
        node[key] = data.draw(st.sampled_from(["x", True, None, [], {}, 0, -1, 0.5]))
    elif how == "any json":
        node[key] = data.draw(json_values)
    elif how == "scale" and isinstance(node[key], (int, float)) and not isinstance(node[key], bool):
        node[key] = node[key] * data.draw(st.sampled_from([-1, 0, 10**-20, 10**20, 2, 0.5, 10**6]))
    elif how in ("drop", "duplicate", "swap"):
        target = node[key] if isinstance(node[key], (list, dict)) and node[key] else node
        if target is doc:  # at the top: the field itself, never another part's
            index: Any = field
        else:
            index = data.draw(st.sampled_from(list(target.keys() if isinstance(target, dict) else range(len(target)))))
        if how == "drop":
            del target[index]
        elif isinstance(target, list):
            other = data.draw(st.integers(0, len(target) - 1))
            if how == "duplicate":
                target.insert(other, target[index])
            else:
                target[index], target[other] = target[other], target[index]
    return doc, literals, part_of_field(field)


def text_of(doc: dict, literals: dict[str, str]) -> bytes:
    text = json.dumps(doc, allow_nan=True)
    for name, lit in literals.items():
        text = text.replace(f'"@{name}@"', lit)
    return text.encode()


def test_a_spoiled_state_damages_only_the_part_it_touched_and_the_daemon_runs_on(tmp_path):
    cfg = sf.config_file(tmp_path)
    good = Totals.from_dict(sf.good_doc())
    tally: Counter = Counter()
    log = logging.getLogger("cmcan.state")
    current = [SPOILINGS[0]]

    @PER_SPOILING
    @given(data=st.data())
    def check(data: st.DataObject) -> None:
        how = current[0]
        doc, literals, touched = spoil(sf.good_doc(), data, how)
        raw = text_of(doc, literals)
        reading = examine(raw)
        damaged = {d.part for d in reading.damage}
        tally[f"spoiling {how}"] += 1
        event(f"spoiling: {how}")
        for p in damaged:
            tally[f"damaged {p}"] += 1
            event(f"damaged: {p}")
        if touched is None:
            assert not damaged
        elif how in SURE:
            assert damaged == {touched}, (how, touched, reading.damage)
        else:
            assert damaged <= {touched}, (how, touched, reading.damage)
        for p in PARTS:
            if p in damaged or "file" in damaged:
                assert sf.part_of(reading.totals, p) == sf.part_of(Totals(), p) or p == "prognosis"
            elif p != touched:
                assert sf.part_of(reading.totals, p) == sf.part_of(good, p), p
                if damaged:
                    tally[f"kept {p} beside a damaged part"] += 1
        daemon_load(raw, reading, log)
        mon = sf.build(cfg, reading.totals)
        refused = [n for n in (mon.baseline_note, mon.prognosis.note if mon.prognosis else None) if n]
        assert not any("could not be used" in n for n in refused), (how, touched, refused)
        assert sf.still_up(mon) > 0

    for how in SPOILINGS:  # each its own run: a drawn spoiling would favour the first ones
        current[0] = how
        check()
    assert {f"spoiling {h}" for h in SPOILINGS} <= set(tally), tally
    assert {f"damaged {p}" for p in [*PARTS, "file"]} <= set(tally), tally
    assert {f"kept {p} beside a damaged part" for p in PARTS} <= set(tally), tally


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def daemon_load(raw: bytes, reading: Any, log: logging.Logger) -> None:
    """The daemon's load of the same bytes: the same totals; when damaged, the file kept aside byte for
    byte and one journal line per damage naming the file; what was kept is on disk and sound."""
    lines = _Lines()
    log.addHandler(lines)
    try:
        with tempfile.TemporaryDirectory() as d:
            store = StateStore(d)
            store.path.write_bytes(raw)
            assert store.load() == reading.totals
            aside = Path(d) / "state.json.corrupt-1"
            assert aside.exists() == bool(reading.damage)
            if reading.damage:
                assert aside.read_bytes() == raw
                assert len(lines.lines) == len(reading.damage)
                assert all(str(store.path) in x and "kept as" in x for x in lines.lines)
                assert store.path.exists() == (reading.totals != Totals())
            if store.path.exists():
                assert store.read() == reading.totals
    finally:
        log.removeHandler(lines)


def sound(count: int, seconds: float, ratios: list[float]) -> bytes:
    t = Totals(warning_count=count, evaluated_s=seconds, filter_ratios=ratios, filter_leaks=ratios)
    return json.dumps(t.to_dict()).encode()


def test_any_bytes_as_a_state_file_are_read_without_an_exception(tmp_path):
    tally: Counter = Counter()
    head = b'{"format": "cmcan-state/1", '

    @SETTINGS
    @given(
        content=st.one_of(
            st.binary(max_size=200),
            json_values.map(lambda v: json.dumps(v, allow_nan=True).encode()),
            st.dictionaries(st.sampled_from([f for fs, _ in PARTS.values() for f in fs]), json_values).map(
                lambda d: head + json.dumps(d, allow_nan=True).encode()[1:]
            ),
            st.builds(sound, st.integers(0, 10**15), st.floats(0, 1e15), st.lists(st.floats(-1e15, 1e15), max_size=5)),
        )
    )
    def check(content: bytes) -> None:
        reading = examine(content)
        kind = "damaged" if reading.damage else "sound"
        tally[kind] += 1
        tally["whole" if reading.whole and reading.damage else "parts"] += 1
        event(kind)
        for d in reading.damage:
            assert d.problem and d.afresh
        with tempfile.TemporaryDirectory() as d:
            (Path(d) / "state.json").write_bytes(content)
            assert StateStore(d).load() == reading.totals

    check()
    assert tally["damaged"] and tally["sound"] and tally["whole"] and tally["parts"], tally


def test_any_bytes_as_the_request_file_are_a_request_or_a_refusal_naming_it(tmp_path):
    tally: Counter = Counter()
    req = tmp_path / BASELINE_REQUEST_FILE

    @SETTINGS
    @given(
        content=st.one_of(
            st.binary(max_size=300),
            st.builds(
                lambda reason, at: json.dumps({"reason": reason, "at": at}).encode(),
                st.text(max_size=400),
                st.text(max_size=60),
            ),
            json_values.map(lambda v: json.dumps(v, allow_nan=True).encode()),
            st.integers(4000, 9000).map(lambda n: json.dumps({"reason": "x" * n}).encode()),
        )
    )
    def check(content: bytes) -> None:
        req.write_bytes(content)
        got = read_baseline_request(tmp_path)
        assert got is not None
        kind = "refused" if got.get("bad") else "request"
        tally[kind] += 1
        event(kind)
        if got.get("bad"):
            assert str(req) in got["reason"]
        else:
            assert len(got["reason"]) <= 200 and len(got["at"]) <= 40
            assert all(c.isprintable() for c in got["reason"] + got["at"])  # one journal line

    check()
    assert tally["refused"] and tally["request"], tally
