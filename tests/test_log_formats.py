"""Logs written by others, in the shapes the public logs came in: candump's screen output, broken
candump lines, oversized frames, hundreds of channel names, logs cut short in every format and CSV
logs of another layout. Every reader (the line reader, the columnar reader with the C helpers and
with numpy, python-can's readers for the other formats) says the same thing, naming file and line."""

from __future__ import annotations

import gzip
import json
import os
import time

import can
import pytest

from cmcan.can.frame import Frame
from cmcan.cli.errors import EX_DATAERR
from cmcan.io.candump import MAX_CHANNELS, Cut, LogError, iter_frames
from cmcan.io.columns import column_chunks
from tests.conftest import run_cli
from tests.helpers import IMPLS, helpers_impl

T0 = 1700000000.0
FRAMES = [
    Frame(T0 + 0.123456, "can0", 0x18FEF100, True, False, False, False, bytes.fromhex("FFFF3412FFFFFFFF")),
    Frame(T0 + 0.25, "can0", 0x123, False, False, False, False, bytes.fromhex("0011")),
    Frame(T0 + 0.5, "can1", 0x7FF, False, False, False, False, b""),
    Frame(T0 + 0.75, "can0", 0x321, False, False, False, True, bytes(range(12))),  # CAN FD
    Frame(T0 + 1.0, "can0", 0x456, False, True, False, False, b""),  # remote
]


def screen_line(f: Frame, stamp: str, ascii_: bool = False, extra: bool = False) -> str:
    """A frame as candump prints it on screen (can-utils' lib.c): ``(stamp)  can0  123   [2]  00 11``;
    CAN FD lengths with two digits, a remote frame as "remote request", -a's ASCII, -x's flags."""
    cid = f"{f.arbitration_id:08X}" if f.extended else f"{f.arbitration_id:03X}"
    flags = "RX - -  " if extra else ""
    if f.remote:
        return f"({stamp})  {f.channel}  {flags}{cid}   [0]  remote request\n"
    length = f"[{len(f.data):02d}]" if f.fd else f"[{len(f.data)}]"
    data = " ".join(f"{b:02X}" for b in f.data)
    text = "  '" + "".join(chr(b) if 32 <= b < 127 else "." for b in f.data) + "'" if ascii_ else ""
    pad = "  " if f.fd else "   "
    return f"({stamp})  {f.channel}  {flags}{cid}{pad}{length}  {data}{text}\n"


def columnar(path, **kw) -> list[Frame]:
    return [f for c in column_chunks(path, **kw) for f in c.frames()]


def every_reader(path, **kw) -> list[list[Frame]]:
    """The frames of a log by the line reader and the columnar reader (C helpers and numpy)."""
    out = [list(iter_frames(path, **kw))]
    for impl in IMPLS:
        if impl == "native":
            from cmcan.io import native

            if native.LIB is None:
                continue
        with helpers_impl(impl):
            out.append(columnar(path, **kw))
    return out


def refused_by_every_reader(path, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        list(iter_frames(path))
    for impl in IMPLS:
        from cmcan.io import native

        if impl == "native" and native.LIB is None:
            continue
        with helpers_impl(impl), pytest.raises(ValueError, match=match):
            columnar(path)


# -- candump's screen output ---------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["plain", "ascii", "extra"])
def test_candump_ta_screen_output_reads_as_the_same_frames_in_every_reader(tmp_path, variant):
    p = tmp_path / "ta.log"
    lines = [
        screen_line(f, f"{f.timestamp_s:017.6f}", ascii_=variant == "ascii", extra=variant == "extra") for f in FRAMES
    ]
    p.write_text("".join(lines))
    for got in every_reader(p):
        assert got == FRAMES


def test_candump_tA_screen_output_is_the_recording_machines_local_time(tmp_path, monkeypatch):
    monkeypatch.setenv("TZ", "Europe/Berlin")
    time.tzset()
    try:
        p = tmp_path / "tA.log"
        # 2023-11-14 23:13:20 in Berlin (UTC+1 in November) is 1700000000 s after the epoch
        stamps = [time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(int(f.timestamp_s))) for f in FRAMES]
        frac = [f"{f.timestamp_s % 1:.6f}"[1:] for f in FRAMES]
        assert stamps[0] == "2023-11-14 23:13:20"
        p.write_text("".join(screen_line(f, s + x) for f, s, x in zip(FRAMES, stamps, frac, strict=True)))
        for got in every_reader(p):
            assert [f.timestamp_s for f in got] == pytest.approx([f.timestamp_s for f in FRAMES], abs=1e-6)
            assert [f._replace(timestamp_s=0.0) for f in got] == [f._replace(timestamp_s=0.0) for f in FRAMES]
    finally:
        os.environ.pop("TZ", None)
        time.tzset()


@pytest.mark.parametrize(
    ("stamp", "needle"),
    [
        ("000.000123", "relative times"),  # candump -td / -tz
        ("012.500000", "relative times"),
        (None, "without timestamps"),  # candump without -t
    ],
)
def test_screen_output_without_absolute_times_says_how_to_record_it(tmp_path, stamp, needle):
    p = tmp_path / "rel.log"
    text = screen_line(FRAMES[0], stamp or "x")
    p.write_text(text if stamp else text.split(") ", 1)[1])
    refused_by_every_reader(p, rf"rel.log: line 1: candump screen output .*{needle}.*candump -l")
    if stamp is None:  # (the command line once: the same error, exit 65)
        r = run_cli("replay", str(p))
        assert r.returncode == EX_DATAERR and "candump -l can0" in r.stderr


# -- broken and oversized lines -------------------------------------------------------------------------


def test_a_candump_line_with_spaces_in_its_data_is_refused_as_python_can_refuses_it(tmp_path):
    p = tmp_path / "broken.log"
    p.write_text("(1700000000.000000) can0 43E#0090\n(1700000000.010000) can0 43E# 00 90 00 00\n")
    with pytest.raises(ValueError):
        list(can.LogReader(str(p)))
    refused_by_every_reader(p, r"broken.log: line 2: not a candump -l line: .*43E# 00 90")
    for engine in ("columnar", "streaming"):
        r = run_cli("replay", str(p), "--engine", engine)
        assert r.returncode == EX_DATAERR and "line 2" in r.stderr, r.stderr


@pytest.mark.parametrize("n_bytes", [65, 2000, 40000])
def test_a_frame_over_64_data_bytes_is_not_a_can_frame(tmp_path, n_bytes):
    p = tmp_path / "big.log"
    p.write_text(f"(1700000000.000000) can0 100#00\n(1700000000.010000) can0 100##0{'AB' * n_bytes}\n")
    refused_by_every_reader(p, r"big.log: line 2: .*(data bytes: not a CAN frame|longer than 4096 bytes)")
    for engine in ("columnar", "streaming") if n_bytes == 65 else ():
        r = run_cli("replay", str(p), "--engine", engine)
        assert r.returncode == EX_DATAERR and "line 2" in r.stderr, r.stderr


def test_64_data_bytes_are_a_can_fd_frame(tmp_path):
    p = tmp_path / "fd.log"
    p.write_text(f"(1700000000.000000) can0 100##0{'AB' * 64}\n")
    for got in every_reader(p):
        assert [len(f.data) for f in got] == [64]


def test_a_log_with_more_channel_names_than_a_bus_has_is_refused_at_the_line(tmp_path):
    p = tmp_path / "names.log"
    p.write_text("".join(f"(1700000000.{i:06d}) c{i} 100#00\n" for i in range(MAX_CHANNELS + 50)))
    refused_by_every_reader(p, rf"names.log: line {MAX_CHANNELS + 1}: more than {MAX_CHANNELS} channel names")
    r = run_cli("replay", str(p))
    assert r.returncode == EX_DATAERR


# -- logs cut short: one rule for every format ---------------------------------------------------------


def _messages():
    return [
        can.Message(timestamp=T0 + i * 0.01, arbitration_id=0x100 + i % 3, data=bytes([i % 256] * 8), channel=0)
        for i in range(40)
    ]


def _write(path, kind):
    if kind in ("log", "log.gz"):
        text = "".join(f"({m.timestamp:.6f}) can0 {m.arbitration_id:03X}#{m.data.hex().upper()}\n" for m in _messages())
        if kind == "log.gz":
            with gzip.open(path, "wt") as f:
                f.write(text)
        else:
            path.write_text(text)
        return
    with can.Logger(str(path)) as w:
        for m in _messages():
            w.on_message_received(m)


def _cut(path, kind):
    """The file cut as a logger killed mid-write leaves it: mid-line (text), mid-stream (gzip), mid-object
    (BLF); the line of the cut for text formats."""
    data = path.read_bytes()
    if kind == "log.gz":
        path.write_bytes(data[: len(data) * 2 // 3])
        return None
    if kind == "blf":
        path.write_bytes(data[: len(data) - 40])
        return None
    text = data.decode()
    # the last data line (asc: before "End TriggerBlock"), cut in its data
    lines = text.splitlines(keepends=True)
    k = max(i for i, ln in enumerate(lines) if "08" in ln or "#" in ln or "," in ln)
    if kind == "asc":
        k = max(i for i, ln in enumerate(lines) if ln.strip() and ln.split()[0][0].isdigit())
    cut_line = lines[k][: len(lines[k]) // 2 + 5]
    path.write_text("".join(lines[:k]) + cut_line)
    return k + 1


@pytest.mark.parametrize("kind", ["log", "log.gz", "asc", "csv", "trc", "blf"])
def test_a_log_cut_short_is_refused_naming_the_line_or_kept_to_its_last_whole_frame(tmp_path, kind):
    p = tmp_path / f"cut.{kind}"
    _write(p, kind)
    whole = list(iter_frames(p))
    assert len(whole) == 40
    line = _cut(p, kind)
    where = rf"line {line}: " if line is not None else ""
    with pytest.raises(LogError, match=rf"cut\.{kind}: {where}.*--keep-truncated"):
        list(iter_frames(p))
    cuts: list[Cut] = []
    kept = list(iter_frames(p, keep_truncated=True, on_cut=cuts.append))
    assert kept == whole[: len(kept)] and 0 < len(kept) < 40
    assert len(cuts) == 1 and cuts[0].frames == len(kept) and cuts[0].path == str(p)
    if line is not None:
        assert cuts[0].line == line
    # the columnar reader (candump logs: its own; others: through python-can) says and keeps the same
    cuts2: list[Cut] = []
    with pytest.raises(LogError, match=rf"cut\.{kind}: {where}"):
        columnar(p)
    assert columnar(p, keep_truncated=True, on_cut=cuts2.append) == kept
    assert cuts2 == cuts


def test_replay_refuses_a_cut_log_and_keeps_it_with_keep_truncated(tmp_path):
    p = tmp_path / "cut.log"
    _write(p, "log")
    line = _cut(p, "log")
    for engine in ("columnar", "streaming"):
        r = run_cli("replay", str(p), "--engine", engine)
        assert r.returncode == EX_DATAERR and f"line {line}" in r.stderr and "--keep-truncated" in r.stderr
        r = run_cli("replay", str(p), "--engine", engine, "--keep-truncated", "--json")
        # (no input of the shipped configuration in these frames: the replay runs, nothing matches)
        assert r.returncode == 0, r.stderr
        cut = json.loads(r.stdout)["cut"]
        assert cut["file"] == str(p) and cut["line"] == line and cut["frames_kept"] > 0
        assert f"line {line}" in r.stderr  # the warning


def test_score_train_and_evaluate_take_keep_truncated():
    from cmcan.cli import build_parser

    parser = build_parser()
    for argv in (
        ["score", "x.log", "--out", "s.csv"],
        ["train", "x.log", "--out", "m.onnx"],
        ["evaluate", "x.log", "--t-trn-h", "1"],
    ):
        assert parser.parse_args([*argv, "--keep-truncated"]).keep_truncated
        assert not parser.parse_args(argv).keep_truncated


# -- CSV logs of another layout ---------------------------------------------------------------------------


def test_a_savvycan_csv_is_refused_naming_the_layout_cmcan_reads(tmp_path):
    p = tmp_path / "savvy.csv"
    p.write_text(
        "Time Stamp,ID,Extended,Dir,Bus,LEN,D1,D2,D3,D4,D5,D6,D7,D8\n"
        "166064000,0000043E,false,Rx,0,8,00,90,00,00,00,00,00,00,\n"
    )
    with pytest.raises(LogError, match=r"savvy.csv: line 1: .*SavvyCAN.*timestamp,arbitration_id"):
        list(iter_frames(p))
    r = run_cli("replay", str(p))
    assert r.returncode == EX_DATAERR and "SavvyCAN" in r.stderr and "unpack" not in r.stderr
