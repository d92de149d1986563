"""Small typed helpers for reading YAML configuration with errors that name file and field."""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any, Sequence

import yaml

from .errors import ConfigError


def load_yaml(path: str | Path) -> dict:
    """Load a YAML mapping from ``path``; raise :class:`ConfigError` naming the file on any problem."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(str(path), "", "file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:  # malformed YAML: report line/column from the parser
        mark = getattr(exc, "problem_mark", None)
        pos = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        raise ConfigError(str(path), "", f"malformed YAML{pos}: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(data, dict):
        raise ConfigError(str(path), "", "top level must be a mapping")
    return data


class Fields:
    """Typed accessor over one YAML mapping that reports errors as ``file: field 'a.b[2].c': message``."""

    def __init__(self, data: Any, source: str, prefix: str = ""):
        if not isinstance(data, dict):
            raise ConfigError(source, prefix, f"expected a mapping, got {type(data).__name__}")
        self.data = data
        self.source = source
        self.prefix = prefix

    def _name(self, key: str) -> str:
        return f"{self.prefix}.{key}" if self.prefix else key

    def error(self, key: str, message: str) -> ConfigError:
        return ConfigError(self.source, self._name(key) if key else self.prefix, message)

    def has(self, key: str) -> bool:
        return key in self.data and self.data[key] is not None

    def check_keys(self, allowed: Sequence[str]) -> None:
        """Reject unknown keys (typos would otherwise be silently ignored)."""
        for key in self.data:
            if key not in allowed:
                raise self.error(str(key), f"unknown field (allowed: {', '.join(allowed)})")

    def raw(self, key: str, default: Any = ...) -> Any:
        if key not in self.data or self.data[key] is None:
            if default is ...:
                raise self.error(key, "required field is missing")
            return default
        return self.data[key]

    def sub(self, key: str) -> "Fields":
        return Fields(self.raw(key), self.source, self._name(key))

    def sub_list(self, key: str, default: Any = ...) -> list["Fields"]:
        items = self.raw(key, default)
        if items is default and default is not ...:
            return []
        if not isinstance(items, list):
            raise self.error(key, "expected a list")
        return [Fields(item, self.source, f"{self._name(key)}[{i}]") for i, item in enumerate(items)]

    def str(self, key: str, default: Any = ...) -> str:
        value = self.raw(key, default)
        if value is default and default is not ...:
            return value
        if not isinstance(value, str):
            raise self.error(key, f"expected a string, got {value!r}")
        return value

    def bool(self, key: str, default: Any = ...) -> bool:
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f"expected true/false, got {value!r}")
        return value

    def float(self, key: str, default: Any = ..., lo: float | None = None, hi: float | None = None) -> float:
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(key, f"expected a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.error(key, f"must be finite, got {value}")
        if lo is not None and value < lo:
            raise self.error(key, f"must be >= {lo}, got {value}")
        if hi is not None and value > hi:
            raise self.error(key, f"must be <= {hi}, got {value}")
        return value

    def int(self, key: str, default: Any = ..., lo: int | None = None) -> int:
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {value!r}")
        if lo is not None and value < lo:
            raise self.error(key, f"must be >= {lo}, got {value}")
        return value

    def vec(self, key: str, n: int | None = None, default: Any = ..., positive: bool = False) -> tuple[float, ...]:
        value = self.raw(key, default)
        if value is default and default is not ...:
            return value
        if not isinstance(value, (list, tuple)) or (n is not None and len(value) != n):
            raise self.error(key, f"expected a list of {n if n is not None else 'some'} numbers, got {value!r}")
        out = []
        for v in value:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise self.error(key, f"expected numbers, got {v!r}")
            if not math.isfinite(float(v)):
                raise self.error(key, f"must be finite (NaN/inf given): {value!r}")
            if positive and v <= 0:
                raise self.error(key, f"must be > 0: {value!r}")
            out.append(float(v))
        return tuple(out)


def typed_value(f: Fields, key: str, default: Any, int_lo: int | None = 0, float_lo: float | None = 0.0) -> Any:
    """``f[key]`` typed as a settings field whose default is ``default``: bool, int (>= ``int_lo``), float
    (>= ``float_lo``) or str; a wrong type is a :class:`ConfigError` naming the file and the field."""
    if isinstance(default, bool):
        return f.bool(key)
    if isinstance(default, int):
        return f.int(key, lo=int_lo)
    if isinstance(default, float):
        return f.float(key, lo=float_lo)
    return f.str(key)


def _nested_class(fl) -> type | None:
    """The settings dataclass a field holds (a ``default_factory`` that makes a dataclass), else None."""
    import dataclasses

    if fl.default_factory is dataclasses.MISSING:
        return None
    made = fl.default_factory()
    return type(made) if dataclasses.is_dataclass(made) else None


def dataclass_kwargs(cls, f: Fields, strict: bool = True, skip: Sequence[str] = (), signed: Sequence[str] = (),
                     int_lo: int | None = 0, float_lo: float | None = 0.0) -> dict:
    """The fields of settings dataclass ``cls`` present in ``f``, each typed by its default (:func:`typed_value`):
    the one YAML-to-settings reader of the planner, replanner, baselines and ``--set`` settings. A field holding a
    settings dataclass (a group, e.g. ``PSPRMSettings.scoring``) is read from its own mapping, recursively.
    ``strict``: a key that is not a field is an error (else ignored); ``skip``: fields the caller reads itself;
    ``signed``: float fields that may be negative (also ``metadata={"signed": True}`` on the field). A class may
    set its own bounds with a ``YAML_BOUNDS`` dict (``int_lo``, ``float_lo``)."""
    import dataclasses

    bounds = getattr(cls, "YAML_BOUNDS", {})
    int_lo, float_lo = bounds.get("int_lo", int_lo), bounds.get("float_lo", float_lo)
    fields = {fl.name: fl for fl in dataclasses.fields(cls)}
    if strict:
        for key in f.data:
            if key not in fields:
                home = leaf_paths(cls).get(str(key))
                if home is not None:  # a leaf of a group given at the top: say where it belongs
                    raise f.error(str(key), f"belongs to the '{'.'.join(home[:-1])}' group "
                                            f"({'.'.join(home[:-1])}: {{{key}: ...}})")
                raise f.error(str(key), f"unknown field (allowed: {', '.join(fields)})")
    out = {}
    for key in f.data:
        if key not in fields or key in skip:
            continue
        sub = _nested_class(fields[key])
        if sub is not None:
            out[key] = sub(**dataclass_kwargs(sub, f.sub(key), strict, (), signed, int_lo, float_lo))
            continue
        lo = None if key in signed or fields[key].metadata.get("signed") else float_lo
        out[key] = typed_value(f, key, fields[key].default, int_lo, lo)
    return out


@functools.lru_cache(maxsize=None)
def leaf_paths(cls) -> dict:
    """Every setting of the (possibly nested) settings dataclass ``cls`` by name: its dotted path
    (``"scoring.alpha"``) and, when no other group has a field of that name, its own name (``"alpha"``), each
    mapped to the path as a tuple (``("scoring", "alpha")``). A group's name maps to the whole group."""
    import dataclasses

    out: dict = {}
    nested: dict = {}

    def walk(c, prefix: tuple) -> None:
        for fl in dataclasses.fields(c):
            path = prefix + (fl.name,)
            out[".".join(path)] = path
            if prefix:
                nested.setdefault(fl.name, []).append(path)
            sub = _nested_class(fl)
            if sub is not None:
                walk(sub, path)

    walk(cls, ())
    for name, paths in nested.items():
        if len(paths) == 1 and name not in out:
            out[name] = paths[0]
    return out


def setting_value(obj, name: str) -> Any:
    """The setting ``name`` (its own name or dotted path, :func:`leaf_paths`) of settings dataclass ``obj``."""
    path = leaf_paths(type(obj)).get(name)
    if path is None:
        raise ConfigError("settings", name, f"unknown setting of {type(obj).__name__}")
    for part in path:
        obj = getattr(obj, part)
    return obj


def replace_settings(obj, changes: dict | None = None, **more) -> Any:
    """A copy of settings dataclass ``obj`` with ``changes`` (names or dotted paths, :func:`leaf_paths`; a group's
    name takes a whole group object) applied; ``obj`` is left as it is. Not validated.

    Raises
    ------
    ConfigError
        A name that is not a setting of ``obj``."""
    import dataclasses

    changes = {**(changes or {}), **more}
    if not changes:
        return obj
    paths = leaf_paths(type(obj))
    tree: dict = {}
    for name, value in changes.items():
        path = paths.get(name)
        if path is None:
            raise ConfigError("settings", name, f"unknown setting of {type(obj).__name__} "
                                                f"(a field name or a dotted path such as "
                                                f"{next((k for k in paths if '.' in k), 'group.field')})")
        node = tree
        for part in path[:-1]:
            node = node.setdefault(part, {})
        node[path[-1]] = value

    def apply(o, t: dict):
        kw = {k: (apply(getattr(o, k), v) if isinstance(v, dict) and dataclasses.is_dataclass(getattr(o, k))
                  else v) for k, v in t.items()}
        return dataclasses.replace(o, **kw)

    return apply(obj, tree)
