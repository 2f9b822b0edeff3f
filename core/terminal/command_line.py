"""What every layer's commands share: the parser, argument types, the result printer, ``bench``.

Each layer with commands registers them from its own ``cli.py`` on the subcommands that
``vservo.app.cli.build_parser`` creates.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from typing import Any, NoReturn


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, as every vservo error is."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def positive(kind: type) -> Any:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}") from None
        if not 0 < value < math.inf:  # nan and inf too: a run for ever is no setting
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}")
        return value

    return parse


def bounded(kind: type, low: float, high: float, unit: str = "") -> Any:
    """A number of ``kind`` (int or float) from ``low`` to ``high``: anything else (nan, inf, 1e300,
    a word) is refused in one line naming the range."""
    words = f"a {'whole number' if kind is int else 'number'} from {low:g} to {high:g}{f' {unit}' if unit else ''}"

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {words}, got {text!r}") from None
        if not low <= value <= high:  # nan compares false
            raise argparse.ArgumentTypeError(f"expected {words}, got {text!r}")
        return value

    return parse


TCP_PORT = bounded(int, 0, 65535)  # 0: any free one
CYCLE_PERIOD = bounded(float, 0.0, 10.0, "s")  # the shortest servo cycle a simulated run is slowed to


def seed(text: str) -> int:
    """A random seed: numpy's generators take a non-negative integer."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {text!r}")
    return value


def fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number from 0 to 1, got {text!r}")
    return value


def print_result(result: dict[str, Any], as_json: bool) -> None:
    """One JSON object, or one line per key (a nested table indented under its name)."""
    if as_json:
        print(json.dumps(result))
        return
    for key, value in result.items():
        if isinstance(value, dict):
            print(f"{key}:")
            for inner, inner_value in value.items():
                print(f"  {inner}: {inner_value}")
        else:
            print(f"{key}: {value}")


class BenchCommand:
    """``vservo bench WHAT``: one parser, where each layer adds its WHAT, options and runner.

    Options go on the one parser (their help names the WHAT they serve), so
    ``vservo bench --help`` lists every bench in one place. ``close`` adds the WHAT
    argument once every layer has added its own.
    """

    def __init__(self, parser: argparse.ArgumentParser) -> None:
        self.parser = parser
        self._runs: dict[str, Callable[[argparse.Namespace], int]] = {}
        self._helps: list[str] = []
        parser.add_argument("--seed", type=seed, default=0)
        parser.set_defaults(run=lambda args: self._runs[args.what](args))

    def add(self, what: str, help_text: str, run: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
        """Register ``vservo bench WHAT``; returns the parser to add its options to."""
        self._runs[what] = run
        self._helps.append(f"{what}: {help_text}")
        return self.parser

    def close(self) -> None:
        self.parser.add_argument("--json", action="store_true", help="one JSON object")
        self.parser.add_argument("what", choices=tuple(self._runs), help="; ".join(self._helps))
