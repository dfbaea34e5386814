"""Text columns formatted with arrays are what Python's formatting writes, byte for byte."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cmcan.io.textcols import Column, fixed, integers, rows

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
    assert text(fixed(np.array(xs, dtype=float), d)) == [f"{x:.{d}f}" for x in xs]


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
def test_candump_lines_equal_candump_line(frames, channel):
    from cmcan.frame import Frame, FrameColumns
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
    assert candump_lines(FrameColumns.from_frames(fs), channel) == "".join(candump_line(f, channel) for f in fs)
