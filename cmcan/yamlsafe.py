"""The one way cmcan reads a YAML file: bounded in size, nesting and alias expansion.

Configurations, scenarios, drive files and points specs are a few kB of plain mappings. YAML can say
far more than that in few bytes: an alias bomb (``a: &a [x, x]``, ``b: &b [*a, *a]``, ... nine levels
deep) is a 1 kB file whose value, once walked (validated, printed, compared), has billions of
nodes; a thousand nested brackets exhaust Python's recursion; an anchor used inside itself is a
value that contains itself. PyYAML builds aliases as shared references, so the blow-up happens later,
wherever the value is walked. So the document is measured on the parser's event stream (no recursion,
no value built) before anything is constructed, and refused when it is:

- larger than :data:`MAX_BYTES` (read with a bounded read: a FIFO or ``/dev/zero`` neither blocks nor
  fills memory; only a regular file is read);
- nested deeper than :data:`MAX_DEPTH` mappings and sequences;
- more than :data:`MAX_NODES` nodes or :data:`MAX_CHARS` characters of scalars once every alias
  (and merge key ``<<``, which is an alias) is expanded: the size of the value as any walk sees it;
- using an alias inside the node it names (a recursive value).

A value the safe constructor cannot build (an integer of more than 4300 digits, a 13th month) is an
error naming the line, not an exception from the depths of PyYAML. Each error names the file.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

import yaml

from cmcan.errors import CmcanError, Kind

MAX_BYTES = 1 << 20  # the shipped configuration is about 30 kB; YAML's parser takes a second per MB
MAX_DEPTH = 64  # the deepest cmcan document nests 5 levels
MAX_NODES = 100_000  # nodes after alias expansion: the largest cmcan document has about 1 500
MAX_CHARS = 4 * MAX_BYTES  # scalar characters after alias expansion: 4 times what the file may hold

_Loader: type[Any] = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml when PyYAML was built with it
_OPEN = (yaml.MappingStartEvent, yaml.SequenceStartEvent)
_CLOSE = (yaml.MappingEndEvent, yaml.SequenceEndEvent)


class YamlError(CmcanError):
    """A YAML file cmcan will not read; ``source`` is the file, ``detail`` what is wrong with it."""

    def __init__(self, source: str, detail: str, kind: Kind) -> None:
        super().__init__(f"{source}: {detail}", kind)
        self.source = source
        self.detail = detail


class _Located(Exception):
    """A value the constructor could not build, with its node: where it is and what it claims to be."""

    def __init__(self, node: Any, exc: BaseException) -> None:
        what = str(node.tag).rsplit(":", 1)[-1]
        value = node.value if isinstance(node.value, str) else ""
        why = f" ({exc})" if isinstance(exc, ValueError) else ""
        text = f"{value[:40]!r}{'...' if len(value) > 40 else ''}"
        super().__init__(f"cannot read {text} as {'an' if what[:1] in 'aeiou' else 'a'} {what}{why}")
        self.mark = node.start_mark


class _BoundedLoader(_Loader):  # type: ignore[misc, valid-type]
    """The safe loader; a value its constructors cannot build is reported with its node's line."""

    def construct_object(self, node: Any, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep)
        except (yaml.YAMLError, _Located):
            raise
        except Exception as exc:  # int(), datetime(), base64 of the file's text: the file's fault
            raise _Located(node, exc) from None


def read_bounded(path: str | Path, kind: Kind = Kind.CONFIG, max_bytes: int = MAX_BYTES) -> str:
    """A regular file's text (UTF-8), at most ``max_bytes``; anything else is a YamlError naming it."""
    p = Path(path)
    src = str(p)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise YamlError(src, "file not found", Kind.NO_INPUT) from None
    except IsADirectoryError:
        raise YamlError(src, "is a folder, expected a YAML file", Kind.NO_INPUT) from None
    except PermissionError as exc:
        raise YamlError(src, f"cannot read: {exc.strerror}", Kind.NO_PERMISSION) from None
    except (OSError, ValueError) as exc:  # ENAMETOOLONG, ELOOP, a NUL in the name
        raise YamlError(src, f"cannot read: {getattr(exc, 'strerror', None) or exc}", Kind.NO_INPUT) from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise YamlError(src, "is a folder, expected a YAML file", Kind.NO_INPUT)
        if not stat.S_ISREG(st.st_mode):
            raise YamlError(src, "not a regular file (a device, FIFO or socket), expected a YAML file", kind)
        if st.st_size > max_bytes:
            raise YamlError(src, f"{st.st_size} bytes, more than any YAML file cmcan reads ({max_bytes})", kind)
        chunks, n = [], 0
        while n <= max_bytes and (chunk := os.read(fd, min(1 << 16, max_bytes + 1 - n))):
            chunks.append(chunk)
            n += len(chunk)
    except OSError as exc:
        raise YamlError(src, f"cannot read: {exc.strerror}", Kind.IO_ERROR) from None
    finally:
        os.close(fd)
    if n > max_bytes:  # it grew while being read
        raise YamlError(src, f"more than {max_bytes} bytes, more than any YAML file cmcan reads", kind)
    data = b"".join(chunks)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise YamlError(src, f"not UTF-8 text (byte {exc.start}): expected a YAML file", kind) from None


def measure(text: str, source: str, kind: Kind = Kind.CONFIG) -> tuple[int, int, int]:
    """(nodes, scalar characters, depth) of the document with every alias expanded, from the parser's
    events; raises YamlError as soon as a bound is passed (so a bomb costs what its text costs)."""
    anchors: dict[str, tuple[int, int]] = {}  # anchor -> expanded (nodes, chars), once its node is complete
    stack: list[list[Any]] = []  # open collections: [anchor, nodes, chars, line]
    total = [0, 0]
    depth = 0

    def add(nodes: int, chars: int, mark: Any) -> None:
        acc = stack[-1] if stack else total
        i = 1 if stack else 0
        acc[i] += nodes
        acc[i + 1] += chars
        if acc[i] > MAX_NODES:
            raise YamlError(
                source,
                f"{_at(mark)}more than {MAX_NODES} nodes once its aliases are expanded "
                "(an alias bomb?); no cmcan file is that large",
                kind,
            )
        if acc[i + 1] > MAX_CHARS:
            raise YamlError(
                source,
                f"{_at(mark)}more than {MAX_CHARS} characters of values once its aliases are expanded "
                "(an alias bomb?); no cmcan file is that large",
                kind,
            )

    try:
        for ev in yaml.parse(text, Loader=_Loader):
            if isinstance(ev, _OPEN):
                if len(stack) >= MAX_DEPTH:
                    raise YamlError(source, f"{_at(ev.start_mark)}nested more than {MAX_DEPTH} levels deep", kind)
                if ev.anchor is not None:  # an alias inside this node names this node, not an earlier one
                    anchors.pop(ev.anchor, None)
                stack.append([ev.anchor, 1, 0])
                depth = max(depth, len(stack))
            elif isinstance(ev, _CLOSE):
                anchor, nodes, chars = stack.pop()
                if anchor is not None:
                    anchors[anchor] = (nodes, chars)
                add(nodes, chars, ev.start_mark)
            elif isinstance(ev, yaml.ScalarEvent):
                if ev.anchor is not None:
                    anchors[ev.anchor] = (1, len(ev.value))
                add(1, len(ev.value), ev.start_mark)
            elif isinstance(ev, yaml.AliasEvent):
                size = anchors.get(ev.anchor)
                if size is None:
                    if any(s[0] == ev.anchor for s in stack):
                        raise YamlError(source, f"{_at(ev.start_mark)}alias *{ev.anchor} inside its own node", kind)
                    raise YamlError(source, f"{_at(ev.start_mark)}alias *{ev.anchor} names no anchor before it", kind)
                add(*size, ev.start_mark)
    except yaml.YAMLError as exc:
        raise YamlError(source, _describe(exc), kind) from None
    return total[0], total[1], depth


def loads(text: str, source: str, kind: Kind = Kind.CONFIG) -> Any:
    """The value of one YAML document, measured first (see the module's docstring)."""
    measure(text, source, kind)
    loader = _BoundedLoader(text)
    try:
        return loader.get_single_data()
    except yaml.YAMLError as exc:
        raise YamlError(source, _describe(exc), kind) from None
    except _Located as exc:
        raise YamlError(source, f"{_at(exc.mark)}{exc}", kind) from None
    finally:
        loader.dispose()


def load_file(path: str | Path, kind: Kind = Kind.CONFIG) -> Any:
    """Read and parse a YAML file within the bounds; a YamlError names the file (and line)."""
    return loads(read_bounded(path, kind), str(path), kind)


def _at(mark: Any) -> str:
    return f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""


def _describe(exc: yaml.YAMLError) -> str:
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc)
    return f"invalid YAML: {_at(mark)}{problem}"


__all__ = ["MAX_BYTES", "MAX_CHARS", "MAX_DEPTH", "MAX_NODES", "YamlError", "load_file", "loads", "read_bounded"]
