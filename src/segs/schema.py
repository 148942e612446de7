"""Typed configs: one builder from a config mapping (dict or OmegaConf node) to a dataclass.

Nested dataclass fields are built from nested mappings; unknown keys, missing keys and values of
the wrong kind are ConfigErrors of one line naming the full key. A `renamed` entry turns an old
key into an error naming its new place. Imports nothing of segs but the errors, so every package
(slam included) may use it.
"""
from __future__ import annotations

import dataclasses
import typing
from typing import Any, Mapping

from segs.errors import ConfigError


def build(cls: type, values: Mapping[str, Any] | None, where: str, renamed: Mapping[str, str] | None = None,
          ignore: tuple[str, ...] = ("_target_",)):  # fmt: skip
    """Dataclass `cls` from `values`; `where` is the key prefix in messages (e.g. "model").

    renamed: old dotted key (relative to where) -> its new full key. ignore: keys skipped (Hydra's).
    Fields with a default may be absent; fields without one must be given.
    """
    values = {k: v for k, v in dict(values or {}).items() if k not in ignore}
    _check_renamed(values, where, renamed or {})
    hints = typing.get_type_hints(cls)
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ConfigError(f"{_key(where, unknown[0])}: unknown key; known keys of {where}: {', '.join(names)}")
    out = {}
    for name, f in names.items():
        key = _key(where, name)
        if name not in values:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{key}: missing key")
            continue
        out[name] = _value(hints[name], values[name], key)
    return cls(**out)


def foreign_keys(values: Mapping[str, Any], cls: type, other: type, ignore: tuple[str, ...] = ("_target_",)) -> list[str]:
    """Dotted keys of `values` that `cls` does not have but the sibling config `other` does (e.g.
    SEGS keys an experiment sets, under the plain 3D-GS model of an ablation)."""
    out = []
    own, theirs = _fields(cls), _fields(other)
    for k, v in values.items():
        if k in ignore:
            continue
        if k not in own:
            if k in theirs and _valid(v, theirs[k]):
                out.append(k)
            continue
        if isinstance(v, Mapping) and dataclasses.is_dataclass(own[k]) and dataclasses.is_dataclass(theirs.get(k)):
            out += [f"{k}.{sub}" for sub in foreign_keys(v, own[k], theirs[k])]
    return out


def without(values: Mapping[str, Any], keys: list[str]) -> dict:
    """A copy of values without the dotted keys."""
    out = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in values.items()}
    for key in keys:
        *parents, last = key.split(".")
        node = out
        for p in parents:
            node[p] = dict(node[p])
            node = node[p]
        node.pop(last, None)
    return out


def _valid(value, hint) -> bool:
    """Every key of a (nested) group value is a field of the dataclass hint."""
    if not (isinstance(value, Mapping) and dataclasses.is_dataclass(hint)):
        return True
    fields = _fields(hint)
    return all(k in fields and _valid(v, fields[k]) for k, v in value.items())


def _fields(cls: type) -> dict[str, Any]:
    """field name -> its type (a dataclass for nested groups)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _key(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


def _check_renamed(values: dict, where: str, renamed: Mapping[str, str]) -> None:
    """ConfigError for an old key that is set; a null placeholder (kept in a yaml so that the old
    key still reaches this message from the command line) is dropped from `values`."""
    for old, new in renamed.items():
        *parents, last = old.split(".")
        node = values
        for p in parents:
            if not isinstance(node.get(p), Mapping):
                break
            node[p] = dict(node[p])  # a copy: the caller's mapping is left as it was
            node = node[p]
        else:
            if last in node and node[last] is not None:
                raise ConfigError(f"{_key(where, old)} was renamed: use {new}")
            node.pop(last, None)


def _value(hint, value, key: str):
    """value checked against the field type hint (nested dataclasses built)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is typing.Union or (origin is not None and type(None) in args):  # X | None
        if value is None and type(None) in args:
            return None
        rest = [a for a in args if a is not type(None)]
        return _value(rest[0], value, key) if len(rest) == 1 else value
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}={value!r}: expected a group of keys ({', '.join(f.name for f in dataclasses.fields(hint))})")
        return build(hint, value, key)
    if origin is tuple or hint is tuple:
        if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__iter__"):
            raise ConfigError(f"{key}={value!r}: expected a list")
        return tuple(value)
    expected = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(hint)
    if expected is None:
        return value
    ok = isinstance(value, hint) and not (hint is int and isinstance(value, bool))
    if hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    if not ok:
        raise ConfigError(f"{key}={value!r}: expected {expected}")
    return value
