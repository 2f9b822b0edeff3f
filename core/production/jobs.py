"""An assembly job: what teaching stores and what one-click assembly replays (Figs. C-2, C-3).

A job holds the taught desired image (features, laser depth Z*, the pose estimated from
them), the pose the assembly starts from (the part's area in view), the fixed taught
transform from the servo's end pose to the pick pose (eMe_pick: the vacuum cup meets the
part there), the place pose in the metal part, the check view the placement is measured
from (core/production/placement_check.py; optional: without it a run reports its placement
unknown), and the settings of the run. Poses are
flange poses in the robot base frame, as the JRC reports them.

A job file is JSON with a format tag and version: ``read_job_file`` refuses a foreign or
broken file with a message that names the file and the field. Version 1 files (before
the check view) still read, as jobs without a check view.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import DesiredImage
from vservo.core.perception.recording import write_atomic
from vservo.core.production.placement_check import CheckView
from vservo.core.servo.methods import METHODS

JOB_FORMAT = "vservo-job"
JOB_VERSION = 2
READABLE_VERSIONS = (1, JOB_VERSION)
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


class JobError(ValueError):
    """A job that cannot be used; the message names the job or file and the field."""


@dataclass(frozen=True)
class Job:
    """One taught assembly.

    threshold_px: servo until the feature error is below this (Fig. C-3: 3 px).
    approach_m: how far above the pick and place poses the cup approaches and retreats.
    check: where the placed part is looked at after the release; None: placement unknown.
    placement_tolerance_mm: a run whose part is seen farther than this from its taught
      place ends missed (the shipped metal part's pocket leaves 1 mm each side).
    """

    name: str
    part_side_m: float
    desired: DesiredImage
    start_bMe: Matrix
    eMe_pick: Matrix
    bMe_place: Matrix
    approach_m: float = 0.04
    threshold_px: float = 3.0
    method: str = "laser"
    gain: float = 1.0
    description: str = ""
    taught_bMe: Matrix = field(default_factory=lambda: np.eye(4))  # where the desired image was taken
    check: CheckView | None = None
    placement_tolerance_mm: float = 1.0

    def __post_init__(self) -> None:
        validate_job_name(self.name)

    def as_dict(self) -> dict[str, Any]:
        d = self.desired
        return {
            "format": JOB_FORMAT,
            "version": JOB_VERSION,
            "name": self.name,
            "description": self.description,
            "part_side_m": self.part_side_m,
            "method": self.method,
            "gain": self.gain,
            "threshold_px": self.threshold_px,
            "approach_m": self.approach_m,
            "desired": {
                "corners_px": d.corners_px.tolist(),
                "laser_spot_px": d.laser_spot_px.tolist(),
                "depth_m": d.depth_m,
                "cdMo": d.cdMo.tolist(),
                "corner_depths_m": d.corner_depths_m.tolist(),
            },
            "taught_bMe": self.taught_bMe.tolist(),
            "start_bMe": self.start_bMe.tolist(),
            "eMe_pick": self.eMe_pick.tolist(),
            "bMe_place": self.bMe_place.tolist(),
            "placement_tolerance_mm": self.placement_tolerance_mm,
            "check": None if self.check is None else {
                "check_bMe": self.check.check_bMe.tolist(),
                "corners_px": self.check.corners_px.tolist(),
            },
        }


def validate_job_name(name: object) -> str:
    if not isinstance(name, str) or not NAME_PATTERN.match(name):
        raise JobError(f"job name {name!r}: use 1 to 64 letters, digits, '_', '-' or '.', starting with a letter or digit")
    return name


class _Fields:
    """Reads a job's JSON object; every failure names the source and the field."""

    def __init__(self, data: Any, source: str) -> None:
        if not isinstance(data, dict):
            raise JobError(f"{source}: not a job (a JSON object was expected)")
        self.data, self.source = data, source

    def fail(self, key: str, why: str) -> JobError:
        return JobError(f"{self.source}: {key}: {why}")

    def get(self, key: str) -> Any:
        if key not in self.data:
            raise self.fail(key, "missing")
        return self.data[key]

    def number(self, key: str, positive: bool = True) -> float:
        value = self.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(key, f"{value!r} is not a finite number")
        if positive and value <= 0:
            raise self.fail(key, f"{value!r} must be positive")
        return float(value)

    def array(self, key: str, shape: tuple[int, ...]) -> Matrix:
        value = self.get(key)
        try:
            array = np.array(value, dtype=float)
        except (TypeError, ValueError):
            raise self.fail(key, f"not an array of numbers of shape {shape}") from None
        if array.shape != shape:
            raise self.fail(key, f"shape {array.shape}, expected {shape}")
        if not np.all(np.isfinite(array)):
            raise self.fail(key, "contains NaN or infinite values")
        return array

    def pose(self, key: str) -> Matrix:
        M = self.array(key, (4, 4))
        R = M[:3, :3]
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.isclose(np.linalg.det(R), 1.0, atol=1e-6)
                and np.allclose(M[3], [0, 0, 0, 1])):
            raise self.fail(key, "not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
        return M


def job_from_dict(data: Any, source: str) -> Job:
    f = _Fields(data, source)
    if f.data.get("format") != JOB_FORMAT:
        raise JobError(f"{source}: not a vservo job file (format {f.data.get('format')!r}, expected {JOB_FORMAT!r})")
    version = f.data.get("version")
    if version not in READABLE_VERSIONS:
        raise JobError(f"{source}: job format version {version!r}; this vservo reads versions "
                       f"{', '.join(map(str, READABLE_VERSIONS))}")
    method = f.get("method")
    if method not in METHODS:
        raise f.fail("method", f"{method!r} is not one of {', '.join(METHODS)}")
    desired = _Fields(f.get("desired"), f"{source}: desired")
    description = f.data.get("description", "")
    if not isinstance(description, str):
        raise f.fail("description", "must be text")
    try:
        name = validate_job_name(f.get("name"))
    except JobError as exc:
        raise JobError(f"{source}: {exc}") from None
    return Job(
        name=name,
        description=description,
        part_side_m=f.number("part_side_m"),
        method=method,
        gain=f.number("gain"),
        threshold_px=f.number("threshold_px"),
        approach_m=f.number("approach_m", positive=False),
        desired=DesiredImage(
            corners_px=desired.array("corners_px", (4, 2)),
            laser_spot_px=desired.array("laser_spot_px", (2,)),
            depth_m=desired.number("depth_m"),
            cdMo=desired.pose("cdMo"),
            corner_depths_m=desired.array("corner_depths_m", (4,)),
        ),
        taught_bMe=f.pose("taught_bMe"),
        start_bMe=f.pose("start_bMe"),
        eMe_pick=f.pose("eMe_pick"),
        bMe_place=f.pose("bMe_place"),
        **(_check_fields(f, source) if version >= 2 else {}),
    )


def _check_fields(f: _Fields, source: str) -> dict[str, Any]:
    """What version 2 added: the placement tolerance and the check view (null: none taught)."""
    check = f.get("check")
    if check is not None:
        view = _Fields(check, f"{source}: check")
        check = CheckView(check_bMe=view.pose("check_bMe"), corners_px=view.array("corners_px", (4, 2)))
    return {"placement_tolerance_mm": f.number("placement_tolerance_mm"), "check": check}


def job_from_json(text: str, source: str) -> Job:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise JobError(f"{source}: not valid JSON ({exc.msg} at line {exc.lineno} column {exc.colno})") from None
    return job_from_dict(data, source)


def read_job_file(path: str | Path) -> Job:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise JobError(f"{path}: no such job file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise JobError(f"{path}: cannot read the job file ({exc})") from None
    return job_from_json(text, str(path))


def write_job_file(job: Job, path: str | Path) -> None:
    write_atomic(Path(path), (json.dumps(job.as_dict(), indent=1) + "\n").encode())
