"""What train, score and gap say about the data they read: a log of several buses read by a machine
of one bus (a foreign bus's frames with a mapped identifier would be read as inputs), as replay says
it; each refusal with the limit that refused it."""

from __future__ import annotations

from tests.conftest import run_cli


def test_score_of_a_log_of_two_buses_notes_they_were_read_as_one(tmp_path):
    one = tmp_path / "a.log"
    res = run_cli("simulate", "single_set_healthy", "--duration-h", "0.02", "--out", str(tmp_path / "r.csv"),
                  "--candump", str(one))  # fmt: skip
    assert res.returncode == 0, res.stderr
    lines = one.read_text().splitlines()
    two = tmp_path / "two.log"
    two.write_text("".join(f"{ln}\n{ln.replace(' can0 ', ' can1 ')}\n" for ln in lines))
    merged = run_cli("score", str(two), "--out", str(tmp_path / "s.csv"))
    assert merged.returncode == 0, merged.stderr
    assert "the log's channels can0, can1 were all read as can0" in merged.stderr
    assert "channels.from_log" in merged.stderr
    single = run_cli("score", str(one), "--out", str(tmp_path / "s1.csv"))
    assert single.returncode == 0 and "were all read as" not in single.stderr, single.stderr


def test_train_names_each_refusal_with_its_limit(tmp_path):
    """The gate report of train: the transient refusals name each role with its (scaled) limit, as
    the other refusals name theirs, so a limit below a sensor's noise can be seen."""
    log = tmp_path / "a.log"
    res = run_cli("simulate", "single_set_healthy", "--duration-h", "0.05", "--out", str(tmp_path / "r.csv"),
                  "--candump", str(log))  # fmt: skip
    assert res.returncode == 0, res.stderr
    res = run_cli("train", str(log), "--out", str(tmp_path / "m.onnx"), "--json")
    assert res.returncode == 0, res.stderr
    import json

    why = json.loads(res.stdout)["gates"]["refused"]["transient"]["why"]
    assert "dp_bar above 5 bar (" in why and "pump_speed_rpm above 8 rpm (" in why, why
