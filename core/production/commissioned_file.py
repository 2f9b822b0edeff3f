"""The cell file commissioning writes: the input file with the measured model in place of
the nominal one, and a record of how it was measured.

The new file keeps every table of the input (devices, motion, safety, the plant of a
simulated cell) and replaces only what was measured: ``[camera]`` focal lengths (in
pixels, ``focal_length_px``), principal point and distortion; ``[hand_eye] eMc``;
``[laser] cMl``; ``[board] pose``. ``[commissioning]`` names the network's file
(relative to the new file) and holds the provenance: date, data folder, steps, each
step's residuals and verdict, the acceptance check. The input is never overwritten.
"""

from __future__ import annotations

import copy
import os
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.cell.cell_file import update_cell
from vservo.core.cell.config import DEFAULT_CELL, ConfigError, parse_cell, read_cell_bytes
from vservo.core.geometry.spatial import Matrix, pose_from_matrix, pose_to_mm_deg
from vservo.core.perception.recording import write_atomic
from vservo.core.production.commissioning import CommissionResult, Step

# The header a commissioned file starts with (a blank line ends it).
_HEADER_START = "Commissioned from "
_HEADER_NOTE = "[camera], [hand_eye], [laser] and [board] pose hold measured values; [commissioning] says how."


def _pose_mm_deg(aMb: Matrix) -> list[float]:
    return [round(float(v), 6) for v in pose_to_mm_deg(pose_from_matrix(aMb))]


def _json_ready(value: Any) -> Any:
    """A TOML-writable copy: no None (TOML has none), numpy scalars as Python numbers."""
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value if v is not None]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def commissioned_tables(
    tables: dict[str, Any], result: CommissionResult, out_path: Path, data_folder: Path, steps: list[Step]
) -> dict[str, Any]:
    """The input cell file's tables with what ``result`` measured (module docstring)."""
    new = copy.deepcopy(tables)
    model = result.model
    if Step.CAMERA in result.steps:
        k = model.camera.intrinsics
        camera = new.setdefault("camera", {})
        camera["focal_length_px"] = [round(k.fx, 6), round(k.fy, 6)]
        camera["principal_point_px"] = [round(k.u0, 6), round(k.v0, 6)]
        camera["distortion"] = [round(float(v), 9) for v in model.camera.distortion.as_opencv()]
    if Step.HAND_EYE in result.steps:
        new.setdefault("hand_eye", {})["eMc"] = _pose_mm_deg(model.eMc)
        new.setdefault("board", {})["pose"] = _pose_mm_deg(result.bMboard)
    if Step.LASER in result.steps:
        new.setdefault("laser", {})["cMl"] = _pose_mm_deg(model.laser.cMl)
    record: dict[str, Any] = {}
    if result.nn_path is not None:
        record["nn_file"] = os.path.relpath(result.nn_path.resolve(), out_path.resolve().parent)
    record["provenance"] = _json_ready(
        {
            "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "data_folder": str(data_folder),
            "steps": [str(s) for s in steps],
            "wall_time_s": round(result.wall_time_s, 1),
            "cell_time_s": round(result.cell_time_s, 1),
            **{str(step): r.as_dict() for step, r in result.steps.items()},
            **({"acceptance": result.acceptance} if result.acceptance else {}),
        }
    )
    new["commissioning"] = record
    return new


def write_commissioned_cell(input_path: str | Path, tables: dict[str, Any], out_path: str | Path) -> Path:
    """Write the new cell file atomically: the input file's text holding ``tables``, so its
    comments and layout stay (cell_file.update_cell), under a header saying where it came
    from. Refuse to overwrite the input, and check that what was written reads back as a
    cell file."""
    out = Path(out_path)
    if Path(input_path).resolve() == out.resolve():
        raise ConfigError(f"--out {out}: that is the input cell file; commissioning writes a new one")
    header = f"{_HEADER_START}{input_path} by vservo commission, {time.strftime('%Y-%m-%d %H:%M:%S')}.\n{_HEADER_NOTE}"
    text = update_cell(_without_header(_input_text(input_path)), tables, header)
    parse_cell(tomllib.loads(text), str(out), out.parent)
    write_atomic(out, text.encode("utf-8"))
    return out


def _input_text(input_path: str | Path) -> str:
    """The text of the cell file commissioned: a file, or the shipped cell by the name it is
    loaded under (config.read_cell_bytes)."""
    shipped = str(input_path) == f"static/{DEFAULT_CELL}" and not Path(input_path).is_file()
    raw, _ = read_cell_bytes(None if shipped else input_path)
    return raw.decode("utf-8")


def _without_header(text: str) -> str:
    """The text without the header of an earlier commissioning: a commissioned cell
    commissioned again says where it came from once."""
    if not text.startswith(f"# {_HEADER_START}"):
        return text
    _, blank, rest = text.partition("\n\n")
    return rest if blank else ""
