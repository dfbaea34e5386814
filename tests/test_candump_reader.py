"""The fast candump reader has python-can's CanutilsLogReader semantics."""

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.can.frame import from_message
from cmcan.io.candump import iter_candump, iter_frames
from tests.helpers import IMPLS, helpers_impl

std_id = st.integers(0, 0x7FF).map(lambda i: f"{i:03X}")
ext_id = st.integers(0, 0x1FFFFFFF).map(lambda i: f"{i:08X}")
err_id = st.integers(0, 0xFF).map(lambda i: f"{0x20000080 | i:08X}")
payload = st.binary(min_size=0, max_size=8).map(lambda b: b.hex().upper())
remote = st.sampled_from(["R", "R0", "R8", "r"])
fd = st.tuples(st.sampled_from("0123"), st.binary(min_size=0, max_size=64)).map(lambda x: "#" + x[0] + x[1].hex())
line = st.tuples(
    st.floats(0, 2e9, allow_nan=False).map(lambda t: f"({t:017.6f})"),
    st.sampled_from(["can0", "vcan0", "1"]),
    st.one_of(std_id, ext_id, err_id),
    st.one_of(payload, remote, fd),
    st.sampled_from(["", " R", " T"]),
).map(lambda x: f"{x[0]} {x[1]} {x[2]}#{x[3]}{x[4]}")


@settings(max_examples=200, deadline=None)
@given(st.lists(line, min_size=1, max_size=20))
def test_same_frames_as_python_can(tmp_path_factory, lines):
    p = tmp_path_factory.mktemp("c") / "x.log"
    p.write_text("\n".join(lines) + "\n\n")
    ours = list(iter_candump(p))
    ref = list(can.io.CanutilsLogReader(str(p)))
    assert len(ours) == len(ref)
    for o, m in zip(ours, ref, strict=True):
        want = from_message(m)
        if m.is_error_frame:  # python-can drops an error frame's channel; cmcan keeps the bus it was on
            want = want._replace(channel=o.channel)
        assert o == want


def test_gzipped_logs_and_other_formats(tmp_path):
    import gzip

    text = "(1767225600.000000) can0 100#0011223344556677\n(1767225600.010000) can0 18FEF100#01\n"
    (tmp_path / "a.log").write_text(text)
    with gzip.open(tmp_path / "a.log.gz", "wt") as f:
        f.write(text)
    a = list(iter_frames(tmp_path / "a.log"))
    assert a == list(iter_frames(tmp_path / "a.log.gz"))
    with can.Logger(str(tmp_path / "a.asc")) as w:
        for m in can.LogReader(str(tmp_path / "a.log")):
            w.on_message_received(m)
    b = list(iter_frames(tmp_path / "a.asc"))
    # ASC stores times relative to its start and numbers channels from 1: compare the rest
    assert [x._replace(timestamp_s=0, channel="") for x in b] == [x._replace(timestamp_s=0, channel="") for x in a]


def test_a_broken_line_names_file_and_line(tmp_path):
    p = tmp_path / "b.log"
    p.write_text("(1.0) can0 100#00\nnonsense\n")
    import pytest

    with pytest.raises(ValueError, match=r"b.log: line 2: not a candump -l line"):
        list(iter_candump(p))


# -- the columnar reader: the same frames as the line reader, whatever the mix of line shapes ------

std_line = st.tuples(
    st.floats(0, 2e9, allow_nan=False).map(lambda t: f"({t:017.6f})"),
    st.sampled_from(["can0", "can1", "vcan0", "1"]),
    st.one_of(std_id, ext_id, err_id, st.integers(0, 0xFFFF).map(lambda i: f"{i:04X}")),
    st.one_of(payload, remote, fd, st.sampled_from(["0", "ZZ", "00112"])),
    st.sampled_from(["", "", "", " R", " T"]),
).map(lambda x: f"{x[0]} {x[1]} {x[2]}#{x[3]}{x[4]}")
odd_line = st.sampled_from(
    [
        "(1e9) can0 100#00",
        "(12.5) can0 7FF#",
        "   ",
        "(1767225600.000001) can0 100#0011",
        # not timestamps: both readers refuse them, on the same line
        "(.) can0 100#0011",
        "(1.) can0 100#0011",
        "(.5) can0 100#0011",
        "(nan) can0 100#0011",
        "1767225600.000001 can0 100#0011",
        "x1767225600.00000y can0 100#0011",
    ]
)


# where the C parser's common shape ends: each either side of a limit it checks
edge_line = st.sampled_from(
    [
        "(1767225600.000000) can0 7ff#00aAbBcC",  # lower-case hex
        "(1767225600.000000) can0 800#00",  # 3 digits above 0x7FF
        "(1767225600.000000) can0 1FFFFFFF#00",
        "(1767225600.000000) can0 20000000#0000000000000000",  # the error flag
        "(1767225600.000000) can0 3FFFFFFF#00",
        "(1767225600.000000) can0 80000123#00",
        "(1767225600.000000) can0 123#001122334455667788",  # 9 bytes, no '##'
        "(1767225600.000000) can0 123#0",
        "(1767225600.000000) can0 12#00",
        "(1767225600.000000) can0 123456789#00",
        "(1767225600.000000)  can0 123#00",  # two spaces
        "(1767225600.000000) can0  123#00",
        "(1767225600.000000)\tcan0 123#00",
        "(1767225600.000000) can0 123#00\r",
        "(1767225600.000000) can0 123#00 ",
        " (1767225600.000000) can0 123#00",
        "(9007199254740.991) can0 123#00",  # 2^53 - 1 in 16 digits
        "(9007199254740.992) can0 123#00",  # 2^53
        "(9999999999.999999999) can0 123#00",  # 19 digits
        "(99999999999.999999999) can0 123#00",  # 20
        "(0000000000000000001.5) can0 123#00",
        "(1767225600.0) " + "c" * 31 + " 123#00",
        "(1767225600.0) " + "c" * 32 + " 123#00",
        "(1767225600.0) can\u00e90 123#00",
        "(1767225600.0) can0 123#R",
        "(1767225600.0) can0 123##1001122",
        "(1767225600.0) can0 123#0g",
    ]
)
many_channels = st.integers(0, 80).map(lambda k: f"(1767225600.{k:06d}) ch{k} 123#{k:02X}")


@pytest.mark.parametrize("impl", IMPLS)
@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.one_of(line, std_line, odd_line, edge_line, many_channels), min_size=1, max_size=60),
    st.integers(16, 400),
)
def test_columnar_reader_gives_the_line_readers_frames(tmp_path_factory, impl, lines, chunk):
    from cmcan.io.candump_columns import iter_candump_columns

    p = tmp_path_factory.mktemp("c") / "x.log"
    p.write_bytes(("\n".join(lines) + "\n").encode("utf-8"))
    with helpers_impl(impl):
        try:
            want = list(iter_candump(p))
        except ValueError as exc:  # a line the reader of record refuses: the columnar one refuses it too
            with pytest.raises(ValueError, match=str(exc).split(": ", 1)[1][:20].replace("(", r"\(")):
                [f for c in iter_candump_columns(p, chunk_bytes=chunk) for f in c.frames()]
            return
        got = [f for c in iter_candump_columns(p, chunk_bytes=chunk) for f in c.frames()]
    assert got == want


# lines python-can reads as cmcan does (no error frames), in upper and lower case
pc_line = st.tuples(
    st.floats(0, 2e9, allow_nan=False).map(lambda t: f"({t:017.6f})"),
    st.sampled_from(["can0", "vcan0", "1"]),
    st.one_of(std_id, ext_id),
    st.one_of(payload, payload, remote, fd),
    st.booleans(),
).map(lambda x: (f"{x[0]} {x[1]} {x[2]}#{x[3]}").lower() if x[4] else f"{x[0]} {x[1]} {x[2]}#{x[3]}")


@pytest.mark.parametrize("impl", IMPLS)
@settings(max_examples=60, deadline=None)
@given(st.lists(pc_line, min_size=1, max_size=40))
def test_columnar_reader_gives_python_cans_frames(tmp_path_factory, impl, lines):
    """Straight against the library: python-can's CanutilsLogReader."""
    from cmcan.io.candump_columns import iter_candump_columns

    p = tmp_path_factory.mktemp("c") / "x.log"
    p.write_text("\n".join(lines) + "\n")
    ref = [from_message(m) for m in can.io.CanutilsLogReader(str(p))]
    with helpers_impl(impl):
        got = [f for c in iter_candump_columns(p, chunk_bytes=1 << 12) for f in c.frames()]
    assert got == ref


@pytest.mark.parametrize("impl", IMPLS)
def test_columnar_reader_on_a_long_uniform_log(tmp_path, impl):
    from cmcan.io.candump_columns import iter_candump_columns

    lines = [
        f"({1767225600 + i * 0.000137:017.6f}) can0 {0x100 + i % 4:03X}#{i % 65536:04X}00FF{i % 251:02X}00AA\n"
        for i in range(20000)
    ]
    p = tmp_path / "u.log"
    p.write_text("".join(lines))
    with helpers_impl(impl):
        got = [f for c in iter_candump_columns(p, chunk_bytes=1 << 16) for f in c.frames()]
    assert got == list(iter_candump(p))


@pytest.mark.parametrize("impl", IMPLS)
def test_chunks_by_lines_hold_as_many_frames_whatever_the_identifier_length(tmp_path, impl):
    """With ``chunk_lines`` a log of 29-bit identifiers (longer lines) comes in chunks of as many
    frames as a log of 11-bit ones, and the frames are those of the line reader."""
    from cmcan.io.candump_columns import iter_candump_columns

    sizes = {}
    for name, ident in (("std", "{:03X}"), ("ext", "18FF{:02X}03")):
        lines = [
            f"({1767225600 + i * 0.001:017.6f}) can0 {ident.format(i % 4)}#{i % 65536:04X}00FF00AA00BB\n"
            for i in range(30000)
        ]
        p = tmp_path / f"{name}.log"
        p.write_text("".join(lines))
        with helpers_impl(impl):
            chunks = list(iter_candump_columns(p, chunk_bytes=1 << 17, chunk_lines=4000))
        assert [f for c in chunks for f in c.frames()] == list(iter_candump(p))
        sizes[name] = [len(c) for c in chunks]
    assert sizes["std"][1:-1] and sizes["std"][1:-1] == sizes["ext"][1:-1] == [4000] * len(sizes["std"][1:-1])


def test_error_frames_of_every_class_are_error_frames(tmp_path):
    """candump writes an error frame's class bits with CAN_ERR_FLAG: a controller problem (0x04) or
    bus-off (0x40) is an error frame as much as a bus error (0x80), as the daemon receives them
    (python-can's reader reads the former as frames of identifier 0x4 and 0x40)."""
    from cmcan.io.candump_columns import iter_candump_columns

    p = tmp_path / "err.log"
    p.write_text(
        "(1.000000) can0 20000004#0004000000000000\n"
        "(1.100000) can0 20000040#0000000000000000\n"
        "(1.200000) can0 20000080#0000000000000000\n"
        "(1.300000) can0 100#0011\n"
    )
    lines = list(iter_candump(p))
    cols = [f for c in iter_candump_columns(p) for f in c.frames()]
    assert lines == cols
    assert [f.error for f in lines] == [True, True, True, False]
    assert all(f.arbitration_id == 0 and f.channel == "can0" for f in lines[:3])


@settings(max_examples=40, deadline=None)
@given(
    rows=st.lists(
        st.tuples(
            st.floats(1e9, 2e9),
            st.sampled_from(["can0", "can1", "vcan7"]),
            st.booleans(),
            st.integers(0, 2**29 - 1),
            st.binary(min_size=0, max_size=64).filter(lambda b: len(b) <= 8 or len(b) in (12, 16, 20, 24, 32, 48, 64)),
        ),
        min_size=1,
        max_size=60,
    ),
    one_channel=st.booleans(),
)
def test_write_candump_reads_back_as_written(tmp_path_factory, rows, one_channel):
    """The columns writer (classic and FD frames, one channel or one per frame) gives lines the reader
    takes back to the same frames, the FD ones with ``##``, as candump writes them."""
    import numpy as np

    from cmcan.io.candump import write_candump

    rows = sorted(rows)
    t = np.array([r[0] for r in rows])
    chans = "can3" if one_channel else [r[1] for r in rows]
    ext = np.array([r[2] for r in rows])
    ids = np.array([r[3] if r[2] else r[3] & 0x7FF for r in rows])
    dlc = np.array([len(r[4]) for r in rows])
    data = np.zeros((len(rows), 64), dtype=np.uint8)
    for i, r in enumerate(rows):
        data[i, : len(r[4])] = np.frombuffer(r[4], dtype=np.uint8)
    path = tmp_path_factory.mktemp("w") / "w.log"
    assert write_candump(path, t, ids, dlc, data, channel=chans, extended=ext) == len(rows)
    back = list(iter_candump(path))
    assert [(f.channel, f.arbitration_id, f.extended, f.fd, f.data) for f in back] == [
        ("can3" if one_channel else r[1], int(i), bool(e), len(r[4]) > 8, r[4])
        for r, i, e in zip(rows, ids, ext, strict=True)
    ]
    assert [f"{f.timestamp_s:.6f}" for f in back] == [f"{x:.6f}" for x in t]
