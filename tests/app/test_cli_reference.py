"""docs/cli.md names every command and option of `vservo`, and nothing else.

The live side is the argparse parser the console script runs (vservo.app.cli.build_parser),
walked through its subparsers; the documented side is each "## `vservo ...`" section of
docs/cli.md with the first cell of its table rows. Options of the root parser (--cell) are
accepted after every command too and are documented once, under `vservo`.
"""

import argparse
import re
from pathlib import Path

from vservo.app.cli import build_parser

CLI_REFERENCE = Path(__file__).resolve().parents[2] / "docs" / "cli.md"
HEADING = re.compile(r"^## `(vservo(?: [a-z][a-z0-9-]*)*)`$")
ROW = re.compile(r"^\| `([^` ]+)[^`]*`")

Arguments = dict[str, set[str]]


def parser_arguments(parser: argparse.ArgumentParser, path: str = "vservo", inherited: frozenset[str] = frozenset()) -> Arguments:
    """Command path -> its option strings and positional names, as --help lists them."""
    own = {
        name
        for action in parser._actions
        if not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction))
        for name in (action.option_strings or [action.dest])
    }
    found: Arguments = {path: own - inherited}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, command in action.choices.items():
                found |= parser_arguments(command, f"{path} {name}", inherited or frozenset(own))
    return found


def documented_arguments(text: str) -> Arguments:
    """Command path -> the arguments in the first column of its section's table."""
    found: Arguments = {}
    section = None
    for line in text.splitlines():
        if line.startswith("## "):
            heading = HEADING.match(line)
            section = heading.group(1) if heading else None
            if section is not None:
                assert section not in found, f"docs/cli.md documents `{section}` twice"
                found[section] = set()
        elif section is not None and (row := ROW.match(line)):
            found[section].add(row.group(1))
    return found


def test_documented_arguments_are_read_from_sections_and_rows():
    text = "## `vservo x`\n\n| option | what |\n|---|---|\n| `--a N` | a |\n| `b` {p,q} | b |\n## Other\n| `--c` | c |\n"
    assert documented_arguments(text) == {"vservo x": {"--a", "b"}}


def test_every_command_is_documented_and_every_documented_command_exists():
    live = parser_arguments(build_parser())
    documented = documented_arguments(CLI_REFERENCE.read_text())
    assert sorted(set(live) - set(documented)) == [], "commands missing from docs/cli.md"
    assert sorted(set(documented) - set(live)) == [], "commands in docs/cli.md that vservo does not have"


def test_every_option_is_documented_and_every_documented_option_exists():
    live = parser_arguments(build_parser())
    documented = documented_arguments(CLI_REFERENCE.read_text())
    for command in sorted(set(live) & set(documented)):
        assert sorted(live[command] - documented[command]) == [], f"`{command}` options missing from docs/cli.md"
        assert sorted(documented[command] - live[command]) == [], f"`{command}` options in docs/cli.md it does not have"
