"""Fleet sources stay where the user said: links out of a folder, manifest paths out of their root and
files that are not regular files are refused before anything opens them; a folder's manifest is used;
a log named twice is taken once and the difference said; machine ids are whole partition names."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from cmcan.errors import CmcanError, Kind
from cmcan.fleet.dataset import check_machine
from cmcan.fleet.sources import discover, find_logs


def touch(p: Path, text: str = "(1767225600.000000) can0 100#00\n") -> Path:
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text)
    return p


@pytest.fixture
def secret(tmp_path):
    """A file outside every fleet folder, as /etc/shadow or a credentials file would be."""
    return touch(tmp_path / "outside" / "shadow", "root:*:20228:0:99999:7:::\n")


def test_a_link_out_of_a_folder_is_refused_unless_asked(tmp_path, secret):
    fleet = tmp_path / "fleet"
    ok = touch(fleet / "m001" / "a.log")
    (fleet / "m001" / "evil.log").symlink_to(secret)
    (fleet / "m002").mkdir()
    kept = touch(fleet / "store" / "x.bin")
    (fleet / "m002" / "inside.log").symlink_to(kept)  # a link that stays inside is fine
    (fleet / "m003").symlink_to(secret.parent, target_is_directory=True)  # a folder link out
    found = find_logs([str(fleet)])
    assert sorted(Path(j.log).name for j in found.jobs) == ["a.log", "inside.log"]
    why = {Path(r.path).name: (r.machine, r.reason) for r in found.refused}
    assert why["evil.log"][0] == "m001" and "symbolic link to outside" in why["evil.log"][1]
    assert "--follow-symlinks" in why["evil.log"][1] and "folder outside" in why["m003"][1]
    with pytest.raises(CmcanError, match=r"refused .*(evil.log|m003)") as exc:
        discover([str(fleet)])
    assert exc.value.kind == Kind.NO_PERMISSION
    assert ok.exists()
    asked = find_logs([str(fleet)], follow_symlinks=True)
    assert sorted(Path(j.log).name for j in asked.jobs) == ["a.log", "evil.log", "inside.log"] and not asked.refused


def test_a_glob_match_through_a_link_out_is_refused(tmp_path, secret):
    fleet = tmp_path / "fleet"
    touch(fleet / "m001" / "a.log")
    (fleet / "m001" / "b.log").symlink_to(secret)
    found = find_logs([str(fleet / "*" / "*.log")])
    assert [Path(j.log).name for j in found.jobs] == ["a.log"]
    assert [Path(r.path).name for r in found.refused] == ["b.log"] and found.refused[0].origin.startswith("glob ")


@pytest.mark.parametrize(
    "row",
    [
        "m001,{secret}",  # an absolute path anywhere
        "m001,../outside/shadow",  # out by '..'
        "m001,logs/a.log,{secret}",  # the configuration outside
        "m001,logs/a.log,,../outside/shadow",  # the model outside
        "m001,link.log",  # a link in the root to outside it
    ],
)
def test_manifest_paths_stay_under_the_manifests_root(tmp_path, secret, row):
    d = tmp_path / "fleet"
    touch(d / "logs" / "a.log")
    (d / "link.log").symlink_to(secret)
    (d / "m.csv").write_text("machine,log,config,model\n" + row.format(secret=secret) + "\n")
    found = find_logs([str(d / "m.csv")])
    assert found.jobs == [] and len(found.refused) == 1
    r = found.refused[0]
    assert r.machine == "m001" and r.origin.endswith("m.csv line 2")
    assert "outside the manifest's root" in r.reason
    # a wider root is the user's explicit choice; a link out still needs --follow-symlinks
    wide = find_logs([str(d / "m.csv")], manifest_root=str(tmp_path))
    assert len(wide.jobs) == 1 and not wide.refused
    if "link.log" in row:  # the link out of the manifest's folder is followed when asked
        assert "--follow-symlinks" in r.reason
        assert len(find_logs([str(d / "m.csv")], follow_symlinks=True).jobs) == 1


def test_fifos_and_devices_are_refused_before_anything_opens_them(tmp_path):
    d = tmp_path / "fleet"
    touch(d / "m001" / "a.log")
    os.mkfifo(d / "m001" / "pipe.log")
    (d / "m.csv").write_text("machine,log\nm002,/dev/zero\nm003,pipe.log\n")
    os.mkfifo(d / "pipe.log")
    found = find_logs([str(d / "m001"), str(d / "m.csv")], manifest_root="/")
    reasons = {Path(r.path).name: r.reason for r in found.refused}
    assert "a FIFO, not a regular file" in reasons["pipe.log"]
    assert "a character device" in reasons["zero"]
    assert len(found.refused) == 3 and [Path(j.log).name for j in found.jobs] == ["a.log"]
    # named directly on the command line, a FIFO is refused the same way (reading it would block)
    only = find_logs([str(d / "m001" / "pipe.log")])
    assert only.jobs == [] and "FIFO" in only.refused[0].reason


def test_a_folder_holding_a_manifest_is_read_through_it(tmp_path):
    f = tmp_path / "f"
    touch(f / "logs" / "m001" / "m001_a.log")
    touch(f / "logs" / "m002" / "m002_a.log")
    touch(f / "types" / "compact" / "cmcan.yaml", "x: 1\n")
    (f / "manifest.csv").write_text("machine,log,config\nm001,logs/m001/m001_a.log,types/compact/cmcan.yaml\n")
    found = find_logs([str(f)])
    assert [(j.machine, Path(j.log).name, Path(j.config).parent.name) for j in found.jobs] == [
        ("m001", "m001_a.log", "compact")
    ]
    assert any("read through its manifest.csv" in n for n in found.notes)
    assert any("1 log(s) below it are not in its manifest.csv" in n for n in found.notes)
    # its logs folder alone: the manifest above names them with their configuration, so the run stops
    with pytest.raises(CmcanError, match=r"manifest.csv names 1 of these logs .* or give --config") as exc:
        find_logs([str(f / "logs")])
    assert exc.value.kind == Kind.USAGE
    # unless one configuration for all is what the user asks for
    assert len(find_logs([str(f / "logs")], config=str(f / "types" / "compact" / "cmcan.yaml")).jobs) == 2
    # or the manifest is among the sources: its rows decide
    both = find_logs([str(f / "logs"), str(f / "manifest.csv")])
    got = {j.machine: j.config for j in both.jobs}
    assert got["m001"].endswith("types/compact/cmcan.yaml") and got["m002"] is None


def test_a_log_named_by_two_sources_says_which_configuration_it_got(tmp_path):
    f = tmp_path / "f"
    touch(f / "logs" / "m001" / "m001_a.log")
    touch(f / "cfg.yaml", "x: 1\n")
    touch(f / "other.yaml", "x: 1\n")
    (f / "m.csv").write_text("machine,log,config\nm001,logs/m001/m001_a.log,cfg.yaml\n")
    for order in ([f / "logs", f / "m.csv"], [f / "m.csv", f / "logs"]):
        found = find_logs([str(p) for p in order], config=str(f / "other.yaml"))
        assert len(found.jobs) == 1 and found.jobs[0].config == str(f / "cfg.yaml")  # the manifest row wins
        (note,) = found.notes
        assert "m.csv line 2" in note and "cfg.yaml" in note and "other.yaml" in note and "folder" in note
    same = find_logs([str(f / "m.csv"), str(f / "m.csv")])
    assert len(same.jobs) == 1 and not same.notes  # the same row twice: nothing to say


@pytest.mark.parametrize("name", ["m002\n", "m002\r", "m002 ", "a/b", "x=1", "", "-m", "m" * 101, "m\x00"])
def test_machine_ids_are_whole_partition_names(name):
    with pytest.raises(CmcanError, match="not usable as a partition name"):
        check_machine(name, "here")


def test_a_machine_folder_named_with_a_newline_is_refused(tmp_path):
    fleet = tmp_path / "fleet"
    touch(fleet / "m002\n" / "a.log")
    with pytest.raises(CmcanError, match=r"machine id 'm002\\n'") as exc:
        find_logs([str(fleet)])
    assert exc.value.kind == Kind.DATA
    # a manifest's cells are stripped of blanks: a quoted 'm002<newline>' is m002, not a new partition
    touch(tmp_path / "x.log")
    (tmp_path / "m.csv").write_text('machine,log\n"m002\n",x.log\n')
    assert [j.machine for j in find_logs([str(tmp_path / "m.csv")]).jobs] == ["m002"]
