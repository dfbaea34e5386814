"""Validation of YAML documents (scenarios, configuration) against small declarative specs.

Every error names the file, the dotted field path and what was expected, e.g.
``scenario.yaml: duty.pump_speed_rpm: expected a number in [800, 3400] rpm, got 9000``.
A field the spec does not know is an error too: a mistyped key must not be silently ignored.
"""

from __future__ import annotations

import difflib
import math
import reprlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from cmcan import yamlsafe
from cmcan.errors import CmcanError, Kind


class SchemaError(CmcanError, ValueError):
    """A document does not match its spec; ``str()`` is the message for the user. A configuration
    error by default; a loader of other documents (scenarios, drive files) sets its own kind."""

    kind = Kind.CONFIG

    def __init__(self, source: str, path: str, message: str, kind: Kind | None = None) -> None:
        self.source = source
        self.path = path
        self.detail = message
        where = f"{source}: {path}: " if path else f"{source}: "
        super().__init__(where + message, kind)


_REQUIRED = object()


@dataclass(frozen=True)
class Num:
    lo: float = -math.inf
    hi: float = math.inf
    unit: str = ""
    default: Any = _REQUIRED
    integer: bool = False

    def describe(self) -> str:
        kind = "an integer" if self.integer else "a number"
        rng = "" if math.isinf(self.lo) and math.isinf(self.hi) else f" in [{_fmt(self.lo)}, {_fmt(self.hi)}]"
        return f"{kind}{rng}{' ' + self.unit if self.unit else ''}"

    def check(self, value: Any, src: str, path: str) -> float | int | None:
        if value is None and self.default is None:  # an optional field left unset
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SchemaError(src, path, f"expected {self.describe()}, got {show(value)}")
        if self.integer and not float(value).is_integer():
            raise SchemaError(src, path, f"expected {self.describe()}, got {show(value)}")
        if not math.isfinite(value) or not (self.lo <= value <= self.hi):
            raise SchemaError(src, path, f"expected {self.describe()}, got {show(value)}")
        return int(value) if self.integer else float(value)


@dataclass(frozen=True)
class Bool:
    default: Any = _REQUIRED

    def describe(self) -> str:
        return "true or false"

    def check(self, value: Any, src: str, path: str) -> bool:
        if not isinstance(value, bool):
            raise SchemaError(src, path, f"expected true or false, got {show(value)}")
        return value


@dataclass(frozen=True)
class Str:
    default: Any = _REQUIRED
    choices: tuple[str, ...] = ()

    def describe(self) -> str:
        if self.choices:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        return "a string"

    def check(self, value: Any, src: str, path: str) -> str | None:
        if value is None and self.default is None:  # an optional field left unset
            return None
        if not isinstance(value, str) or (self.choices and value not in self.choices):
            raise SchemaError(src, path, f"expected {self.describe()}, got {show(value)}")
        if "\x00" in value:  # no name, path or identifier holds one; the OS and MQTT refuse it
            raise SchemaError(src, path, f"contains a NUL character: {show(value)}")
        return value


@dataclass(frozen=True)
class Seq:
    item: Any
    default: Any = _REQUIRED
    min_len: int = 0
    max_len: int = 10**9

    def describe(self) -> str:
        return f"a list of {self.item.describe()}"

    def check(self, value: Any, src: str, path: str) -> list[Any]:
        if not isinstance(value, list):
            raise SchemaError(src, path, f"expected {self.describe()}, got {show(value)}")
        if not (self.min_len <= len(value) <= self.max_len):
            raise SchemaError(src, path, f"expected between {self.min_len} and {self.max_len} items, got {len(value)}")
        return [self.item.check(v, src, f"{path}[{i}]") for i, v in enumerate(value)]


@dataclass(frozen=True)
class Obj:
    fields: Mapping[str, Any]
    default: Any = _REQUIRED
    # Cross-field rule run after the fields: returns an error message (field path, text) or None.
    rule: Callable[[dict[str, Any]], tuple[str, str] | None] | None = None
    extra: Any = None  # spec for keys not in ``fields`` (a free mapping), or None to reject them

    def describe(self) -> str:
        return "a mapping with keys " + ", ".join(self.fields)

    def check(self, value: Any, src: str, path: str) -> dict[str, Any]:
        if value is None and all(_has_default(s) for s in self.fields.values()):
            value = {}
        if not isinstance(value, dict):
            raise SchemaError(src, path, f"expected a mapping, got {show(value)}")
        out: dict[str, Any] = {}
        for key, raw in value.items():
            sub = _join(path, str(key))
            if key in self.fields:
                out[key] = self.fields[key].check(raw, src, sub)
            elif self.extra is not None:
                out[key] = self.extra.check(raw, src, sub)
            else:
                hint = difflib.get_close_matches(str(key), list(self.fields), n=1)
                known = f"did you mean {hint[0]!r}?" if hint else "known keys: " + ", ".join(self.fields)
                raise SchemaError(src, sub, f"unknown field ({known})")
        for key, spec in self.fields.items():
            if key in out:
                continue
            if not _has_default(spec):
                raise SchemaError(src, _join(path, key), f"missing; expected {spec.describe()}")
            out[key] = _default_of(spec, src, _join(path, key))
        if self.rule is not None:
            problem = self.rule(out)
            if problem is not None:
                sub, message = problem
                raise SchemaError(src, _join(path, sub), message)
        return out


@dataclass(frozen=True)
class OneOf:
    """A tagged union: the value of ``tag`` picks the spec that checks the whole mapping."""

    tag: str
    variants: Mapping[str, Obj]
    default: Any = _REQUIRED

    def describe(self) -> str:
        return f"a mapping with {self.tag!r} one of " + ", ".join(repr(k) for k in self.variants)

    def check(self, value: Any, src: str, path: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise SchemaError(src, path, f"expected {self.describe()}, got {show(value)}")
        kind = value.get(self.tag)
        if kind not in self.variants:
            raise SchemaError(
                src,
                _join(path, self.tag),
                "expected one of " + ", ".join(repr(k) for k in self.variants) + f", got {show(kind)}",
            )
        spec = self.variants[kind]
        fields = {self.tag: Str(choices=(kind,)), **spec.fields}
        return Obj(fields, rule=spec.rule).check(value, src, path)


@dataclass(frozen=True)
class Either:
    """The first of ``options`` that accepts the value (e.g. ``any`` or a list of addresses)."""

    options: tuple[Any, ...]
    default: Any = _REQUIRED

    def describe(self) -> str:
        return " or ".join(o.describe() for o in self.options)

    def check(self, value: Any, src: str, path: str) -> Any:
        for o in self.options:
            try:
                return o.check(value, src, path)
            except SchemaError:
                continue
        raise SchemaError(src, path, f"expected {self.describe()}, got {show(value)}")


@dataclass(frozen=True)
class Any_:
    default: Any = _REQUIRED

    def describe(self) -> str:
        return "any value"

    def check(self, value: Any, src: str, path: str) -> Any:
        return value


# -- settings declared once -------------------------------------------------------------------------
#
# A setting is declared once, as a field of the typed section that the core receives (a frozen
# dataclass such as the prognosis's parameters): its name, its spec (type, range, unit, default) and
# one line of docs. The YAML section's validation (:func:`section`), the values read from it
# (:func:`values_of`) and the configuration reference (:func:`reference`) are derived from it.


@dataclass(frozen=True)
class Setting:
    spec: Any  # Num, Bool, Str, Seq, ...: the type, range, unit and default
    doc: str  # one line for the configuration reference
    path: str = ""  # its dotted place in the YAML section when not the field's name


def finite_number(x: Any) -> bool:
    """A JSON number that is a finite float or int (not a bool): what a saved state may hold."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def integer(x: Any) -> bool:
    """An int that is not a bool."""
    return isinstance(x, int) and not isinstance(x, bool)


def setting(spec: Any, doc: str, path: str = "") -> Any:
    """A dataclass field declared as a configuration setting (its default the spec's)."""
    default = spec.default
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata={"setting": Setting(spec, doc, path)})
    return field(default=default, metadata={"setting": Setting(spec, doc, path)})


def settings_of(cls: type) -> list[tuple[str, str, Setting]]:
    """(field name, YAML path within the section, setting) of each setting ``cls`` declares."""
    out = []
    for f in fields(cls):
        st = f.metadata.get("setting")
        if st is not None:
            out.append((f.name, st.path or f.name, st))
    return out


def section(
    cls: type,
    head: Mapping[str, Any] | None = None,
    rule: Callable[[dict[str, Any]], tuple[str, str] | None] | None = None,
) -> Obj:
    """The YAML section of ``cls``'s settings (nested where a path has dots), after the ``head``
    fields that are the section's own (e.g. ``enabled``), with its cross-field ``rule``."""
    tree: dict[str, Any] = dict(head or {})
    for _, path, st in settings_of(cls):
        *parents, leaf = path.split(".")
        node = tree
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = st.spec

    def build(node: dict[str, Any], top: bool) -> Obj:
        specs = {k: build(v, False) if isinstance(v, dict) else v for k, v in node.items()}
        return Obj(specs, default={}, rule=rule if top else None)

    return build(tree, True)


def values_of(cls: type, checked: Mapping[str, Any]) -> dict[str, Any]:
    """``cls``'s settings by field name from a section :func:`section` has checked."""
    out = {}
    for name, path, _ in settings_of(cls):
        v: Any = checked
        for part in path.split("."):
            v = v[part]
        out[name] = v
    return out


def carried(settings: Any, cls: type) -> dict[str, Any]:
    """The settings of a section (an instance of a class that declares them) that ``cls`` takes
    under the same name: what a derived parameter set gets as it is, not copied field by field."""
    taken = {f.name for f in fields(cls)}
    return {name: getattr(settings, name) for name, _, _ in settings_of(type(settings)) if name in taken}


def reference(cls: type, prefix: str, head: Mapping[str, tuple[Any, str]] | None = None) -> list[str]:
    """The configuration reference of a section as Markdown table rows: setting, what it takes,
    default, what it does (``head``: the section's own fields, spec and doc)."""
    rows = [(k, spec, doc) for k, (spec, doc) in (head or {}).items()]
    rows += [(path, st.spec, st.doc) for _, path, st in settings_of(cls)]
    out = ["| setting | takes | default | what it does |", "|---|---|---|---|"]
    for path, spec, doc in rows:
        default = _show_default(spec.default) if _has_default(spec) else "required"
        out.append(f"| `{prefix}.{path}` | {spec.describe()} | {default} | {doc} |")
    return out


def _show_default(v: Any) -> str:
    if v is None:
        return "none"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return _fmt(v)
    return f"`{v}`" if isinstance(v, str) else str(v)


_SHOW = reprlib.Repr()
_SHOW.maxstring = _SHOW.maxother = 80
_SHOW.maxlevel, _SHOW.maxlist, _SHOW.maxdict = 3, 6, 6


def show(value: Any) -> str:
    """A value as an error message quotes it: its repr, cut short (a file's value may be huge)."""
    return _SHOW.repr(value)


def _has_default(spec: Any) -> bool:
    return getattr(spec, "default", _REQUIRED) is not _REQUIRED


def _default_of(spec: Any, src: str, path: str) -> Any:
    default = spec.default
    if isinstance(spec, Obj) and isinstance(default, dict):
        return spec.check(default, src, path)
    if isinstance(default, (list, dict)):
        return type(default)(default)
    return default


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def load_yaml(path: str | Path, kind: Kind = Kind.CONFIG) -> Any:
    """Read a YAML file within cmcan's bounds (:mod:`cmcan.yamlsafe`: size, nesting, alias expansion);
    a missing file, a syntax error or a bound passed names the file (and line)."""
    try:
        return yamlsafe.load_file(path, kind)
    except yamlsafe.YamlError as exc:
        raise SchemaError(exc.source, "", exc.detail, exc.kind) from None


__all__ = [
    "Any_",
    "Bool",
    "Either",
    "Num",
    "Obj",
    "OneOf",
    "SchemaError",
    "Seq",
    "Setting",
    "Str",
    "carried",
    "load_yaml",
    "reference",
    "section",
    "setting",
    "settings_of",
    "show",
    "values_of",
]
