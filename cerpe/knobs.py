"""Knobs: the fields of cerpe's configuration tree, each with its meaning and unit.

The method's configuration is one tree of small frozen dataclasses (:class:`Group`), one per phase
(see :mod:`cerpe.method_config`). Every leaf is declared with :func:`knob`, which carries a one-line
description (meaning and unit) and, where it helps, the allowed ``choices`` or bounds; a sub-tree
is declared with :func:`group`. From these declarations alone this module

* checks values when a group is built (types, choices, bounds: one error naming the dotted key);
* lists every knob of a tree (:func:`knobs`), which ``cerpe config show`` prints and
  ``docs/config.md`` is generated from;
* applies dotted overrides (``{"anchors.rot_tol_rad": 0.2}``, :func:`override`) strictly: an unknown
  key is an error that lists the known ones;
* converts a tree to nested dicts and back (:func:`as_dict`, :func:`from_dict`).

A value nobody needs to change is a named constant in its module, not a knob. Nothing here knows
about files, models or the command line.
"""
from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import Any, Iterator, Mapping

from .errors import CerpeError

__all__ = ["KnobError", "Group", "Knob", "knob", "group", "knobs", "count", "override", "as_dict", "from_dict",
           "flatten", "nest"]


class KnobError(CerpeError, ValueError):
    """An unknown key, a value of the wrong type or out of range (names the dotted key)."""


_NUMBER = (int, float)


def knob(default: Any, doc: str, *, choices: tuple | None = None, low: float | None = None,
         high: float | None = None, low_open: bool = False) -> Any:
    """A leaf of the tree: its default, a one-line ``doc`` (meaning and unit), optional checks.

    Args:
        choices: the only values allowed (compared with ``==``).
        low, high: inclusive bounds of a number (``low_open``: ``low`` itself is refused).
    """
    if not doc or not doc.strip():
        raise KnobError("knob: every knob needs a one-line description")
    meta = {"doc": doc.strip(), "choices": choices, "low": low, "high": high, "low_open": low_open}
    return dataclasses.field(default=default, metadata={"knob": meta})


def group(cls: type, doc: str) -> Any:
    """A sub-tree of the configuration: a :class:`Group` subclass, built from its defaults."""
    return dataclasses.field(default_factory=cls, metadata={"group": {"doc": doc.strip()}})


@dataclass(frozen=True)
class Knob:
    """One leaf as listed by :func:`knobs`: dotted path, value, default, type name, description."""

    path: str
    value: Any
    default: Any
    type: str
    doc: str
    choices: tuple | None = None


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _type_name(tp: Any) -> str:
    args = typing.get_args(tp)
    if args:
        return " | ".join(_type_name(a) for a in args)
    return "None" if tp is type(None) else getattr(tp, "__name__", str(tp))


def _accepts(tp: Any, value: Any) -> tuple[bool, Any]:
    """Whether ``value`` fits annotation ``tp``; returns it converted (an int where a float is asked)."""
    args = typing.get_args(tp)
    if args:  # a union, e.g. float | None
        for a in args:
            ok, v = _accepts(a, value)
            if ok:
                return True, v
        return False, value
    if tp is type(None):
        return value is None, value
    if tp is Any:
        return True, value
    if tp is bool:
        return isinstance(value, bool), value
    if tp is int:
        if isinstance(value, bool):
            return False, value
        if isinstance(value, int):
            return True, value
        if isinstance(value, float) and math.isfinite(value) and value == int(value):
            return True, int(value)
        return False, value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, _NUMBER):
            return False, value
        return math.isfinite(float(value)), float(value)
    if tp is str:
        return isinstance(value, str), value
    return isinstance(value, tp), value


@dataclass(frozen=True)
class Group:
    """Base of every group of the tree: checks its knobs when built (see :func:`knob`).

    A subclass may add its own ``check(self)`` for rules between knobs (``tau_k <= tau_m``); it raises
    :class:`KnobError` naming the keys.
    """

    def __post_init__(self) -> None:
        hints = _hints(type(self))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if "group" in f.metadata:
                if isinstance(value, Mapping):  # a dict of the sub-group's knobs
                    object.__setattr__(self, f.name, from_dict(hints[f.name], value, f.name))
                elif not isinstance(value, hints[f.name]):
                    raise KnobError(f"{f.name}: expected a {hints[f.name].__name__} or a mapping of its knobs, "
                                    f"got {type(value).__name__}")
                continue
            meta = f.metadata.get("knob")
            if meta is None:
                continue
            object.__setattr__(self, f.name, _check_value(f.name, hints[f.name], meta, value))
        self.check()

    def check(self) -> None:
        """Rules between this group's knobs (none by default)."""

    def override(self, values: Mapping[str, Any]) -> Any:
        """This tree with ``values`` (dotted keys or nested dicts) applied, checked (:func:`override`)."""
        return override(self, values)


def _check_value(path: str, tp: Any, meta: Mapping[str, Any], value: Any) -> Any:
    choices = meta.get("choices")
    if choices is not None:
        if not any(value == c and type(value) is type(c) for c in choices) and not (
                isinstance(value, _NUMBER) and not isinstance(value, bool) and value in choices):
            raise KnobError(f"{path}: {value!r} is not one of {list(choices)}")
        return value
    ok, v = _accepts(tp, value)
    if not ok:
        raise KnobError(f"{path}: expected {_type_name(tp)}, got {value!r} ({type(value).__name__})")
    if isinstance(v, _NUMBER) and not isinstance(v, bool):
        low, high = meta.get("low"), meta.get("high")
        if low is not None and (v < low or (meta.get("low_open") and v == low)):
            raise KnobError(f"{path}: must be {'>' if meta.get('low_open') else '>='} {low}, got {v!r}")
        if high is not None and v > high:
            raise KnobError(f"{path}: must be <= {high}, got {v!r}")
    return v


def _fields(obj_or_cls: Any) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(obj_or_cls) if "knob" in f.metadata or "group" in f.metadata]


def knobs(tree: Any, prefix: str = "") -> Iterator[Knob]:
    """Every leaf of ``tree`` (an instance, or a class for its defaults), in declaration order."""
    inst = tree() if isinstance(tree, type) else tree
    default = type(inst)()
    hints = _hints(type(inst))
    for f in _fields(inst):
        path = f"{prefix}{f.name}"
        if "group" in f.metadata:
            yield from knobs(getattr(inst, f.name), path + ".")
            continue
        meta = f.metadata["knob"]
        yield Knob(path, getattr(inst, f.name), getattr(default, f.name), _type_name(hints[f.name]), meta["doc"],
                   meta.get("choices"))


def groups(tree: Any, prefix: str = "") -> Iterator[tuple[str, str]]:
    """``(dotted path, description)`` of every sub-group of ``tree``, parents first."""
    inst = tree() if isinstance(tree, type) else tree
    for f in _fields(inst):
        if "group" in f.metadata:
            path = f"{prefix}{f.name}"
            yield path, f.metadata["group"]["doc"]
            yield from groups(getattr(inst, f.name), path + ".")


def count(tree: Any) -> int:
    """The number of knobs of a tree (an instance or a class)."""
    return sum(1 for _ in knobs(tree))


def as_dict(tree: Any) -> dict[str, Any]:
    """The tree as nested dicts of plain values (what ``run.json`` records)."""
    out: dict[str, Any] = {}
    for f in _fields(tree):
        v = getattr(tree, f.name)
        out[f.name] = as_dict(v) if "group" in f.metadata else (list(v) if isinstance(v, tuple) else v)
    return out


def _known(cls: type) -> str:
    return ", ".join(f.name for f in _fields(cls))


def from_dict(cls: type, values: Mapping[str, Any], where: str = "") -> Any:
    """A ``cls`` tree from nested dicts (missing keys keep their defaults; an unknown key is an error)."""
    if not isinstance(values, Mapping):
        raise KnobError(f"{where or cls.__name__}: expected a mapping of knobs, got {type(values).__name__}")
    names = {f.name: f for f in _fields(cls)}
    kwargs: dict[str, Any] = {}
    hints = _hints(cls)
    for key, v in values.items():
        path = f"{where}.{key}" if where else str(key)
        if key not in names:
            raise KnobError(f"unknown key {path!r}; known{' under ' + where if where else ''}: {_known(cls)}")
        if "group" in names[key].metadata:
            kwargs[key] = from_dict(hints[key], v, path) if isinstance(v, Mapping) else v
            if not isinstance(v, Mapping) and not isinstance(v, hints[key]):
                raise KnobError(f"{path}: a group of knobs (known: {_known(hints[key])}), not a value {v!r}")
        else:
            if isinstance(v, Mapping):
                raise KnobError(f"{path}: a single value, not a mapping")
            kwargs[key] = _check_value(path, hints[key], names[key].metadata["knob"], v)
    try:
        return cls(**kwargs)
    except KnobError as exc:
        if where and not str(exc).startswith(where):
            raise KnobError(f"{where}.{exc}") from None
        raise


def flatten(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts -> ``{"a.b": value}``."""
    out: dict[str, Any] = {}
    for k, v in values.items():
        path = f"{prefix}{k}"
        if isinstance(v, Mapping) and v:
            out.update(flatten(v, path + "."))
        else:
            out[path] = v
    return out


def nest(dotted: Mapping[str, Any]) -> dict[str, Any]:
    """``{"a.b": value}`` -> nested dicts (a key given both a value and sub-keys is an error)."""
    out: dict[str, Any] = {}
    for path, v in dotted.items():
        parts = str(path).split(".")
        if not all(p.strip() for p in parts):
            raise KnobError(f"{path!r}: an empty part in a dotted key")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise KnobError(f"{path!r}: {p} was given a value and sub-keys")
        if isinstance(node.get(parts[-1]), dict):
            raise KnobError(f"{path!r}: was given a value and sub-keys")
        node[parts[-1]] = v
    return out


def override(tree: Any, values: Mapping[str, Any]) -> Any:
    """``tree`` with ``values`` (dotted keys, or nested dicts, or both) applied, checked strictly."""
    if not values:
        return tree
    merged = _merge(as_dict(tree), nest(flatten(values)), type(tree), "")
    return from_dict(type(tree), merged)


def _merge(base: dict[str, Any], new: Mapping[str, Any], cls: type, where: str) -> dict[str, Any]:
    names = {f.name: f for f in _fields(cls)}
    hints = _hints(cls)
    out = dict(base)
    for k, v in new.items():
        path = f"{where}.{k}" if where else k
        if k not in names:
            raise KnobError(f"unknown key {path!r}; known{' under ' + where if where else ''}: {_known(cls)}")
        if "group" in names[k].metadata:
            if not isinstance(v, Mapping):
                raise KnobError(f"{path}: a group of knobs (known: {_known(hints[k])}), not a value {v!r}")
            out[k] = _merge(base[k], v, hints[k], path)
        else:
            out[k] = v
    return out
