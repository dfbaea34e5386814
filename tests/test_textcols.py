"""Text columns formatted with arrays are what Python's formatting writes, byte for byte."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.io.textcols import Column, fixed, integers, rows
from tests.helpers import IMPLS, helpers_impl

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
edge = st.sampled_from(
    [
        0.0,
        -0.0,
        0.5,
        -0.5,
        1.5,
        2.5,
        0.125,
        0.0005,
        -0.0005,
        0.00049999,
        1e15,
        -1e15,
        9.9995,
        99.995,
        1767225600.1,
        1767225600.05,
        1e300,
        -1e-300,
        math.nan,
        math.inf,
        -math.inf,
        2**52,
        2**53 + 1.0,
    ]
)
values = st.lists(
    st.one_of(finite, edge, st.floats(-1e6, 1e6), st.integers(-(10**6), 10**6).map(lambda i: i / 8)),
    min_size=1,
    max_size=60,
)


def text(col: Column) -> list[str]:
    return rows([col], end=b"\n").decode().splitlines()


@settings(max_examples=300, deadline=None)
@given(values, st.integers(0, 6))
def test_fixed_equals_python(xs, d):
    assert text(fixed(np.array(xs, dtype=float), d)) == [py_fixed(x, d) for x in xs]


def py_fixed(x: float, d: int) -> str:
    """Python's own formatting; NaN (a value that is not there) an empty cell."""
    return "" if x != x else f"{x:.{d}f}"


@given(st.lists(st.integers(-(2**62), 2**62), min_size=1, max_size=50))
def test_integers_equal_python(xs):
    assert text(integers(np.array(xs, dtype=np.int64))) == [str(x) for x in xs]


def test_rows_join_fields_and_literals():
    a = fixed(np.array([1.5, -22.25, 333.0]), 2)
    b = Column.of_names(np.array([2, 0, 2]), {0: "ok", 2: "fault"})
    got = rows([a, b",", b, b",x"], end=b"\r\n")
    assert got == b"1.50,fault,x\r\n-22.25,ok,x\r\n333.00,fault,x\r\n"


@settings(max_examples=200, deadline=None)
@given(st.integers(-(10**9), 10**9), st.integers(0, 6), st.integers(-3, 3))
def test_fixed_next_to_a_rounding_boundary(k, d, ulps):
    """Halfway between two d-decimal numbers, and a few ulps either side: where a scaled float could
    round the wrong way."""
    x = (k + 0.5) / 10**d
    for _ in range(abs(ulps)):
        x = math.nextafter(x, math.inf if ulps > 0 else -math.inf)
    xs = [x, -x, x * 1e6, x / 1e3]
    assert text(fixed(np.array(xs), d)) == [f"{v:.{d}f}" for v in xs]


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.one_of(st.floats(1e9, 9.9e9), st.floats(0, 1e12), st.just(1767225600.1)),
            st.integers(0, 0x1FFFFFFF),
            st.booleans(),
            st.binary(min_size=0, max_size=8),
            st.sampled_from(["plain", "plain", "plain", "remote", "fd"]),
        ),
        min_size=1,
        max_size=40,
    ),
    st.sampled_from([None, "can1"]),
)
@pytest.mark.parametrize("impl", IMPLS)
def test_candump_lines_equal_candump_line(impl, frames, channel):
    from cmcan.can.frame import Frame, FrameColumns
    from cmcan.io.candump import candump_line, candump_lines

    fs = [
        Frame(
            t,
            "can0",
            i if ext else i & 0x7FF,
            ext,
            kind == "remote",
            False,
            kind == "fd",
            b"" if kind == "remote" else d,
        )
        for t, i, ext, d, kind in frames
    ]
    with helpers_impl(impl):
        got = candump_lines(FrameColumns.from_frames(fs), channel)
    assert got == "".join(candump_line(f, channel) for f in fs)


# -- the C formatter (cmcan/io/_textcols_fast.c): the same text as Python's formatting --------------


def c_rows(columns, end=b"\n"):
    from cmcan.io import native

    if native.LIB is None:
        pytest.skip("the C helpers are not built here (no C compiler at install)")
    n = len(columns[0].values)
    return native.format_rows(n, columns, end)


@settings(max_examples=300, deadline=None)
@given(values, st.integers(0, 9))
def test_c_fixed_equals_python(xs, d):
    from cmcan.io import native

    got = c_rows([native.TextColumn(native.FIXED, np.array(xs, dtype=float), decimals=d)])
    want = "".join(f"{py_fixed(x, d)}\n" for x in xs)
    # None only for a number written out in full beyond the usual width: the caller formats those rows
    huge = any(math.isfinite(x) and abs(x) >= 2**52 for x in xs)
    assert got == want.encode() or (got is None and huge)


@settings(max_examples=200, deadline=None)
@given(st.integers(-(10**9), 10**9), st.integers(0, 9), st.integers(-3, 3))
def test_c_fixed_next_to_a_rounding_boundary(k, d, ulps):
    from cmcan.io import native

    x = (k + 0.5) / 10**d
    for _ in range(abs(ulps)):
        x = math.nextafter(x, math.inf if ulps > 0 else -math.inf)
    xs = [x, -x, x * 1e6, x / 1e3]
    got = c_rows([native.TextColumn(native.FIXED, np.array(xs), decimals=d)])
    assert got == "".join(f"{v:.{d}f}\n" for v in xs).encode()


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(-(2**63), 2**63 - 1),
            st.integers(0, 3),
            st.integers(0, 0x1FFFFFFF),
            st.booleans(),
            st.binary(min_size=0, max_size=8),
        ),
        min_size=1,
        max_size=40,
    )
)
def test_c_integers_names_and_hex_equal_python(rows_):
    from cmcan.io import native

    names = [b"ok", b"", b"a_longer_name", b"x"]
    rows_ = [(i, w, c if e else c & 0x7FF, e, d) for i, w, c, e, d in rows_]  # a standard id: 11 bits
    ints, which, ids, ext, data = (list(c) for c in zip(*rows_, strict=True))
    payload = np.zeros((len(data), 8), dtype=np.uint8)
    for i, d in enumerate(data):
        payload[i, : len(d)] = np.frombuffer(d, dtype=np.uint8)
    got = c_rows(
        [
            native.TextColumn(native.INT, np.array(ints, dtype=np.int64), b"["),
            native.TextColumn(native.NAME, np.array(which), b",", names=names),
            native.TextColumn(native.HEX_ID, np.array(ids, dtype=np.uint32), b" ", widths=np.array(ext)),
            native.TextColumn(native.HEX_DATA, payload, b"#", widths=np.array([len(d) for d in data])),
        ],
        end=b"]\r\n",
    )
    want = "".join(
        f"[{i},{names[w].decode()} {(f'{c:08X}' if e else f'{c:03X}')}#{d.hex().upper()}]\r\n"
        for i, w, c, e, d in rows_
    )
    assert got == want.encode()


def test_c_formatter_refuses_what_it_cannot_write():
    from cmcan.io import native

    with pytest.raises(IndexError):
        c_rows([native.TextColumn(native.NAME, np.array([0, 2]), names=[b"a", b"b"])])
    with pytest.raises(ValueError, match="decimals"):
        c_rows([native.TextColumn(native.FIXED, np.array([1.0]), decimals=10)])
    # one number written out in full (1e300 has 301 digits) does not fit a row's usual width
    assert c_rows([native.TextColumn(native.FIXED, np.array([1e300]), decimals=3)]) is None
    assert (
        c_rows([native.TextColumn(native.FIXED, np.array([1e300] + [0.0] * 20), decimals=3)])
        == (f"{1e300:.3f}\n" + "0.000\n" * 20).encode()
    )


@pytest.mark.parametrize("impl", IMPLS)
@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(values.map(lambda v: v[0]), st.floats(-1e9, 1e9)), min_size=1, max_size=30), st.data())
def test_timeline_rows_are_the_same_either_way(tmp_path_factory, impl, rows_, data):
    """The timeline writer's rows by the C formatter or with arrays: the same bytes."""
    from cmcan.monitor.gating import Gate
    from cmcan.monitor.tick import TickColumns
    from cmcan.monitor.warnings import Level, Reason
    from cmcan.replay import TimelineWriter
    from cmcan.roles import MOTOR_SPEED

    n = len(rows_)
    x = np.array([r[0] for r in rows_], dtype=float)
    codes = lambda enum: np.array(data.draw(st.lists(st.sampled_from([int(e) for e in enum]), min_size=n, max_size=n)))  # noqa: E731
    c = TickColumns(
        t_s=np.abs(np.array([r[1] for r in rows_])),
        gate=codes(Gate).astype(np.int8),
        measured=x,
        predicted=x / 1.5,
        whitebox=-x,
        ratio_raw_pct=x / 7,
        ratio_filt_pct=x / 3,
        extra_leak_lpm=x * 0.01,
        filt_valid=np.arange(n) % 2 == 0,
        level=codes(Level).astype(np.int8),
        reason=codes(Reason).astype(np.int8),
        time_below_s=np.abs(x),
    )
    out = {}
    d = tmp_path_factory.mktemp("tl")
    for which in (impl, "numpy"):
        with helpers_impl(which):
            w = TimelineWriter(d / f"{which}.csv", MOTOR_SPEED)
            w.start(float(c.t_s[0]))
            w.ticks(c)
            w.close()
        out[which] = (d / f"{which}.csv").read_bytes()
    assert out[impl] == out["numpy"]
