"""A short run of the command-line fuzz harness (tests/fuzz_cli.py): every target twice, a fixed seed.
The 10-minute run's figures are in docs/reliability.md."""

from __future__ import annotations

import hashlib
import json

from tests.fuzz_cli import TARGETS, Case, Corpus, Target, available, fuzz, run_case


def test_a_short_fuzz_run_over_every_command_finds_nothing(tmp_path):
    targets = available(TARGETS)
    s = fuzz(17, cases=2 * len(targets), jobs=2, work=tmp_path, round_robin=True)
    assert s.cases == 2 * len(targets)
    assert not s.failures, json.dumps(s.failures, indent=1)
    assert set(s.targets) == {t.name for t in targets}
    assert sum(n for code, n in s.codes.items() if code != "0") > len(targets)  # mostly refused inputs


def test_the_harness_sees_a_message_that_does_not_name_the_file(tmp_path):
    """The checks can fail: a usage error about something else does not name the spoiled log."""
    corpus = Corpus(tmp_path / "base")
    d = tmp_path / "case"
    d.mkdir()
    (d / "run.log").write_bytes(corpus.path("log").read_bytes()[:1000])
    t = Target("bogus", ("log",), ("log",), ("replay", "run.log", "--engine", "warp"))
    o = run_case(Case(0, t, "log", "truncate", dir=d, argv=list(t.argv)))
    assert o.code == 64 and o.problems == ["the message does not name run.log"]


def test_the_harness_sees_a_spoiled_model_that_was_used(tmp_path):
    """A command that does not read the spoiled model exits 0: the harness calls that an accepted model."""
    corpus = Corpus(tmp_path / "base")
    d = tmp_path / "case"
    d.mkdir()
    (d / "run.log").write_bytes(corpus.path("log").read_bytes())
    model = corpus.path("model").read_bytes()
    (d / "model.onnx").write_bytes(model[:-1] + bytes([model[-1] ^ 1]))
    t = Target("bogus", ("log", "model"), ("model",), ("replay", "run.log", "--out", "timeline.csv"))
    case = Case(0, t, "model", "bitflip", dir=d, argv=list(t.argv), pristine=hashlib.sha256(model).hexdigest())
    o = run_case(case)
    assert o.code == 0 and o.problems == ["a spoiled model was accepted"]
