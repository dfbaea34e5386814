"""The compiled-DBC cache: a command whose DBC has not changed reads it without cantools.

:func:`load_compiled` is what the monitor, the replay, the check and the simulator load a DBC with:
a :class:`cmcan.can.dbcmodel.CompiledDatabase`, from a small JSON file when one was written for
these very bytes, else from cantools through :func:`cmcan.can.dbc.load_dbc` (the same lenient load,
the same problems and log lines), then written for the next start.

An entry is keyed by the SHA-256 of the DBC file's bytes, this module's :data:`FORMAT` and the
version of the cantools that parsed it: an edited DBC, a new cache layout or another cantools is a
miss, never a stale answer. Entries live in ``$CMCAN_CACHE_DIR``, else the service's
``$CACHE_DIRECTORY`` (systemd's ``CacheDirectory=``), else ``$XDG_CACHE_HOME/cmcan``, else
``~/.cache/cmcan`` (under ``dbc/``). They are written through a temporary file renamed into
place (processes racing to write one entry each write a whole file), and read defensively: a file
that is not exactly what :func:`cmcan.can.dbcmodel.from_doc` accepts, or whose body does not match
its own digest, is ignored and rewritten. A cache directory that cannot be created or written is
no error: the DBC is then parsed by cantools at every start, as without a cache.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import stat
import tempfile
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING

from cmcan.can.dbc import dbc_name, file_sha256, load_dbc, load_dbc_digest, message_problems
from cmcan.can.dbcmodel import BadDoc, CompiledDatabase, compile_database, from_doc, to_doc

if TYPE_CHECKING:
    from cantools.database.can import Database

log = logging.getLogger("cmcan.dbc")

# Bump when the document's layout or what cmcan.can.dbc's loader makes of a DBC changes: older
# entries are then misses.
FORMAT = 1
ENV_DIR = "CMCAN_CACHE_DIR"
MAX_ENTRY_BYTES = 64 << 20  # a compiled DBC is some 1-2 % of its text; larger is not an entry
MEMO_MAX = 8  # compiled databases kept per process, by file and content

_memo: OrderedDict[tuple[str, str], CompiledDatabase | Database] = OrderedDict()


def cache_dir() -> Path:
    """Where compiled DBCs are kept: ``$CMCAN_CACHE_DIR``, else systemd's ``$CACHE_DIRECTORY`` (a
    service's ``CacheDirectory=``), else ``$XDG_CACHE_HOME/cmcan``, else ``~/.cache/cmcan``
    (entries under ``dbc/``)."""
    own = os.environ.get(ENV_DIR)
    if own:
        return Path(own)
    systemd = os.environ.get("CACHE_DIRECTORY", "").split(":")[0]  # a service's CacheDirectory=
    if systemd and os.path.isabs(systemd):
        return Path(systemd)
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg and os.path.isabs(xdg):  # the XDG spec: a relative path is to be ignored
        return Path(xdg) / "cmcan"
    return Path.home() / ".cache" / "cmcan"


def cantools_version() -> str:
    """The installed cantools' version, found without importing it (that import is what the cache
    saves): the name of its ``.dist-info`` directory beside the package; else, where there is none,
    its ``__init__.py``'s size and time; "none" when cantools is not installed."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("cantools")
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.origin:
        return "none"
    origin = Path(spec.origin)
    site = origin.parent.parent
    try:
        infos = [n for n in os.listdir(site) if n.startswith("cantools-") and n.endswith(".dist-info")]
    except OSError:
        infos = []
    if len(infos) == 1:
        return infos[0][len("cantools-") : -len(".dist-info")]
    try:
        st = origin.stat()
    except OSError:
        return "unknown"
    return f"unknown-{st.st_size}-{st.st_mtime_ns}"


def entry_name(sha256: str, cantools: str) -> str:
    safe = "".join(c if c.isalnum() or c in ".+-_" else "_" for c in cantools)[:64]
    return f"{sha256}.v{FORMAT}.cantools-{safe}.json"


def load_compiled(path: str | Path | None = None) -> CompiledDatabase | Database:
    """The DBC at ``path`` (default: the shipped one) as cmcan reads it: from the cache when an entry
    for its bytes exists, else parsed by cantools (:func:`cmcan.can.dbc.load_dbc`, DbcError as
    there) and cached. A DBC whose compiled form cannot be cached (beyond the cache's bounds) comes
    back as cantools' database itself."""
    name = dbc_name(path)
    sha = file_sha256(name)
    if sha is None:
        return load_dbc(name)  # DbcError naming the file, as without a cache
    key = (name, sha)
    if key in _memo:
        _memo.move_to_end(key)
        return _memo[key]
    db = _load(name, sha)
    _memo[key] = db
    while len(_memo) > MEMO_MAX:
        _memo.popitem(last=False)
    return db


def _load(name: str, sha: str) -> CompiledDatabase | Database:
    version = cantools_version()
    where = cache_dir() / "dbc" / entry_name(sha, version)
    hit = read_entry(where, name, sha, version)
    if hit is not None:
        for msg, why in sorted(hit.problems.items()):  # what load_dbc logs when it parses the file
            log.info("%s: message %s does not pass cantools' strict check: %s", name, msg, why)
        return hit
    full, parsed = load_dbc_digest(name)
    body = json.dumps(to_doc(compile_database(full, name, sha, message_problems(full))), separators=(",", ":"))
    try:
        # through JSON and back: a miss gives what a hit will (and what cannot be read back is not kept)
        compiled = from_doc(json.loads(body), name, sha)
    except BadDoc as exc:
        log.debug("%s: not cached (%s): read by cantools at each start", name, exc)
        return full
    if parsed == sha:  # else the file changed while it was read: what was parsed is not keyed by sha
        write_entry(where, body, sha, version)
    return compiled


def envelope(body: str, sha: str, version: str) -> str:
    """The file's text: the key it was written for and the digest of its body, then the body."""
    head = {"format": FORMAT, "dbc_sha256": sha, "cantools": version, "body_sha256": _digest(body)}
    return f'{{"key":{json.dumps(head, sort_keys=True)},"body":{body}}}'


def read_entry(where: Path, name: str, sha: str, version: str) -> CompiledDatabase | None:
    """The compiled database in ``where`` when it is a whole, well-formed entry for exactly this key;
    None otherwise (missing, unreadable, truncated, another key, damaged: each a miss)."""
    try:
        fd = os.open(where, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                return None
            raw = f.read(MAX_ENTRY_BYTES + 1)
    except OSError:
        return None
    if len(raw) > MAX_ENTRY_BYTES:
        return _miss(where, "too large")
    try:
        doc = json.loads(raw)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        return _miss(where, f"not JSON: {exc}")
    if not isinstance(doc, dict) or set(doc) != {"key", "body"}:
        return _miss(where, "not an entry")
    want = {"format": FORMAT, "dbc_sha256": sha, "cantools": version}
    key = doc["key"]
    if not isinstance(key, dict) or {k: key.get(k) for k in want} != want:
        return _miss(where, "written for another key")
    # the body's own digest: a file damaged into other valid JSON is refused too
    try:
        same = key.get("body_sha256") == _digest(json.dumps(doc["body"], separators=(",", ":")))
    except (RecursionError, ValueError) as exc:
        return _miss(where, f"{type(exc).__name__}: {exc}")
    if not same:
        return _miss(where, "its body does not match its digest")
    try:
        return from_doc(doc["body"], name, sha)
    except BadDoc as exc:
        return _miss(where, str(exc))
    except (RecursionError, TypeError, ValueError) as exc:  # not reached with from_doc's checks: kept safe
        return _miss(where, f"{type(exc).__name__}: {exc}")


def write_entry(where: Path, body: str, sha: str, version: str) -> bool:
    """The entry written through a temporary file in its directory renamed over ``where`` (a reader
    sees the old file or the new one, whole); False, and nothing said above debug level, when the
    directory cannot be made or written: a cache is an optimisation."""
    text = envelope(body, sha, version).encode("utf-8")
    tmp = None
    try:
        where.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        fd, tmp = tempfile.mkstemp(prefix=f".{where.name}.", suffix=".tmp", dir=where.parent)
        with os.fdopen(fd, "wb") as f:
            f.write(text)
        os.replace(tmp, where)
        return True
    except OSError as exc:
        log.debug("DBC cache %s not written: %s", where, exc)
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        return False


def _digest(body: str) -> str:
    return hashlib.sha256(body.encode("utf-8")).hexdigest()


def _miss(where: Path, why: str) -> None:
    log.debug("DBC cache %s ignored: %s", where, why)
    return None


def clear_memo() -> None:
    """Forget the compiled databases of this process (tests: the next load reads the cache again)."""
    _memo.clear()
