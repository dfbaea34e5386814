"""Sinks on their own thread: same files as written in line, a sink's failure ends the replay and
leaves no partial file behind."""

import pytest

from cmcan import config as cfgmod
from cmcan.assemble import assemble
from cmcan.io.columns import column_chunks
from cmcan.replay import EmitWriter, SinkThread, TimelineWriter, replay_columns, replay_file
from tests.helpers import sim_frames, write_log


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    p = tmp_path_factory.mktemp("sinkthread") / "run.log"
    _, frames = sim_frames("two_set_validation", duration_h=0.1)
    write_log(p, frames)
    return p


def monitor():
    return assemble(cfgmod.load()).monitor


def test_threaded_sinks_write_what_inline_sinks_write(log, tmp_path):
    inline = [TimelineWriter(tmp_path / "a.csv"), EmitWriter(tmp_path / "a.log")]
    replay_columns(monitor(), column_chunks(log, chunk_bytes=4096), inline)
    replay_file(log, monitor(), [TimelineWriter(tmp_path / "b.csv"), EmitWriter(tmp_path / "b.log")])
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    assert (tmp_path / "a.log").read_bytes() == (tmp_path / "b.log").read_bytes()
    assert len((tmp_path / "b.log").read_bytes()) > 0


class Broken(TimelineWriter):
    def ticks(self, c):
        raise OSError(28, "No space left on device")


def test_a_failing_sink_fails_the_replay_and_leaves_nothing(log, tmp_path):
    sinks = [Broken(tmp_path / "t.csv"), EmitWriter(tmp_path / "e.log")]
    with pytest.raises(OSError, match="No space"):
        replay_file(log, monitor(), sinks)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_sink_thread_raises_at_close_when_the_last_chunk_failed(tmp_path):
    st = SinkThread([Broken(tmp_path / "t.csv")])
    st.start(0.0)
    from cmcan.monitor.tick import TickColumns

    st.ticks(TickColumns.from_ticks([]))
    with pytest.raises(OSError):
        st.close()
    assert not (tmp_path / "t.csv").exists() and not (tmp_path / "t.csv.tmp").exists()
