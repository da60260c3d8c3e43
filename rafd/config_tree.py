"""Configs as trees of frozen dataclasses, read and changed by dotted keys (torch-free).

A config is a frozen dataclass whose fields are plain values (bool, int, float, str, Path, tuples of them, `X | None`)
or configs themselves. Every field has a dotted key from the root (`model.flow.local_radius`, `train.lr`), and
`overridden(config, {"train.lr": "1e-3"})` returns the config with those fields changed: text is parsed by the field's
type (what the command line gives), other values are taken as they are (what Python gives). The changes go into the
config's dict and the tree is rebuilt once, so the dataclasses' checks judge the whole result, not each step (a
backbone's blocks and channels change together).

`from_dict(kind, data)` rebuilds a config from its dict (`dataclasses.asdict`, or JSON of it): an unknown or a
missing key is an error, never silently dropped or defaulted, so a stored config names every field it was made
with.
"""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any, TypeVar

Config = TypeVar("Config")

TRUE, FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")
NONE = ("none", "null")


def is_config(kind: Any) -> bool:
    return isinstance(kind, type) and dataclasses.is_dataclass(kind)


def field_types(kind: type) -> dict[str, Any]:
    """Field name -> its resolved type (the modules write annotations as text: `from __future__ import annotations`)."""
    hints = typing.get_type_hints(kind)
    return {f.name: hints[f.name] for f in dataclasses.fields(kind)}


def from_dict(kind: type[Config], data: Mapping[str, Any]) -> Config:
    """A config of type `kind` from its dict: nested configs from nested dicts, tuples from lists (JSON has no
    tuples), paths from text. ValueError naming the keys that are unknown or missing."""
    types_ = field_types(kind)
    unknown, missing = sorted(set(data) - set(types_)), sorted(set(types_) - set(data))
    if unknown or missing:
        problems = [f"{what} fields {names}" for what, names in (("unknown", unknown), ("missing", missing)) if names]
        raise ValueError(f"{kind.__name__}: {', '.join(problems)}")
    return kind(**{name: _value(types_[name], data[name], name) for name in types_})


def to_dict(config: Any) -> dict[str, Any]:
    """The config's dict with JSON's types: tuples as lists, paths as text."""
    return _jsonable(dataclasses.asdict(config))


def dotted_items(config: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted key, value) of every plain field of the tree, depth first in field order."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            yield from dotted_items(value, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", value


def overridden(config: Config, changes: Mapping[str, Any]) -> Config:
    """`config` with the fields named by dotted keys changed (text parsed by the field's type); ValueError naming a
    key that is no field (with the closest one) or a value its field cannot take."""
    tree = dataclasses.asdict(config)  # type: ignore[call-overload]
    keys = [key for key, _ in dotted_items(config)]
    for key, value in changes.items():
        kind: Any = type(config)
        parent = tree
        for name in key.split(".")[:-1]:
            kind = field_types(kind).get(name) if is_config(kind) else None
            if not is_config(kind) or name not in parent:
                raise ValueError(_unknown(key, keys))
            parent = parent[name]
        name = key.rsplit(".", 1)[-1]
        field_type = field_types(kind).get(name)
        if field_type is None:
            raise ValueError(_unknown(key, keys))
        if is_config(without_none(field_type)):
            fields = ", ".join(k for k in keys if k.startswith(key + "."))
            raise ValueError(f"{key} is a group of settings: set one of its fields ({fields})")
        parent[name] = parse(field_type, value, key) if isinstance(value, str) else value
    try:
        return from_dict(type(config), tree)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{', '.join(changes)}: {error}") from error


def parse_overrides(texts: Iterator[str] | list[str] | tuple[str, ...]) -> dict[str, str]:
    """["model.flow.stride=8", ...] -> {"model.flow.stride": "8", ...}, in order (a key given twice: the last)."""
    changes: dict[str, str] = {}
    for text in texts:
        key, sign, value = text.partition("=")
        if not sign or not key or " " in key:
            raise ValueError(f"{text!r} is not KEY=VALUE (e.g. train.lr=1e-3)")
        changes[key.strip()] = value.strip()
    return changes


def parse(kind: Any, text: str, key: str = "value") -> Any:
    """`text` as a value of type `kind`: bool as true/false (yes/no, on/off, 1/0), None as "none", a tuple as
    comma-separated items (empty: the empty tuple)."""
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        if text.strip().lower() in NONE and type(None) in typing.get_args(kind):
            return None
        kind = without_none(kind)
    if typing.get_origin(kind) is tuple:
        args = typing.get_args(kind)
        items = [item.strip() for item in text.split(",") if item.strip()]
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(parse(args[0], item, key) for item in items)
        if len(items) != len(args):
            raise ValueError(f"{key} takes {len(args)} comma-separated values, got {text!r}")
        return tuple(parse(arg, item, key) for arg, item in zip(args, items))
    if kind is bool:
        lowered = text.strip().lower()
        if lowered not in TRUE + FALSE:
            raise ValueError(f"{key} is true or false, got {text!r}")
        return lowered in TRUE
    if kind in (int, float, str, Path):
        try:
            return kind(text)
        except ValueError as error:
            raise ValueError(f"{key} takes {kind.__name__}, got {text!r}") from error
    raise ValueError(f"{key}: no parser for {kind!r}")


def _value(kind: Any, value: Any, key: str) -> Any:
    """A stored value as the field's type: a config from a dict, a tuple from a list, a path from text."""
    inner = without_none(kind)
    if value is None:
        return None
    if is_config(inner) and isinstance(value, Mapping):
        return from_dict(inner, value)
    if typing.get_origin(inner) is tuple and isinstance(value, (list, tuple)):
        return tuple(value)
    if inner is Path and isinstance(value, str):
        return Path(value)
    return value


def without_none(kind: Any) -> Any:
    """`X | None` -> X; any other type as it is."""
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return kind


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def _unknown(key: str, keys: list[str]) -> str:
    close = difflib.get_close_matches(key, keys, n=1)
    return f"{key} is no setting" + (f"; did you mean {close[0]}?" if close else "")
