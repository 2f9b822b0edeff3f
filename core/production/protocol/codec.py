"""The channel's typed values as JSON and back.

A value on the channel is a frozen dataclass whose fields are numbers, strings, booleans,
enums, poses and pixel arrays (``Matrix``), tuples and frozensets of them, mappings keyed
by an enum, or other such dataclasses. ``to_json`` turns one into plain JSON;
``from_json(kind, raw)`` turns JSON back into ``kind``, read from the dataclass's own
annotations, so every field is spelled once: in its dataclass. A key the dataclass does not
have is skipped (a newer controller's addition); a key it needs and lacks, or a value of
the wrong shape, raises ``DecodeError`` naming where.

Arrays arrive read-only: a state is shared by every thread of the app that reads it.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from collections.abc import Mapping
from enum import Enum
from typing import Any

import numpy as np

from vservo.core.errors import VservoError


class DecodeError(VservoError, ValueError):
    """JSON that is not the typed value it should be; the message says where."""


def to_json(value: Any) -> Any:
    """``value`` as JSON: dataclasses as objects, enums as their values, arrays and tuples as lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, frozenset | set):
        return [to_json(v) for v in sorted(value, key=_order)]
    if isinstance(value, tuple | list):
        return [to_json(v) for v in value]
    if isinstance(value, Mapping):
        return {str(to_json(k)): to_json(v) for k, v in value.items()}
    return value


def _order(value: Any) -> Any:
    """Enums in the order they are declared, anything else by itself."""
    return list(type(value)).index(value) if isinstance(value, Enum) else value


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def from_json(kind: Any, raw: Any, where: str = "") -> Any:
    """``raw`` read as ``kind`` (a type as annotated: a dataclass, ``float | None``, ``tuple[str, ...]``, ...)."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin in (types.UnionType, typing.Union):
        if raw is None and type(None) in args:
            return None
        (present,) = [a for a in args if a is not type(None)]  # the channel's unions are X | None
        return from_json(present, raw, where)
    if kind is Any:
        return raw
    if origin is np.ndarray:
        return _array(raw, where)
    if origin in (tuple, frozenset, dict):
        return _collection(origin, args, raw, where)
    if isinstance(kind, type):
        if dataclasses.is_dataclass(kind):
            return _dataclass(kind, raw, where)
        if issubclass(kind, Enum):
            try:
                return kind(raw)
            except ValueError:
                raise DecodeError(f"{where or kind.__name__}: {raw!r} is not a {kind.__name__}") from None
        return _scalar(kind, raw, where)
    raise DecodeError(f"{where}: the channel carries no {kind!r}")


def _dataclass(kind: type, raw: Any, where: str) -> Any:
    if not isinstance(raw, dict):
        raise DecodeError(f"{where or kind.__name__}: an object was expected, got {type(raw).__name__}")
    hints = _hints(kind)
    values = {}
    for f in dataclasses.fields(kind):
        if f.name in raw:
            values[f.name] = from_json(hints[f.name], raw[f.name], f"{where}.{f.name}" if where else f.name)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise DecodeError(f"{where or kind.__name__}: {f.name} is missing")
    return kind(**values)


def _collection(origin: Any, args: tuple, raw: Any, where: str) -> Any:
    if origin is dict:
        if not isinstance(raw, dict):
            raise DecodeError(f"{where}: an object was expected, got {type(raw).__name__}")
        key, value = args
        return {from_json(key, k, where): from_json(value, v, f"{where}.{k}") for k, v in raw.items()}
    if not isinstance(raw, list):
        raise DecodeError(f"{where}: a list was expected, got {type(raw).__name__}")
    if origin is frozenset:
        return frozenset(from_json(args[0], v, where) for v in raw)
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(from_json(args[0], v, f"{where}[{k}]") for k, v in enumerate(raw))
    if len(raw) != len(args):
        raise DecodeError(f"{where}: {len(args)} values were expected, got {len(raw)}")
    return tuple(from_json(a, v, f"{where}[{k}]") for k, (a, v) in enumerate(zip(args, raw)))


def _array(raw: Any, where: str) -> np.ndarray:
    try:
        array = np.array(raw, dtype=float)
    except (TypeError, ValueError):
        raise DecodeError(f"{where}: numbers were expected, got {raw!r}") from None
    array.flags.writeable = False
    return array


def _scalar(kind: type, raw: Any, where: str) -> Any:
    if kind is float and isinstance(raw, int | float) and not isinstance(raw, bool):
        return float(raw)
    if kind is not float and isinstance(raw, kind) and not (kind is int and isinstance(raw, bool)):
        return raw
    raise DecodeError(f"{where}: a {kind.__name__} was expected, got {raw!r}")
