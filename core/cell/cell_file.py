"""Writing a cell file: TOML text from the tables a cell file is read into.

Commissioning and the virtual cell write cell files for the controller. Python reads
TOML (tomllib) but does not write it, and a cell file needs only a little of TOML:
tables, nested tables, strings, numbers, booleans and flat arrays of them. ``dumps_cell``
writes exactly that (the caller writes the text, atomically), so ``tomllib.loads(dumps_cell(tables)) == tables``; anything else is
refused with the key that holds it.
"""

from __future__ import annotations

import json
import math
from typing import Any

Tables = dict[str, Any]


def dumps_cell(tables: Tables, header: str = "") -> str:
    """The TOML text of ``tables``, each comment line of ``header`` first."""
    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    _write_table(tables, [], lines)
    return "\n".join(lines).strip("\n") + "\n"


def _write_table(table: Tables, path: list[str], lines: list[str]) -> None:
    values = {k: v for k, v in table.items() if not isinstance(v, dict)}
    if path and (values or not any(isinstance(v, dict) for v in table.values())):
        lines += ["", f"[{'.'.join(_key(p) for p in path)}]"]
    lines += [f"{_key(k)} = {_value(v, [*path, k])}" for k, v in values.items()]
    for key, sub in table.items():
        if isinstance(sub, dict):
            _write_table(sub, [*path, key], lines)


def _key(key: str) -> str:
    return key if key.replace("_", "").replace("-", "").isalnum() and key.isascii() else json.dumps(key)


def _value(value: Any, path: list[str]) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{'.'.join(path)}: {value!r} has no place in a cell file")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(v, path) for v in value) + "]"
    raise ValueError(f"{'.'.join(path)}: cannot write {type(value).__name__} {value!r} to a cell file")
