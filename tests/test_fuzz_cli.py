"""A short run of the command-line fuzz harness (tests/fuzz_cli.py): every target twice, a fixed seed.
The 10-minute run's figures are in docs/reliability.md."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys

import pytest

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
    assert o.code == 64 and o.problems == ["the message does not name 'run.log'"]


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


def fake_cmcan(tmp_path, monkeypatch, body: str) -> None:
    """The harness runs ``sys.executable -m cmcan ...``: a shell script in its place does ``body``."""
    script = tmp_path / "fake-python"
    script.write_text("#!/bin/sh\n" + body + "\n")
    script.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(script))


def test_the_harness_sees_a_quoted_secret_and_writes_besides_the_outputs(tmp_path, monkeypatch):
    corpus = Corpus(tmp_path / "base")
    outside = corpus.secret().parent
    d = tmp_path / "case"
    d.mkdir()
    (d / "run.log").write_text("x\n")
    t = Target("bogus", ("log",), ("log",), ("replay", "run.log", "--out", "timeline.csv"))
    fake_cmcan(tmp_path, monkeypatch, f'cat "{corpus.secret()}" >&2; echo ok > timeline.csv; echo x > stray.txt')
    o = run_case(Case(0, t, "log", "truncate", dir=d, argv=list(t.argv), names=["run.log"]), outside)
    assert o.code == 0
    assert "a message quotes a file outside the folder (the canary secret)" in o.problems
    assert "written besides its outputs ['timeline.csv']: ['stray.txt']" in o.problems
    fake_cmcan(tmp_path, monkeypatch, f'cp "{corpus.secret()}" timeline.csv; echo x > "{outside}/dropped"; exit 65')
    o = run_case(Case(1, t, "log", "truncate", dir=d, argv=list(t.argv), names=["run.log"]), outside)
    assert o.code == 65 and any("an output quotes a file outside the folder" in p for p in o.problems)
    assert f"written outside the case's folder: {outside}" in o.problems
    assert "no message" in o.problems and any(p.startswith("written on failure") for p in o.problems)


def test_hostile_mutations_make_what_they_say(tmp_path):
    """Each hostile mutation, applied to a copy of its corpus item, holds the attack it names."""
    import numpy as np
    import yaml

    from cmcan import yamlsafe
    from cmcan.service.statefile import examine, read_baseline_request
    from tests.fuzz_cli import HOSTILE, hostile_for, make_hostile

    corpus = Corpus(tmp_path / "base")
    made = set()
    for i, (item, how) in enumerate((it, h) for it in Corpus.ITEMS for h in hostile_for(it)):
        for k in range(3):
            d = tmp_path / f"c{i}-{k}"
            d.mkdir()
            src, dst = corpus.path(item), d / Corpus.ITEMS[item][0]
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copytree(src, dst) if src.is_dir() else shutil.copyfile(src, dst)
            detail, names = make_hostile(dst, item, how, np.random.default_rng([5, i, k]), corpus)
            made.add(how)
            assert dst.name in names and detail
            if how in ("aliasbomb", "deepnest", "recursive"):
                with pytest.raises(yamlsafe.YamlError):
                    yamlsafe.load_file(dst)
            elif how == "mqttstring":
                assert yaml.safe_load(dst.read_text())["uplink"]
            elif how == "bigframe":
                longest = max(len(line.split("#")[-1]) for line in dst.read_text().splitlines())
                assert longest > 2 * 64
            elif item == "fleetdir" and how != "machinenl":
                links = [p for p in (dst / "wl-1").iterdir() if p.is_symlink() or not p.is_file()]
                assert links, list((dst / "wl-1").iterdir())
            elif item == "manifest":
                assert dst.read_text() != src.read_text()
            elif item == "state":  # damaged, part by part, as the daemon reads it (tests/test_statefile*.py)
                assert examine(dst.read_bytes()).damage, detail
            elif item == "request":
                assert read_baseline_request(dst.parent)["bad"] == "1", detail
    assert examine(corpus.path("state").read_bytes()).damage == ()  # the corpus's own state is sound
    assert read_baseline_request(corpus.path("request").parent)["reason"] == "fuzz: pump replaced"
    assert made == set(HOSTILE)
