"""Build a rosbags message by name from the fields given, every other field at its ROS default (0, "", false, empty
sequences, nested messages built the same way): the messages rafd writes set a few fields of large types (a Marker
has twenty), and a typo in a field's name is an error, not a silently empty field."""

from __future__ import annotations

from typing import Any

import numpy as np

_NUMPY = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}


def _default(store: Any, node: tuple) -> Any:
    kind, detail = node
    kind = int(kind)
    if kind == 1:  # BASE: (type name, string bound)
        name = detail[0]
        if name == "string":
            return ""
        if name == "bool":
            return False
        return 0.0 if name.startswith("float") else 0
    if kind == 2:  # NAME: a nested message
        return make(store, detail)
    element, count = detail  # ARRAY (3): fixed length, SEQUENCE (4): empty
    if int(element[0]) == 1 and element[1][0] in _NUMPY:
        return np.zeros(count if kind == 3 else 0, dtype=_NUMPY[element[1][0]])
    return [_default(store, element) for _ in range(count)] if kind == 3 else []


def make(store: Any, typename: str, **given: Any) -> Any:
    """A `typename` message of `store` with the `given` fields; TypeError naming a field the type does not have."""
    fields = store.fielddefs[typename][1]
    names = [name for name, _ in fields]
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise TypeError(f"{typename} has no field {', '.join(unknown)}")
    values = {name: given[name] if name in given else _default(store, node) for name, node in fields}
    return store.types[typename](**values)
