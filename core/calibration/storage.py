"""Calibration files: numpy arrays and a JSON header in one .npz, written atomically.

Datasets and trained calibrations are both stored this way: one file holds everything
(no array can be separated from the metadata that says what it is), it is replaced in
one step (an interrupted write leaves the old file), and it is read without pickle.
The header names the file's kind and format version; a reader asks for the kind it
expects and gets a ``CalibrationFileError`` naming the file and what is wrong otherwise.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.errors import VservoError
from vservo.core.perception.recording import to_jsonable, write_atomic

FORMAT_VERSION = 1
_HEADER = "header_json"


class CalibrationFileError(VservoError, ValueError):
    """A calibration file that cannot be used; the message names the file and the fault."""


def write_archive(path: str | Path, kind: str, arrays: dict[str, np.ndarray], metadata: dict[str, Any]) -> Path:
    """Store ``arrays`` and ``metadata`` (JSON-able) as a ``kind`` file at ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"kind": kind, "format_version": FORMAT_VERSION, "metadata": to_jsonable(metadata)}
    buffer = io.BytesIO()
    # (numpy's stub fears an array named allow_pickle among the keywords; the names are ours)
    np.savez_compressed(buffer, **arrays, **{_HEADER: np.array(json.dumps(header, allow_nan=False))})  # type: ignore[arg-type]
    write_atomic(path, buffer.getvalue())
    return path


def read_archive(
    path: str | Path, kind: str, error: type[CalibrationFileError] = CalibrationFileError
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The arrays and metadata of a ``kind`` file; ``error`` (a CalibrationFileError, the
    caller's own kind) naming the file and the fault if it is anything else."""
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise error(f"{path}: not a vservo calibration file ({exc})") from None
    if _HEADER not in arrays:
        raise error(f"{path}: not a vservo calibration file (no header)")
    try:
        header = json.loads(str(arrays.pop(_HEADER)))
    except json.JSONDecodeError as exc:
        raise error(f"{path}: corrupt header ({exc})") from None
    if not isinstance(header, dict) or header.get("kind") != kind:
        found = header.get("kind") if isinstance(header, dict) else None
        raise error(f"{path}: holds a {found!r}, not a {kind!r}")
    if header.get("format_version") != FORMAT_VERSION:
        raise error(f"{path}: format version {header.get('format_version')!r}, this vservo reads version {FORMAT_VERSION}")
    metadata = header.get("metadata")
    if not isinstance(metadata, dict):
        raise error(f"{path}: header has no metadata table")
    return arrays, metadata
