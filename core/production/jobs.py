"""An assembly job: what teaching stores and what one-click assembly replays (Figs. C-2, C-3).

A job holds the taught desired image (features, laser depth Z*, the pose estimated from
them), the pose the assembly starts from (the part's area in view), the fixed taught
transform from the servo's end pose to the pick pose (eMe_pick: the vacuum cup meets the
part there), the place pose in the metal part, the check view the placement is measured
from (core/production/placement_check.py; optional: without it a run reports its placement
unknown), and the settings of the run. Poses are
flange poses in the robot base frame, as the JRC reports them.

Pixels are seen through a camera, a hand-eye transform and a laser: the job records the
cell model it was taught through (``taught_model``), so that a run on a recalibrated cell
can see the same part through the new model (core/production/retarget.py). A job that
locates its part names the pose the camera surveys the table from (``survey_bMe``).

A job file is JSON with a format tag and version: ``read_job_file`` refuses a foreign or
broken file with a message that names the file and the field. Version 1 files (before
the check view) still read, as jobs without a check view; versions 1 and 2 (before the
taught model) as jobs without a taught model, which run as they were taught. The key
``grasp_symmetry`` is optional in every version: a file without it is of a square-faced
part (4); so is ``laser_law``: a file without it runs the robust law.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.cell.config import CellModel
from vservo.core.errors import VservoError
from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import DesiredImage
from vservo.core.perception.recording import write_atomic
from vservo.core.production.grasp import SYMMETRIES
from vservo.core.production.placement_check import CheckView
from vservo.core.production.protocol.commands import (
    APPROACH_M,
    GAIN,
    JOB_NAME,
    JOB_NAME_WORDS,
    PLACEMENT_TOLERANCE_MM,
    POSE_TRANSLATION_M,
    THRESHOLD_PX,
)
from vservo.core.servo.methods import METHODS, LaserLaw

JOB_FORMAT = "vservo-job"
JOB_VERSION = 3
READABLE_VERSIONS = (1, 2, JOB_VERSION)


class JobError(VservoError, ValueError):
    """A job that cannot be used; the message names the job or file and the field."""


@dataclass(frozen=True, eq=False)
class TaughtModel:
    """The cell model a job's pixels were seen through: the camera (intrinsics, image size,
    distortion), the hand-eye transform eMc and the laser's pose cMl in the camera. The
    vacuum cup's eMv is not part of it: the pick is taught by moving the flange, not
    through the cup's model."""

    camera: CameraModel
    eMc: Matrix
    cMl: Matrix
    # Whether the model was the cell's own, measured (CellConfig.model_measured), when the job
    # was taught: then the pixels are of a known camera and any commissioned cell can see them
    # through its own; else they are of the cell they were taught on, whose true camera nobody knows.
    measured: bool = False

    # Tight enough that only the very model matches (a JSON round trip is exact), loose
    # enough that float noise in a model read from a cell file does not count as a change.
    PIXEL_TOLERANCE = 1e-6
    TOLERANCE = 1e-9

    @classmethod
    def of(cls, model: CellModel, measured: bool = False) -> TaughtModel:
        return cls(model.camera, np.array(model.eMc, dtype=float), np.array(model.laser.cMl, dtype=float), measured)

    def matches(self, model: CellModel) -> bool:
        """Whether ``model`` is this one: same image size, intrinsics to 1e-6 px, distortion,
        eMc and cMl to 1e-9."""
        mine, theirs = self.camera, model.camera
        if mine.image_size != theirs.image_size:
            return False
        k, k2 = mine.intrinsics, theirs.intrinsics
        return (
            np.allclose([k.fx, k.fy, k.u0, k.v0], [k2.fx, k2.fy, k2.u0, k2.v0], rtol=0, atol=self.PIXEL_TOLERANCE)
            and np.allclose(mine.distortion.as_opencv(), theirs.distortion.as_opencv(), rtol=0, atol=self.TOLERANCE)
            and np.allclose(self.eMc, model.eMc, rtol=0, atol=self.TOLERANCE)
            and np.allclose(self.cMl, model.laser.cMl, rtol=0, atol=self.TOLERANCE)
        )

    def as_dict(self) -> dict[str, Any]:
        k = self.camera.intrinsics
        return {
            "camera": {
                "fx_px": k.fx,
                "fy_px": k.fy,
                "principal_point_px": [k.u0, k.v0],
                "image_size_px": [k.width, k.height],
                "distortion": self.camera.distortion.as_opencv().tolist(),
            },
            "eMc": self.eMc.tolist(),
            "cMl": self.cMl.tolist(),
            "measured": self.measured,
        }


@dataclass(frozen=True)
class Job:
    """One taught assembly.

    threshold_px: servo until the feature error is below this. Fig. C-3 stops at 3 px; at
      the desired 162 mm a pixel is about 0.2 mm on the part, and 3 px left parts up to
      0.33 mm off centre, so the default is 1 px.
    approach_m: how far above the pick and place poses the cup approaches and retreats.
    check: where the placed part is looked at after the release; None: placement unknown.
    placement_tolerance_mm: a run whose part is seen farther than this from its taught
      place ends missed (the shipped metal part's pocket leaves 1 mm each side).
    taught_model: the cell model the desired image and the check view were seen through;
      None: a job file from before it was recorded (run as taught, never retargeted).
    survey_bMe: where the camera surveys the table to locate the part before the run;
      None: the job does not locate, the part arrives where it was taught.
    grasp_symmetry: how many turns about the top face's vertical axis map the part onto
      itself (4: a square face, 2: a half turn only, 1: none); a run may pick and place it
      at the taught grasp turned by any of them (core/production/grasp.py).
    laser_law: which switching IBVS with laser the laser method runs: the one robust to
      calibration error (the default: a cell not yet commissioned still servoes), or the
      thesis's own (docs/thesis-notes.md, "The robust law").
    """

    name: str
    part_side_m: float
    desired: DesiredImage
    start_bMe: Matrix
    eMe_pick: Matrix
    bMe_place: Matrix
    approach_m: float = 0.04
    threshold_px: float = 1.0
    method: str = "laser"
    gain: float = 1.0
    description: str = ""
    taught_bMe: Matrix = field(default_factory=lambda: np.eye(4))  # where the desired image was taken
    check: CheckView | None = None
    placement_tolerance_mm: float = 1.0
    taught_model: TaughtModel | None = None
    survey_bMe: Matrix | None = None
    grasp_symmetry: int = 4
    laser_law: LaserLaw = LaserLaw.ROBUST

    def __post_init__(self) -> None:
        validate_job_name(self.name)
        # The ranges the page and the channel's commands take: a job file is held to them too,
        # so no file can hang a run (an approach of 10^9 m) or pass anything (a threshold of 10^12 px).
        for field_name, allowed in RANGES.items():
            value = getattr(self, field_name)
            if not allowed.low <= value <= allowed.high:  # NaN fails too
                raise JobError(f"job {self.name!r}: {field_name} must be {allowed.words()}, got {value:g}")
        for pose_name in ("taught_bMe", "start_bMe", "eMe_pick", "bMe_place", "survey_bMe"):
            _check_translation(self.name, pose_name, getattr(self, pose_name))
        if self.check is not None:
            _check_translation(self.name, "check.check_bMe", self.check.check_bMe)
        if self.grasp_symmetry not in SYMMETRIES:
            raise JobError(
                f"job {self.name!r}: grasp_symmetry {self.grasp_symmetry!r} is not one of {', '.join(map(str, SYMMETRIES))}"
            )

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
            "check": None
            if self.check is None
            else {
                "check_bMe": self.check.check_bMe.tolist(),
                "corners_px": self.check.corners_px.tolist(),
            },
            "taught_model": None if self.taught_model is None else self.taught_model.as_dict(),
            "survey_bMe": None if self.survey_bMe is None else self.survey_bMe.tolist(),
            "grasp_symmetry": self.grasp_symmetry,
            "laser_law": self.laser_law.value,
        }


# Each setting's range, the page's (the protocol's commands check the same).
RANGES = {
    "threshold_px": THRESHOLD_PX,
    "gain": GAIN,
    "approach_m": APPROACH_M,
    "placement_tolerance_mm": PLACEMENT_TOLERANCE_MM,
}


def _check_translation(job: str, name: str, bMx: Matrix | None) -> None:
    """A pose's translation within the protocol's POSE_TRANSLATION_M on every axis."""
    if bMx is None:
        return
    t = np.asarray(bMx, dtype=float)[:3, 3]
    if not np.all((POSE_TRANSLATION_M.low <= t) & (t <= POSE_TRANSLATION_M.high)):
        raise JobError(f"job {job!r}: {name}'s translation must be {POSE_TRANSLATION_M.words()} each, got {t.tolist()}")


def validate_job_name(name: object) -> str:
    if not isinstance(name, str) or not JOB_NAME.match(name):
        raise JobError(f"job name {name!r}: use {JOB_NAME_WORDS}")
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
        if not (
            np.allclose(R.T @ R, np.eye(3), atol=1e-6)
            and np.isclose(np.linalg.det(R), 1.0, atol=1e-6)
            and np.allclose(M[3], [0, 0, 0, 1])
        ):
            raise self.fail(key, "not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
        return M


def job_from_dict(data: Any, source: str) -> Job:
    f = _Fields(data, source)
    if f.data.get("format") != JOB_FORMAT:
        raise JobError(f"{source}: not a vservo job file (format {f.data.get('format')!r}, expected {JOB_FORMAT!r})")
    version = f.data.get("version")
    if version not in READABLE_VERSIONS:
        raise JobError(
            f"{source}: job format version {version!r}; this vservo reads versions {', '.join(map(str, READABLE_VERSIONS))}"
        )
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
    fields: dict[str, Any] = dict(
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
        grasp_symmetry=_grasp_symmetry(f),
        laser_law=_laser_law(f),
        **(_check_fields(f, source) if version >= 2 else {}),
        **(_model_fields(f, source) if version >= 3 else {}),
    )
    try:
        return Job(**fields)
    except JobError as exc:  # a value out of its range: the file named too
        raise JobError(f"{source}: {exc}") from None


def _grasp_symmetry(f: _Fields) -> int:
    """The optional grasp_symmetry (a job file without it: a square face, 4)."""
    value = f.data.get("grasp_symmetry", 4)
    if isinstance(value, bool) or value not in SYMMETRIES:
        raise f.fail(
            "grasp_symmetry",
            f"{value!r} is not one of {', '.join(map(str, SYMMETRIES))} (the turns "
            "about the top face's vertical axis that map the part onto itself)",
        )
    return int(value)


def _laser_law(f: _Fields) -> LaserLaw:
    """The optional laser_law (a job file without it: the robust law, the product's default)."""
    value = f.data.get("laser_law", LaserLaw.ROBUST.value)
    if value not in tuple(LaserLaw):
        raise f.fail("laser_law", f"{value!r} is not one of {', '.join(law.value for law in LaserLaw)}")
    return LaserLaw(value)


def _check_fields(f: _Fields, source: str) -> dict[str, Any]:
    """What version 2 added: the placement tolerance and the check view (null: none taught)."""
    check = f.get("check")
    if check is not None:
        view = _Fields(check, f"{source}: check")
        check = CheckView(check_bMe=view.pose("check_bMe"), corners_px=view.array("corners_px", (4, 2)))
    return {"placement_tolerance_mm": f.number("placement_tolerance_mm"), "check": check}


def _model_fields(f: _Fields, source: str) -> dict[str, Any]:
    """What version 3 added: the taught model and the survey pose (null: none)."""
    model = f.get("taught_model")
    if model is not None:
        fields = _Fields(model, f"{source}: taught_model")
        camera = _Fields(fields.get("camera"), f"{source}: taught_model: camera")
        u0, v0 = camera.array("principal_point_px", (2,))
        size = camera.array("image_size_px", (2,))
        if np.any(size < 1) or np.any(size != np.round(size)):
            raise camera.fail("image_size_px", f"{size.tolist()} is not two positive whole numbers")
        intrinsics = Intrinsics(camera.number("fx_px"), camera.number("fy_px"), float(u0), float(v0), int(size[0]), int(size[1]))
        distortion = Distortion(*camera.array("distortion", (5,)))
        measured = fields.data.get("measured", False)  # optional: files before it taught on an unknown model
        if not isinstance(measured, bool):
            raise fields.fail("measured", f"{measured!r} is not true or false")
        model = TaughtModel(CameraModel(intrinsics, distortion), fields.pose("eMc"), fields.pose("cMl"), measured)
    survey = f.get("survey_bMe")
    return {"taught_model": model, "survey_bMe": None if survey is None else f.pose("survey_bMe")}


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
