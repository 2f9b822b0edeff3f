"""What the controller publishes: its state, typed, and what it saw in each camera frame.

``ControllerState`` is sent on every change and every servo cycle; the app decodes it once
(``from_json``) and reads its fields, never a dict of loose keys. The phase is an enum, the
teaching steps are an enum (what the draft has and lacks), the run's servo figures, its
outcome and commissioning's progress are records of their own.

Arrays (poses, joints, pixels) are read-only numpy arrays: one state is read by every
thread of the app at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum, StrEnum

import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.production.protocol.catalogue import RunEnd
from vservo.core.servo.laws.base import Stage


class Phase(str, Enum):
    """The states of the cell's sequence (the controller process adds idle, teaching and commissioning)."""

    IDLE = "idle"
    MANUAL = "manual"  # the operator moves the arm by hand (jog, Move there), entered and left on purpose
    TEACHING = "teaching"
    COMMISSIONING = "commissioning"
    SERVOING = "servoing"
    PICKING = "picking"
    PLACING = "placing"
    DONE = "done"
    FAULT = "fault"
    ESTOPPED = "e-stopped"


# Where no run moves the arm: Home, Survey, a part presented (as the controller checks them).
STANDING = frozenset({Phase.IDLE, Phase.MANUAL, Phase.TEACHING, Phase.DONE, Phase.FAULT})
HAND_MOVES = frozenset({Phase.MANUAL, Phase.TEACHING})  # where the operator jogs and types moves
MOVING = frozenset({Phase.SERVOING, Phase.PICKING, Phase.PLACING})  # a run moves the arm


class Outcome(StrEnum):
    """How a run ended, as the store, the recording and ``vservo run --json`` say it.

    E-stopped is spelled as the phase is; runs stored before the two were one spelling
    said "estopped", and still read back (``Outcome("estopped")``).
    """

    PLACED = "placed"
    MISSED = "missed"
    FAULT = "fault"
    ESTOPPED = Phase.ESTOPPED.value
    INTERRUPTED = "interrupted"  # the controller process died during the run (found so at its next start)

    @classmethod
    def _missing_(cls, value: object) -> Outcome | None:
        return cls.ESTOPPED if value == "estopped" else None


class TeachStep(Enum):
    """What teaching a job captures, in the draft's order; the value is how the screens name it."""

    DESIRED_IMAGE = "the desired image"
    START_POSE = "the start pose"
    PICK_POSE = "the pick pose"
    PLACE_POSE = "the place pose"
    CHECK_VIEW = "the check view"

    @property
    def required(self) -> bool:
        """A job cannot be saved without it (without the check view, runs report placement unknown)."""
        return self is not TeachStep.CHECK_VIEW

    @property
    def words(self) -> str:
        """The step as the checklist names it, with what leaving it out costs."""
        return self.value if self.required else f"{self.value} (without it, runs report placement unknown)"


def _frozen(values: object, shape: tuple[int, ...] | None = None) -> Matrix:
    """A read-only float copy (the controller keeps writing its own arrays)."""
    array = np.array(values, dtype=float)
    if shape is not None:
        array = array.reshape(shape)
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False)
class Teaching:
    """A job being taught: the steps its draft has, and the poses the Teach tab offers to go to,
    each once known: the desired view; from the cell file's [metal_part], the flange pose that
    sets the picked part down centred in its pocket and where the taught place sets it."""

    taught: frozenset[TeachStep] = frozenset()
    test_pick_held: bool | None = None  # the last test pick's grip (None: none tried since the desired image)
    view_bMe: Matrix | None = None
    pocket_bMe: Matrix | None = None
    place_bMo: Matrix | None = None
    # Whether the cell's model is measured (CellConfig.model_measured): else the aids that
    # rest on it (the part's position in mm, the flange to view it, the cup on it) are the
    # nominal model's, tens of mm off, and the page says so.
    model_measured: bool = True

    def __post_init__(self) -> None:
        for name in ("view_bMe", "pocket_bMe", "place_bMo"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _frozen(getattr(self, name), (4, 4)))

    @property
    def missing(self) -> tuple[TeachStep, ...]:
        """What the job cannot be saved without."""
        return tuple(step for step in TeachStep if step.required and step not in self.taught)

    @property
    def optional_missing(self) -> tuple[TeachStep, ...]:
        """What the job can be saved without, at a cost the operator should know."""
        return tuple(step for step in TeachStep if not step.required and step not in self.taught)


@dataclass(frozen=True, eq=False)
class RunFigures:
    """The servo of the run under way (or the last one): its stage, cycle, feature error (px,
    None when not measured) and the camera twist cVc (m/s, rad/s; NaN where not finite);
    the part's ID when the run was given one."""

    run_id: int | None = None
    stage: Stage | None = None
    iteration: int = 0
    error_px: float | None = None
    cVc: Matrix = field(default_factory=lambda: np.zeros(6))
    part_id: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "cVc", _frozen(self.cVc, (6,)))


@dataclass(frozen=True)
class RunOutcome:
    """How the last run ended: what the Assemble tab and the banner say of it."""

    outcome: Outcome
    reason: str
    final_error_px: float | None = None
    placement_error_mm: float | None = None  # from the check view; None without one, NaN when not seen
    duration_s: float = 0.0
    iterations: int = 0
    notes: tuple[str, ...] = ()  # how the job was run (retargeted, not recorded, ...)
    end: RunEnd | None = None  # why, as the catalogue explains it (protocol/catalogue.py)
    cell_time_s: float | None = None  # the run on the cell's clock (None where the backend keeps none)


class CommissionStep(StrEnum):
    """Commissioning's steps (docs/commissioning.md), as the Calibrate tab and ``--steps`` name them."""

    CAMERA = "camera"
    HAND_EYE = "hand-eye"
    LASER = "laser"
    NN = "nn"


class Verdict(StrEnum):
    GOOD = "good"
    RETAKE = "retake"


@dataclass(frozen=True)
class ProcedureProgress:
    """One part of commissioning's procedure: views (or the network's epochs) done of total, the last note."""

    done: int
    total: int
    note: str


@dataclass(frozen=True)
class StepReport:
    """A commissioning step's verdict and its residuals; each step fills its own figures."""

    verdict: Verdict
    why: str = ""
    views: int | None = None  # camera, nn
    rms_px: float | None = None  # camera, hand-eye
    worst_view_rms_px: float | None = None  # camera
    std_fx_px: float | None = None  # camera
    spread_mm: float | None = None  # hand-eye: the board seen still to this
    spread_deg: float | None = None
    line_rms_mm: float | None = None  # laser
    depth_span_mm: float | None = None
    spots: int | None = None
    validation_mean_mm: float | None = None  # nn
    validation_max_mm: float | None = None
    corners: int | None = None


@dataclass(frozen=True)
class MeasuredCamera:
    fx_px: float
    fy_px: float
    principal_point_px: tuple[float, float]


@dataclass(frozen=True)
class LaserGeometry:
    baseline_mm: float  # d, eqs. 4-18 .. 4-21
    alpha_deg: float


@dataclass(frozen=True)
class Acceptance:
    """The acceptance check: where the commissioned model puts board corners the camera sees."""

    corners: int
    mean_mm: float
    max_mm: float


@dataclass(frozen=True)
class ViewCount:
    taken: int
    used: int


@dataclass(frozen=True)
class CommissionSummary:
    """A finished commissioning: the measured model and each step's report (``vservo commission --json``)."""

    camera: MeasuredCamera
    eMc_mm_deg: tuple[float, ...]
    cMl_mm_deg: tuple[float, ...]
    laser: LaserGeometry
    steps: dict[CommissionStep, StepReport]
    acceptance: Acceptance | None
    good: bool
    views: ViewCount
    cell_time_s: float


@dataclass(frozen=True)
class CommissioningProgress:
    """This session's commissioning: its steps, the file Apply writes, each part of the
    procedure's progress, then the summary or the error that stopped it; the file applied."""

    steps: tuple[CommissionStep, ...]
    out: str
    step: str | None = None  # the part of the procedure under way
    progress: dict[str, ProcedureProgress] = field(default_factory=dict)  # by part, in the order they ran
    summary: CommissionSummary | None = None
    error: str | None = None
    applied: str | None = None

    @property
    def to_apply(self) -> bool:
        """A good commissioning waits for Apply."""
        return self.summary is not None and self.summary.good and self.applied is None


@dataclass(frozen=True, eq=False)
class ControllerState:
    """What every screen shows; published on every change and every servo cycle.

    bMe and q are the robot's readout (q empty until the controller has read the robot:
    never a made-up pose); ``teaching`` is set while a job is taught."""

    phase: Phase = Phase.IDLE
    detail: str = ""
    job: str | None = None
    run: RunFigures = field(default_factory=RunFigures)
    last_outcome: RunOutcome | None = None
    bMe: Matrix = field(default_factory=lambda: np.eye(4))
    q: Matrix = field(default_factory=lambda: np.zeros(0))
    holding_part: bool = False
    robot: str = ""
    backend: str = ""
    can_present_part: bool = False  # the cell can put a new part on the table (simulated, or a test fixture)
    teaching: Teaching | None = None
    cell_file: str = ""  # the cell file whose model the controller runs on
    commissioning: CommissioningProgress | None = None
    time_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "bMe", _frozen(self.bMe, (4, 4)))
        object.__setattr__(self, "q", _frozen(self.q).ravel())


@dataclass(frozen=True, eq=False)
class FrameMeta:
    """What the vision saw in a frame the controller sends (pixels, NaN where not seen)."""

    index: int = 0
    time_s: float = 0.0
    corners_px: Matrix | None = None  # (4, 2)
    laser_spot_px: Matrix | None = None  # (2,)
    desired_corners_px: Matrix | None = None  # (4, 2)
    desired_laser_px: Matrix | None = None  # (2,)
    trail_px: Matrix | None = None  # (T, 4, 2): the corners so far in this run
