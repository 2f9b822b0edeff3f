"""Writing a cell file: TOML text from the tables a cell file is read into, with tomlkit.

Commissioning and the virtual cell write cell files for the controller. ``update_cell``
lays tables over the text of an existing cell file: a value that did not change keeps its
line, a changed one keeps its comment, a new key joins the end of its table and a key the
tables no longer hold is removed, so the integrator's comments and layout survive.
``dumps_cell`` writes tables as a new file. Either way ``tomllib.loads(text) == tables``
(the caller writes the text, atomically), any Unicode string included: a cell file holds
tables, strings, numbers, booleans and arrays of them, and anything else (a NaN, None, an
object, a string that is no text) is refused with the key that holds it.
"""

from __future__ import annotations

import math
from typing import Any

import tomlkit

Tables = dict[str, Any]


def dumps_cell(tables: Tables, header: str = "") -> str:
    """The TOML text of ``tables``, each line of ``header`` first as a comment."""
    return update_cell("", tables, header)


def update_cell(text: str, tables: Tables, header: str = "") -> str:
    """``text``, a cell file, holding ``tables`` instead of its own values (module docstring);
    each line of ``header`` goes first as a comment, a blank line after it."""
    _check(tables, [])
    document = tomlkit.parse(text)
    _lay_over(document, tables)
    comments = "".join(f"# {line}".rstrip() + "\n" for line in header.splitlines())
    body = tomlkit.dumps(document).lstrip("\n")
    return comments + "\n" + body if comments and body else comments + body


def _lay_over(container: dict[str, Any], tables: Tables) -> None:
    """Make ``container`` (a tomlkit document or table) hold ``tables``, touching only what differs."""
    for key in [key for key in container if key not in tables]:
        del container[key]
    for key, value in tables.items():
        old = container.get(key)
        if isinstance(value, dict) and isinstance(old, dict):  # (tomlkit's tables are dicts)
            _lay_over(old, value)
        elif old is None or repr(tomlkit.item(old).unwrap()) != repr(value):
            # (by repr: 6 is not 6.0 in a cell file; an equal value keeps its spelling; a bool is no Item)
            container[key] = value


def _check(value: Any, path: list[str]) -> None:
    """Refuse what a cell file cannot hold, naming the key that holds it."""
    where = ".".join(path)
    if isinstance(value, dict):
        for key, sub in value.items():
            if not isinstance(key, str):
                raise ValueError(f"{where}: key {key!r} is not a string")
            _check_text(key, where)
            _check(sub, [*path, key])
    elif isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{where}: {value!r} has no place in a cell file")
    elif isinstance(value, str):
        _check_text(value, where)
    elif isinstance(value, (list, tuple)):
        for item in value:
            if isinstance(item, dict):
                raise ValueError(f"{where}: cannot write a table inside an array to a cell file")
            _check(item, path)
    elif not isinstance(value, (bool, int, float)):
        raise ValueError(f"{where}: cannot write {type(value).__name__} {value!r} to a cell file")


def _check_text(text: str, where: str) -> None:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError(f"{where}: {text!r} is no text (it holds a lone surrogate)") from None
