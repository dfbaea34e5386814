"""The daemon's persisted state: one JSON file in the state directory, written atomically, and the
lock that keeps a second daemon off the directory.

Whatever lies in the state directory is untrusted input (whoever can write the directory can put
anything there): every file is opened without following a symbolic link and without blocking (a FIFO
never hangs a start or a reload), refused unless it is a regular file, read up to a bound, parsed with
bounded nesting, and every number in it checked (finite, within +-1e15). A state file is read in four
parts (``PARTS``); a damaged part starts afresh alone, the file is kept aside as
``state.json.corrupt-N`` and the journal says which part, which field and what was expected. Files
are written through a new temporary file in the directory (``O_EXCL``: never through a link someone
left), renamed into place, and given to the directory's owner when root writes them."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import itertools
import json
import logging
import math
import os
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cmcan.errors import CmcanError, Kind, kind_of_oserror
from cmcan.monitor.baseline import BIN_ROLES, MODE_NAMES, N_FEATURES
from cmcan.monitor.baseline import FORMAT as BASELINE_FORMAT
from cmcan.monitor.operating import OperatingClock
from cmcan.monitor.prognosis import FORMAT as PROGNOSIS_FORMAT
from cmcan.monitor.prognosis import Prognosis, PrognosisParams, count
from cmcan.monitor.totals import StateError, Totals
from cmcan.schema import finite_number, integer

log = logging.getLogger("cmcan.state")
STATE_FILE = "state.json"
LOCK_FILE = "cmcan.lock"
NODE_FILE = "j1939-node.json"  # the J1939 node's address claim as the daemon last saw it (uplink health)
# ``cmcan baseline reset`` asks the running daemon through this file and a reload (never two writers)
BASELINE_REQUEST_FILE = "baseline-reset.json"

FILE_MODE = 0o640  # the owner reads and writes, the group reads, others nothing
MAX_STATE_BYTES = 16 << 20  # a state of 1000 level changes and a baseline of 10 000 bins is under 4 MiB
MAX_REQUEST_BYTES = 4096  # a reason of 200 characters, escaped
MAX_NODE_BYTES = 64 << 10
MAX_DEPTH = 64  # a state nests 6 deep
MAX_MAGNITUDE = 1e15  # beyond any count, time (s) or sum cmcan keeps; squares stay far from overflow
_PROGNOSIS_V1 = "cmcan-prognosis/1"  # the first prognosis history: the core begins a new one, and says so
_PROGNOSIS_V2 = "cmcan-prognosis/2"  # laminar sums only: the core reads it on (no orifice sums yet)
_BIN_H = PrognosisParams().bin_h  # the only width cmcan bins the prognosis history by
SIGHUP = 1  # its bit in /proc/PID/status SigCgt (signal N is bit N - 1)

# The parts of a state that start afresh alone: the warning totals (counters, times, level changes,
# condition and ratio filter: one warning machine's record, which only makes sense whole), the J1939
# DTC counts and clears, the on-board baseline, the prognosis. Each: its fields, and what starts afresh.
_FILTER = ("filter_ratios", "filter_leaks")
PARTS: dict[str, tuple[tuple[str, ...], str]] = {
    "totals": (
        ("warning_count", "fault_count", "evaluated_s", "time_in_level_s", "history", "condition", *_FILTER),
        "the warning totals (counters, times, level history, ratio filter)",
    ),
    "dtc": (("dtc_occurrences", "dtc_active", "dtc_clears"), "the J1939 DTC counts and clears"),
    "baseline": (("baseline",), "the baseline (learning afresh; its earlier history too)"),
    "prognosis": (("prognosis",), "the prognosis history"),
}
_CLOCK_AFRESH = "the prognosis's operating clock (it goes on from the history's newest hour)"
_REQUIRED = PARTS["totals"][0]  # every state file has these (the others came with later versions)


# -- reading untrusted JSON ------------------------------------------------------------------------


class _Refused:
    """A number a state file may not hold, left where it stood in the parsed document: the check then
    names its field, and a bad number in one part spoils only that part."""

    __slots__ = ("text",)

    def __init__(self, text: str) -> None:
        self.text = text if len(text) <= 24 else f"{text[:16]}... ({len(text)} characters)"

    def __repr__(self) -> str:
        return self.text


def _parse_int(s: str) -> int | _Refused:
    if len(s) > 17:  # longer than any integer within the bound (and no 4300-digit conversion)
        return _Refused(s)
    v = int(s)
    return v if abs(v) <= MAX_MAGNITUDE else _Refused(s)


def _parse_float(s: str) -> float | _Refused:
    v = float(s)  # 1e400 is inf here
    return v if math.isfinite(v) and abs(v) <= MAX_MAGNITUDE else _Refused(s)


def parse_json(raw: bytes) -> Any:
    """A document from untrusted bytes: UTF-8, JSON, nested at most as deep as Python's reader goes
    (deeper raises ``ValueError``, not ``RecursionError``); numbers out of range, NaN and Infinity
    are left as :class:`_Refused` for :func:`first_refused` to name."""
    text = raw.decode("utf-8")
    try:
        return json.loads(text, parse_int=_parse_int, parse_float=_parse_float, parse_constant=_Refused)
    except RecursionError:  # the C reader stops at the interpreter's recursion limit, cleanly
        raise ValueError(f"nested deeper than {MAX_DEPTH} levels") from None


def first_refused(value: Any, name: str) -> str | None:
    """The first thing under ``value`` a state file may not hold: a number out of range (or NaN, or
    Infinity), or nesting deeper than ``MAX_DEPTH``; said with its field's path, or None."""
    stack: list[tuple[Any, Any, int]] = [(value, name, 1)]  # value, its path (built only to be said), depth
    while stack:
        v, where, depth = stack.pop()
        if isinstance(v, _Refused):
            return f"field '{_path(where)}': {v.text} is not a number a state file holds (finite, within +-1e15)"
        if isinstance(v, (dict, list)) and depth > MAX_DEPTH:
            return f"field '{_path(where)}': nested deeper than {MAX_DEPTH} levels"
        if isinstance(v, dict):
            stack.extend((x, (where, f".{k}"), depth + 1) for k, x in reversed(v.items()))
        elif isinstance(v, list):
            stack.extend((x, (where, f"[{i}]"), depth + 1) for i, x in reversed(list(enumerate(v))))
    return None


def _path(where: Any) -> str:
    parts = []
    while isinstance(where, tuple):
        where, step = where
        parts.append(step)
    return where + "".join(reversed(parts))


# -- the state file's parts ------------------------------------------------------------------------


@dataclass(frozen=True)
class Damage:
    """One part of a state file that cannot be used: the part (a key of ``PARTS``, or "file"), what is
    wrong (the field and what was expected) and what starts afresh for it."""

    part: str
    problem: str
    afresh: str


@dataclass(frozen=True)
class Reading:
    """A state file read: the totals to go on with (damaged parts fresh) and what was damaged."""

    totals: Totals
    damage: tuple[Damage, ...] = ()

    @property
    def whole(self) -> bool:
        """Nothing of the file could be used."""
        return any(d.part == "file" for d in self.damage) or {d.part for d in self.damage} >= set(PARTS)

    def afresh(self) -> str:
        """What starts afresh, for people."""
        if self.whole:
            return "fresh totals"
        return "; ".join(d.afresh for d in self.damage) + " (the rest of the state kept)"


def whole_damage(problem: str) -> Reading:
    return Reading(Totals(), (Damage("file", problem, "everything"),))


def examine(raw: bytes) -> Reading:
    """Read a state file's bytes part by part (``PARTS``): each part checked on its own, a damaged one
    fresh, the others kept. Pure: the property tests drive it with any bytes."""
    try:
        doc = parse_json(raw)
    except ValueError as exc:  # not UTF-8, not JSON, nested too deep
        return whole_damage(f"not a readable state file: {exc}")
    fresh = Totals().to_dict()
    if not isinstance(doc, dict) or doc.get("format") != fresh["format"]:
        return whole_damage(f"not a {fresh['format']} document")
    keep = dict(fresh)
    damage = []
    for part, (fields, afresh) in PARTS.items():
        problem, kept = _part(doc, part, fields)
        if problem is not None:  # (something kept of a damaged part: the prognosis without its clock)
            damage.append(Damage(part, problem, _CLOCK_AFRESH if kept else afresh))
        keep.update(kept)
    try:
        return Reading(Totals.from_dict(keep), tuple(damage))
    except StateError as exc:  # parts that are good alone but not together: nothing is kept
        return whole_damage(str(exc))


def _part(doc: dict[str, Any], part: str, fields: tuple[str, ...]) -> tuple[str | None, dict[str, Any]]:
    """What is wrong with one part of ``doc`` (None: nothing) and the fields to go on with (the file's,
    a repaired prognosis without its clock, or none: fresh)."""
    missing = [f for f in fields if f in _REQUIRED and f not in doc]
    if missing:
        return f"field {missing[0]!r} missing", {}
    given = {f: doc[f] for f in fields if f in doc}
    for f, v in given.items():
        if (problem := first_refused(v, f)) is not None:
            return problem, {}
    try:  # the part alone, every other part fresh: Totals' own checks of its fields
        Totals.from_dict({**Totals().to_dict(), **given})
    except StateError as exc:
        return str(exc), {}
    if part == "baseline" and given.get("baseline") is not None:
        problem = _baseline_problem(given["baseline"])
        return (problem, {}) if problem else (None, given)
    if part == "prognosis" and given.get("prognosis") is not None:
        return _prognosis_part(given["prognosis"])
    return None, given


def _baseline_problem(d: dict[str, Any]) -> str | None:
    """A saved baseline checked against its own envelope (the core checks it again against the one
    configured, and learns afresh where the configuration changed it)."""
    if d.get("format") != BASELINE_FORMAT:
        return f"field 'baseline.format': expected {BASELINE_FORMAT!r}, got {d.get('format')!r:.40}"
    env = d.get("envelope")
    edges = env.get("edges") if isinstance(env, dict) else None
    ok = isinstance(edges, list) and len(edges) == len(BIN_ROLES) and all(_rising(e) for e in edges)
    if not (ok and env.get("roles") == list(BIN_ROLES)):  # type: ignore[union-attr]
        return f"field 'baseline.envelope': expected rising bin edges along {', '.join(BIN_ROLES)}, got {env!r:.80}"
    nb = math.prod(len(e) - 1 for e in edges)  # type: ignore[union-attr]
    for name, width, good, what in _BASELINE_ARRAYS:
        v = d.get(name)
        if not (isinstance(v, list) and len(v) == nb):
            got = f"{len(v)}" if isinstance(v, list) else f"{v!r:.40}"
            return f"field 'baseline.{name}': expected {nb} entries (one per bin of its envelope), got {got}"
        for i, row in enumerate(v if width else [v]):
            if not (isinstance(row, list) and (not width or len(row) == width) and all(good(x) for x in row)):
                at = f"[{i}]" if width else ""
                return f"field 'baseline.{name}{at}': expected {width or nb} {what}, got {row!r:.60}"
    return _baseline_scalars(d)


_BASELINE_ARRAYS = (
    ("n", 0, count, "counts"),
    ("sy", 0, finite_number, "finite numbers"),
    ("sxx", N_FEATURES * N_FEATURES, finite_number, "finite numbers"),
    ("sxy", N_FEATURES, finite_number, "finite numbers"),
)


def _rising(e: Any) -> bool:
    return (
        isinstance(e, list)
        and len(e) >= 2
        and all(finite_number(x) for x in e)
        and all(a < b for a, b in itertools.pairwise(e))
    )


def _clock_ok(c: Any) -> bool:
    try:
        OperatingClock.state_from(c, "clock")
    except ValueError:
        return False
    return True


def _baseline_scalars(d: dict[str, Any]) -> str | None:
    theta = d.get("theta")
    checks = (
        ("state", d.get("state") in MODE_NAMES.values(), f"one of {', '.join(MODE_NAMES.values())}"),
        ("theta", isinstance(theta, list) and len(theta) == N_FEATURES and all(map(finite_number, theta)), "3 numbers"),
        ("distance_lpm", finite_number(d.get("distance_lpm")), "a finite number"),
        ("learned_ticks", count(d.get("learned_ticks")), "a count"),
        ("started_t_s", d.get("started_t_s") is None or finite_number(d.get("started_t_s")), "a time or null"),
        ("finished_t_s", d.get("finished_t_s") is None or finite_number(d.get("finished_t_s")), "a time or null"),
        ("block", d.get("block") is None or integer(d.get("block")), "a block number or null"),
        (
            "clock",
            d.get("clock") is None or _clock_ok(d.get("clock")),
            "{operating_s: seconds, last_t_s: seconds or null}",
        ),
        ("history", isinstance(d.get("history", []), list), "a list of records"),
    )
    for name, ok, expected in checks:
        if not ok:
            return f"field 'baseline.{name}': expected {expected}, got {d.get(name)!r:.40}"
    if not all(isinstance(h, dict) for h in d.get("history", [])):
        return "field 'baseline.history': expected a list of records"
    return None


def _prognosis_part(d: dict[str, Any]) -> tuple[str | None, dict[str, Any]]:
    """A saved prognosis: a damaged history starts afresh (clock and all); a damaged clock alone
    goes on from the history's newest hour, as the core does for a history saved without one."""
    problem = _prognosis_problem(d)
    if problem is not None:
        return problem, {}
    c = d.get("clock")
    if c is None:
        return None, {"prognosis": d}
    try:
        OperatingClock.state_from(c, "prognosis.clock")
    except ValueError as exc:
        return str(exc), {"prognosis": {k: v for k, v in d.items() if k != "clock"}}
    return None, {"prognosis": d}


def _prognosis_problem(d: dict[str, Any]) -> str | None:
    fmt = d.get("format")
    if fmt == _PROGNOSIS_V1:
        return None
    if fmt not in (PROGNOSIS_FORMAT, _PROGNOSIS_V2):
        return f"field 'prognosis.format': expected {PROGNOSIS_FORMAT!r}, got {fmt!r:.40}"
    width = len(_POINT) + 1 if fmt == PROGNOSIS_FORMAT else 5
    if d.get("bin_h") != _BIN_H:
        return f"field 'prognosis.bin_h': expected {_BIN_H} (hours per point), got {d.get('bin_h')!r:.40}"
    ref = d.get("reference")
    if not (isinstance(ref, list) and len(ref) == 4 and all(map(finite_number, ref))):
        return f"field 'prognosis.reference': expected [dp, temperature, nu40, nu100], got {ref!r:.60}"
    pts = d.get("points")
    if not isinstance(pts, list):
        return f"field 'prognosis.points': expected a list, got {pts!r:.40}"
    for i, q in enumerate(pts):
        ok = isinstance(q, list) and len(q) == width and count(q[3])
        values = q[:3] + q[4:] if ok else []
        if not (ok and all(finite_number(x) and lo <= x <= hi for x, (lo, hi) in zip(values, _POINT, strict=False))):
            return f"field 'prognosis.points[{i}]': expected [{', '.join(_POINT_TEXT[:width])}], got {q!r:.60}"
        if i and not q[0] > pts[i - 1][0]:
            return f"field 'prognosis.points[{i}]': hour {q[0]!r} after {pts[i - 1][0]!r}: the hours must increase"
    return _open_problem(d.get("open"), pts, width + 1) or _estimate_problem(d)


# What a prognosis point may hold (hour, leakage at the reference conditions in l/min, ratio in %, its
# weight: the bin's sum of squared laminar gains, from the coldest oil to the hottest; in
# cmcan-prognosis/3 also the sums of leak times orifice gain, of both gains' product and of the
# orifice gain squared): beyond, no drive. The sums' consistency the core checks (Prognosis.from_dict).
_POINT = ((0.0, 1e6), (-1e5, 1e5), (-1e4, 1e4), (1e-12, 1e12), (-1e15, 1e15), (0.0, 1e12), (0.0, 1e12))
_POINT_TEXT = (
    "hour 0..1e6",
    "leak +-1e5 l/min",
    "ratio +-1e4 %",
    "ticks",
    "weight 1e-12..1e12",
    "sum_lo +-1e15",
    "sum_ao 0..1e12",
    "sum_oo 0..1e12",
)
_OPEN_TEXT = ("bin", "ticks", "sum_h", "sum_lg", "sum_gg", "sum_ratio", "sum_lo", "sum_ao", "sum_oo")


def _estimate_problem(d: dict[str, Any]) -> str | None:
    """The core's own estimate tried on the saved history (under the default thresholds: they move
    where a curve is cut, not whether the history can be fitted): a history it cannot fit (one that
    lies exactly on a curve: no scatter to weigh the draws by) would stop every start."""
    params = PrognosisParams()
    try:
        with np.errstate(all="ignore"):
            history = Prognosis.from_dict({**d, "reference": Prognosis(params).to_dict()["reference"]}, params)
            if history.points:
                history.estimate()
    except Exception as exc:  # whatever the core cannot make of the history, said, not exit 70
        return f"field 'prognosis.points': no estimate can be made from this history ({type(exc).__name__}: {exc})"
    return None


def _open_problem(op: Any, pts: list[Any], width: int) -> str | None:
    if op is None:
        return None
    ok = isinstance(op, list) and len(op) == width and integer(op[0]) and count(op[1])
    if not (ok and all(finite_number(x) for x in op[2:]) and op[4] >= 0):
        return f"field 'prognosis.open': expected [{', '.join(_OPEN_TEXT[:width])}], got {op!r:.60}"
    if pts and op[0] < math.floor(pts[-1][0] / _BIN_H):
        return f"field 'prognosis.open': bin {op[0]} lies before the last point's"
    return None


_HOW = {True: "unreadable", False: "damaged"}


class DamagedState(StateError):
    """A state file with damaged parts (``cmcan check --state``, ``cmcan baseline``: refused, nothing
    changed). ``on_start`` says what ``cmcan run`` does with it."""

    def __init__(self, path: Path, reading: Reading) -> None:
        super().__init__(f"{path}: " + "; ".join(d.problem for d in reading.damage))
        self.reading = reading
        self.on_start = (
            f"cmcan run would keep it aside as {path.name}.corrupt-N and start with {reading.afresh()}"
            if reading.whole
            else f"cmcan run would keep it aside as {path.name}.corrupt-N and start afresh: {reading.afresh()}"
        )


# -- the store -------------------------------------------------------------------------------------


class StateStore:
    def __init__(self, directory: str | Path) -> None:
        self.dir = Path(directory)
        self.path = self.dir / STATE_FILE

    def check_writable(self) -> str | None:
        """None when the directory can hold the state, else why not."""
        if not self.dir.exists():
            return f"{self.dir}: state directory does not exist"
        if not self.dir.is_dir():
            return f"{self.dir}: not a directory"
        if not os.access(self.dir, os.W_OK | os.X_OK):
            return f"{self.dir}: state directory is not writable by this user"
        return None

    def examine(self) -> Reading | None:
        """The state file read (None: there is none), changing nothing. A file that is there but
        cannot be read (permissions, an I/O error) raises ``StateAccessError``: that is no damage,
        and what the file holds may be perfectly good."""
        try:
            raw = read_limited(self.path, MAX_STATE_BYTES)
        except FileNotFoundError:
            return None
        except NotAFile as exc:
            return whole_damage(f"not a regular file ({exc.what}), expected a state file")
        except TooLarge as exc:
            return whole_damage(f"larger than {exc.limit >> 20} MiB, not a state file")
        except OSError as exc:
            raise StateAccessError(self.path, exc) from None
        return examine(raw)

    def read(self) -> Totals:
        """The saved totals (fresh ones when there is no file), changing nothing; a file with a damaged
        part raises :class:`DamagedState` (a data error) naming the file, the field and what was
        expected of each."""
        reading = self.examine()
        if reading is None:
            return Totals()
        if reading.damage:
            raise DamagedState(self.path, reading)
        return reading.totals

    def load(self) -> Totals:
        """The saved totals for the daemon; a missing file is a fresh start. A file with damaged parts
        is kept aside (``state.json.corrupt-N``), not lost, each damage said in the journal, and only
        the damaged parts start afresh (what was kept is saved at once). A file that cannot be read
        (``StateAccessError``) stops the start: starting afresh would throw the machine's history away
        at the next save, and a restart or a fixed permission brings it back."""
        reading = self.examine()
        if reading is None:
            return Totals()
        if not reading.damage:
            return reading.totals
        aside = self._keep_aside()
        for d in reading.damage:  # one journal line each: the file, the field, what was expected
            then = "starting with fresh totals" if reading.whole else f"starting afresh: {d.afresh}"
            log.error("%s state: %s: %s; kept as %s, %s", _HOW[reading.whole], self.path, d.problem, aside, then)
        if reading.totals != Totals():  # what was kept is on disk at once, not only at the next save
            try:
                self.save(reading.totals)
            except OSError as exc:
                log.error("cannot save the state kept from %s: %s (saved at the next save)", aside, exc)
        return reading.totals

    def _keep_aside(self) -> Path:
        """Rename the file to the first free ``state.json.corrupt-N`` (a link there counts as taken).
        When that fails, the start stops: starting afresh would overwrite it at the next save."""
        n = 1
        while os.path.lexists(candidate := self.dir / f"{STATE_FILE}.corrupt-{n}"):
            n += 1
        try:
            os.rename(self.path, candidate)
        except OSError as exc:
            raise CmcanError(
                f"{self.path}: cannot keep the damaged state file aside as {candidate.name}: {exc.strerror}",
                kind_of_oserror(exc),
            ) from None
        return candidate

    def save(self, totals: Totals) -> None:
        """Write a new temporary file, fsync it, rename it over the old one, fsync the directory: a
        crash or power cut leaves either the old or the new state, never a torn one."""
        write_atomic(self.dir, STATE_FILE, json.dumps(totals.to_dict(), indent=1).encode("utf-8"))


# -- files in the state directory ------------------------------------------------------------------


class NotAFile(OSError):
    """A path that is no regular file (a link, a FIFO, a folder, a device); ``what`` says which."""

    def __init__(self, path: Path, what: str) -> None:
        super().__init__(errno.EINVAL, f"not a regular file ({what})", str(path))
        self.what = what


class TooLarge(OSError):
    def __init__(self, path: Path, limit: int) -> None:
        super().__init__(errno.EFBIG, f"larger than {limit} bytes", str(path))
        self.limit = limit


def read_limited(path: Path, limit: int) -> bytes:
    """The bytes of the regular file at ``path``, at most ``limit``: opened without following a link
    and without blocking (a FIFO must not hang a start or a reload), then checked with ``fstat``.
    Raises ``FileNotFoundError``, :class:`NotAFile`, :class:`TooLarge` or the OSError of the read."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        if exc.errno == errno.ELOOP and os.path.islink(path):
            raise NotAFile(path, "a symbolic link") from None
        raise
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise NotAFile(path, _kind_of(mode))
        chunks, size = [], 0
        while size <= limit and (chunk := os.read(fd, min(1 << 20, limit + 1 - size))):
            chunks.append(chunk)
            size += len(chunk)
        if size > limit:
            raise TooLarge(path, limit)
        return b"".join(chunks)
    finally:
        os.close(fd)


def _kind_of(mode: int) -> str:
    kinds = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"))
    return next((name for test, name in kinds if test(mode)), "a device")


def write_atomic(directory: Path, name: str, data: bytes, durable: bool = True) -> None:
    """``data`` into ``directory/name`` through a new temporary file there (created with O_EXCL, so a
    link left in the directory is never followed), mode 0640, owned by the directory's owner when root
    writes it, renamed over the old file; with ``durable`` fsynced, and the directory after it."""
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=directory)
    try:
        try:
            _owned_like(fd, directory)
            os.fchmod(fd, FILE_MODE)
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
            if durable:
                os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, directory / name)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    if durable:
        dfd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def _owned_like(fd: int, directory: Path) -> None:
    """Root writing into the state directory (``cmcan baseline reset`` with the daemon stopped) gives
    the new file to the directory's owner: a root-owned state file or lock would keep the daemon's
    user out (exit 77, which systemd does not restart)."""
    if os.geteuid() == 0:
        st = os.stat(directory)
        os.fchown(fd, st.st_uid, st.st_gid)


# -- the baseline reset request --------------------------------------------------------------------


REASON_MAX, AT_MAX = 200, 40  # what of a request's reason and time is kept


def write_baseline_request(directory: str | Path, reason: str, at: str) -> Path:
    """Leave a baseline reset for the daemon (written atomically: it reads all of it or nothing)."""
    path = Path(directory) / BASELINE_REQUEST_FILE
    doc = {"reason": reason[:REASON_MAX], "at": at[:AT_MAX]}
    try:
        write_atomic(path.parent, path.name, (json.dumps(doc) + "\n").encode("utf-8"))
    except OSError as exc:
        raise CmcanError(
            f"{path}: cannot leave the request for the daemon: {exc.strerror}", kind_of_oserror(exc)
        ) from None
    return path


def read_baseline_request(directory: str | Path) -> dict[str, str] | None:
    """The reset a ``cmcan baseline reset`` left; None when there is none. A file that is not such a
    request (not a regular file, too large, not JSON, no reason) says so in ``reason`` with ``bad``
    set (remove it with :func:`done_baseline_request`: it must not block later resets). Never blocks,
    never follows a link: the daemon reads it on its loop."""
    path = Path(directory) / BASELINE_REQUEST_FILE
    try:
        doc = parse_json(read_limited(path, MAX_REQUEST_BYTES))
    except FileNotFoundError:
        return None
    except OSError as exc:  # not a regular file, too large, unreadable
        return _bad_request(path, exc.strerror or str(exc))
    except ValueError as exc:  # not UTF-8, not JSON, too deep
        return _bad_request(path, f"not a request: {str(exc)[:80]}")
    if not (isinstance(doc, dict) and isinstance(doc.get("reason"), str) and isinstance(doc.get("at", ""), str)):
        return _bad_request(path, 'not a request: expected {"reason": text, "at": time}')
    return {"reason": _printable(doc["reason"][:REASON_MAX]), "at": _printable(doc.get("at", "")[:AT_MAX])}


def _bad_request(path: Path, why: str) -> dict[str, str]:
    return {"reason": f"unreadable request {path} ({why})", "at": "", "bad": "1"}


def _printable(text: str) -> str:
    """One journal line: control characters (a newline forging a line) as spaces."""
    return "".join(c if c.isprintable() else " " for c in text)


def done_baseline_request(directory: str | Path) -> None:
    """The request carried out and saved (the command waiting for it sees the file go only now); a
    bad one removed so that it blocks no later reset (an empty folder too)."""
    path = Path(directory) / BASELINE_REQUEST_FILE
    with contextlib.suppress(OSError):
        try:
            path.unlink()
        except IsADirectoryError:
            path.rmdir()


def takes_reload(pid: int) -> bool | None:
    """Whether process ``pid`` handles SIGHUP now (its SigCgt in /proc): a daemon between its lock and
    its signal handlers would be killed by one. None: no such process; True where /proc cannot tell."""
    try:
        status = read_limited(Path(f"/proc/{pid}/status"), 1 << 16).decode("ascii", errors="replace")
    except FileNotFoundError:
        return None if Path("/proc/self/status").exists() else True
    except OSError:
        return True
    line = next((x for x in status.splitlines() if x.startswith("SigCgt:")), None)
    if line is None:
        return True
    try:
        caught = int(line.split(":", 1)[1].strip(), 16)
    except ValueError:
        return True
    return bool(caught & 1 << (SIGHUP - 1))


# -- the J1939 node file ---------------------------------------------------------------------------


def write_node_status(directory: str | Path, status: dict[str, object]) -> None:
    """The J1939 node's state (claimed, lost, its address) in the state directory, replaced
    atomically, for ``cmcan uplink``'s health messages and ``cmcan check --state``."""
    data = json.dumps(status, indent=1, default=str).encode("utf-8")
    write_atomic(Path(directory), NODE_FILE, data, durable=False)  # a claim's news, not the machine's history


def read_node_status(directory: str | Path) -> dict[str, object] | None:
    """What :func:`write_node_status` wrote (None: no file, or not one it wrote)."""
    try:
        doc = parse_json(read_limited(Path(directory) / NODE_FILE, MAX_NODE_BYTES))
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) and first_refused(doc, NODE_FILE) is None else None


class StateAccessError(CmcanError):
    """The state file is there but the operating system refused to read it: no permission
    (EACCES, EPERM: e.g. a backup restored as root) or an I/O error (EIO and the like)."""

    def __init__(self, path: Path, exc: OSError) -> None:
        denied = exc.errno in (errno.EACCES, errno.EPERM)
        name = errno.errorcode.get(exc.errno or 0, "")
        why = f"{exc.strerror or exc} ({name})" if name else str(exc.strerror or exc)
        hint = "; the daemon's user needs to read and write it" if denied else ""
        super().__init__(
            f"{path}: cannot read the state file: {why}{hint}; nothing was changed",
            Kind.NO_PERMISSION if denied else Kind.IO_ERROR,
        )
        self.path = path
        self.errno = exc.errno


# -- the lock --------------------------------------------------------------------------------------


class LockHeld(CmcanError):
    """Another process holds a lock cmcan wants (a temporary failure: that one may end)."""


class LockFileError(CmcanError):
    """A lock file that cannot be opened or written; ``strerror`` is the system's reason."""

    def __init__(self, message: str, exc: OSError) -> None:
        super().__init__(f"{message}: {exc.strerror}", kind_of_oserror(exc))
        self.strerror = exc.strerror or str(exc)


class StateLock:
    """An exclusive ``flock`` on ``cmcan.lock`` in the state directory, held for the daemon's life:
    two daemons on one directory would overwrite each other's state. The kernel drops the lock when
    the process ends however it ends (kill -9 included), so a lock file left behind never blocks a
    start; the file says which process holds the lock."""

    def __init__(self, directory: str | Path) -> None:
        self.path = Path(directory) / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> StateLock:
        """Take the lock or raise a temporary failure naming the lock file and the holder's pid."""
        fd = self._open()
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = _read_pid(fd)
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise CmcanError(f"{self.path}: cannot lock: {exc.strerror}", Kind.CANT_CREATE) from None
            who = f"pid {holder}" if holder else "another process"
            raise LockHeld(
                f"{self.path}: the state directory is in use by another cmcan ({who} holds the lock); "
                "one daemon per state directory",
                Kind.TEMPFAIL,
            ) from None
        try:  # the holder's pid, for whoever finds the lock taken
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as exc:
            os.close(fd)
            raise LockFileError(f"{self.path}: cannot write the state lock", exc) from None
        self._fd = fd
        return self

    def _open(self) -> int:
        """The lock file, made here if there is none (given to the directory's owner when root makes
        it), never through a link and never blocking; anything but a regular file is refused."""
        flags = os.O_RDWR | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
        try:
            try:
                fd = os.open(self.path, flags | os.O_CREAT | os.O_EXCL, FILE_MODE)
                _owned_like(fd, self.path.parent)
            except FileExistsError:
                fd = os.open(self.path, flags)
        except OSError as exc:
            raise LockFileError(f"{self.path}: cannot open the state lock", exc) from None
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            os.close(fd)
            raise CmcanError(
                f"{self.path}: not a regular file ({_kind_of(mode)}), expected the state lock", Kind.CANT_CREATE
            )
        return fd

    def holder(self) -> int | None:
        """The pid holding the lock now, or None when nobody does (read-only: for ``cmcan check``)."""
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
        except OSError:
            return None
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                return None
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except OSError:
                return _read_pid(fd) or -1
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        finally:
            os.close(fd)

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", errors="replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() and len(text) < 11 else None
