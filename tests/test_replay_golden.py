"""The replay's output frames and timelines on every shipped scenario stay byte for byte what they
were (``tests/data/replay_golden.json``, rewritten only on purpose by ``python -m tests.replay_golden
--write``)."""

import json

import pytest

from tests.replay_golden import CASES, GOLDEN, replay_digests

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("name", list(CASES))
def test_replay_output_is_unchanged(tmp_path, name):
    want = json.loads(GOLDEN.read_text())[name]
    got = replay_digests(name, CASES[name], tmp_path)
    assert got["warnings"] == want["warnings"]
    assert got["emitted_sha256"] == want["emitted_sha256"]
    assert got["timeline_sha256"] == want["timeline_sha256"]
