"""Cell files written with tomlkit (core/cell/cell_file.py, core/production/commissioned_file.py):
a commissioned file keeps every comment and the layout of its input, and any Unicode
string round-trips through write and load."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import pytest

from vservo.core.cell.cell_file import dumps_cell, update_cell
from vservo.core.cell.config import load_cell, read_cell_data
from vservo.core.production.commissioned_file import write_commissioned_cell

SHIPPED = Path(__file__).resolve().parents[2] / "static" / "cell.toml"
# The values a commissioning changes in the shipped cell (commissioned_file.commissioned_tables).
MEASURED_KEYS = ("principal_point_px", "distortion", "eMc", "cMl", "pose")


def comments_of(text: str) -> list[str]:
    """Every comment of a TOML text, from its '#' to the end of its line (a '#' inside a
    one-line string is none; cell files hold no multi-line strings)."""
    found = []
    for line in text.splitlines():
        quote, escaped = "", False
        for i, char in enumerate(line):
            if quote:
                if escaped:
                    escaped = False
                elif char == "\\" and quote == '"':
                    escaped = True
                elif char == quote:
                    quote = ""
            elif char in "\"'":
                quote = char
            elif char == "#":
                found.append(line[i:].rstrip())
                break
    return found


def is_subsequence(items: list[str], of: list[str]) -> bool:
    rest = iter(of)
    return all(item in rest for item in items)


def measured(tables: dict, data_folder: str = "cell-commissioning") -> dict:
    """The tables as a commissioning leaves them: measured values, a [commissioning] record."""
    new = copy.deepcopy(tables)
    new["camera"]["focal_length_px"] = [812.345678, 811.987654]
    new["camera"]["principal_point_px"] = [321.5, 239.25]
    new["camera"]["distortion"] = [-0.012, 0.0031, 0.0, 0.0, 1e-05]
    new["hand_eye"]["eMc"] = [0.4, -0.2, 0.1, 0.05, -0.02, 0.01]
    new["laser"]["cMl"] = [30.1, 0.2, -0.1, 0.0, -10.05, 0.01]
    new["board"]["pose"] = [-434.2, -30.5, -175.0, 0.3, 0.0, 0.0]
    new["commissioning"] = {
        "nn_file": f"{data_folder}/nn.pt",
        "provenance": {"data_folder": data_folder, "steps": ["camera", "eyes", "laser"], "camera": {"rms_px": 0.12}},
    }
    return new


def test_a_commissioned_file_keeps_every_comment_and_line_of_its_input(tmp_path):
    source = SHIPPED.read_text()
    assert len(comments_of(source)) > 30  # the shipped cell comments nearly every key
    tables = measured(tomllib.loads(source))
    out = write_commissioned_cell(SHIPPED, tables, tmp_path / "cell-commissioned.toml")
    text = out.read_text()
    assert text.startswith(f"# Commissioned from {SHIPPED} by vservo commission, ")
    # Every comment, in its order; every line but the measured values' verbatim, in its order.
    assert is_subsequence(comments_of(source), comments_of(text)), set(comments_of(source)) - set(comments_of(text))
    lines = text.splitlines()
    changed = [line for line in source.splitlines() if line not in lines]
    assert sorted(line.split(" = ")[0] for line in changed) == sorted(MEASURED_KEYS), changed
    assert is_subsequence([line for line in source.splitlines() if line not in changed], lines)
    # A changed value keeps its end-of-line comment.
    assert "eMc = [0.4, -0.2, 0.1, 0.05, -0.02, 0.01]      # camera frame = flange frame, as in the thesis simulation" in lines
    assert tomllib.loads(text) == tables
    assert load_cell(out).nominal.camera.intrinsics.fx == 812.345678


def test_commissioning_a_commissioned_file_again_says_once_where_it_came_from(tmp_path):
    first = write_commissioned_cell(SHIPPED, measured(tomllib.loads(SHIPPED.read_text())), tmp_path / "a.toml")
    again = measured(tomllib.loads(first.read_text()))
    again["hand_eye"]["eMc"] = [0.5, -0.2, 0.1, 0.05, -0.02, 0.01]
    second = write_commissioned_cell(first, again, tmp_path / "b.toml").read_text()
    assert second.count("# Commissioned from ") == 1 and second.startswith(f"# Commissioned from {first} ")
    assert is_subsequence(comments_of(SHIPPED.read_text()), comments_of(second))
    assert tomllib.loads(second) == again


def test_the_shipped_cell_commissioned_by_its_name_keeps_its_comments(tmp_path, monkeypatch):
    """The controller names the shipped cell static/cell.toml, which is no file outside the source tree."""
    monkeypatch.chdir(tmp_path)
    tables, source = read_cell_data()
    assert source == "static/cell.toml" and not Path(source).exists()
    text = write_commissioned_cell(source, measured(tables), tmp_path / "cell-commissioned.toml").read_text()
    assert is_subsequence(comments_of(SHIPPED.read_text()), comments_of(text))


def test_an_unchanged_cell_file_is_written_back_byte_for_byte():
    source = SHIPPED.read_text()
    assert update_cell(source, tomllib.loads(source)) == source


NAMES = ["cell 🤖", "Zelle ö ß, ячейка, 单元", "𝔠𝔢𝔩𝔩 and 🦾🦿", 'quote " backslash \\ tab \t newline \n end', "\x01 \x1f \x7f"]


@pytest.mark.parametrize("name", NAMES)
def test_any_unicode_string_round_trips_through_write_and_load(name, tmp_path):
    """Outside the Basic Multilingual Plane too (the hand-written TOML wrote a surrogate pair there,
    which tomllib refuses)."""
    assert tomllib.loads(dumps_cell({"names": {name: name}})) == {"names": {name: name}}
    out = write_commissioned_cell(SHIPPED, measured(tomllib.loads(SHIPPED.read_text()), name), tmp_path / "cell.toml")
    commissioning = load_cell(out).commissioning
    assert commissioning.provenance["data_folder"] == name
    assert commissioning.nn_path == tmp_path / name / "nn.pt"


@pytest.mark.parametrize(
    "tables, refusal",
    [
        ({"motion": {"speed_mm_s": float("nan")}}, "motion.speed_mm_s: nan has no place"),
        ({"commissioning": {"provenance": {"rms_px": None}}}, "commissioning.provenance.rms_px: cannot write NoneType"),
        ({"robot": {"arm": "\ud83e"}}, "robot.arm: .* is no text"),
        ({"robot": {"poses": [{"x": 1.0}]}}, "robot.poses: cannot write a table inside an array"),
    ],
)
def test_what_a_cell_file_cannot_hold_is_refused_with_its_key(tables, refusal):
    with pytest.raises(ValueError, match=refusal):
        dumps_cell(tables)
