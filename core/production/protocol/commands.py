"""The commands the app sends the controller: one small frozen dataclass each.

A command checks its own fields as it is made (``__post_init__``), with the ranges the
page offers, and refuses a bad one in one line naming the field and its range
(``CommandRefused``): the same check whether the app builds it or the controller reads it
off the channel, so a number the page would never send is refused at the controller too.

Each class is its command: its name on the channel is the class's name in snake case
(``SetSettings`` is ``set_settings``), which is also the controller's method that carries
it out with the fields as keyword arguments (``carry_out``). ``result_type`` is what its
reply carries, decoded at the app. Queries (``Query``) read the job store and change
nothing: any browser may send them.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, ClassVar, Protocol

import numpy as np

from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix
from vservo.core.production.protocol.catalogue import Refusal
from vservo.core.production.protocol.codec import from_json, to_json
from vservo.core.production.protocol.state import CommissionStep, Outcome


class CommandRefused(VservoError):
    """A command that cannot be carried out now, or with a field out of range; the message says why.

    ``kind`` is what the catalogue explains to the operator (protocol/catalogue.py; a field
    out of range unless said); ``advice``, when given, the operator's words for this case
    (which joint, which way), said beside the kind's sentence."""

    def __init__(self, message: str, kind: Refusal = Refusal.OUT_OF_RANGE, advice: str = "") -> None:
        super().__init__(message)
        self.kind = kind
        self.advice = advice


@dataclass(frozen=True)
class Range:
    """The values a number field takes (inclusive), as the page's input offers them."""

    low: float
    high: float
    unit: str = ""

    def words(self) -> str:
        return f"from {self.low:g} to {self.high:g}{' ' + self.unit if self.unit else ''}"

    def check(self, name: str, value: object) -> float:
        number = _number(name, value)
        if not self.low <= number <= self.high:  # NaN is refused too
            raise CommandRefused(f"{name} must be {self.words()}, got {number:g}")
        return number


# The page's ranges (the Teach tab's inputs take their limits from here).
THRESHOLD_PX = Range(0.1, 50.0, "px")
GAIN = Range(0.05, 5.0)
APPROACH_M = Range(0.005, 0.2, "m")
PLACEMENT_TOLERANCE_MM = Range(0.05, 20.0, "mm")
JOG_TRANSLATION_M = Range(-0.02, 0.02, "m")  # the largest jog step: 20 mm
JOG_ROTATION_RAD = Range(-math.radians(10.0), math.radians(10.0), "rad")  # and 10 deg
# A pose's translation: far beyond any arm's reach, short of a number that is no position at all
# (the workspace itself is the safety layer's to check).
POSE_TRANSLATION_M = Range(-5.0, 5.0, "m")
ROTATION_TOLERANCE = 1e-6  # how far from orthonormal a pose's rotation may be
PART_CENTRE_MM = Range(-1000.0, 1000.0, "mm")
PART_TURN_DEG = Range(-360.0, 360.0, "deg")
LIST_LIMIT = Range(1, 10_000, "rows")
MAX_TEXT = 4096  # characters of a description or a file path
JOB_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
JOB_NAME_WORDS = "1 to 64 letters, digits, '_', '-' or '.', starting with a letter or digit"
PART_ID = re.compile(r"[^\s\x00-\x1f\x7f]([^\x00-\x1f\x7f]{0,62}[^\s\x00-\x1f\x7f])?")  # as a PLC or a scanner gives it
PART_ID_WORDS = "1 to 64 printable characters (no spaces at either end, no control characters)"
PART_SIDE_M = 0.020  # the part the controller teaches: the shipped 20 mm cube (section 5.3)
# What a vector or a pose field takes (JSON's lists, tuples, arrays); it holds tuples once checked.
Numbers = Sequence[float] | Matrix
Rows = Sequence[Sequence[float]] | Matrix


def _shown(value: object) -> str:
    """A refused value in a line: numbers as %g, anything else as its (shortened) repr."""
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list | tuple | np.ndarray):
        return "[" + ", ".join(_shown(v) for v in list(value)[:16]) + (", ..." if len(value) > 16 else "") + "]"
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _number(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise CommandRefused(f"{name} must be a number, got {_shown(value)}")
    return float(value)


def _vector(name: str, value: object, length: int, bounds: Range) -> tuple[float, ...]:
    numbers = _numbers(name, value, (length,), f"{length} numbers")
    if not all(bounds.low <= v <= bounds.high for v in numbers.ravel()):
        raise CommandRefused(f"{name} must be {length} numbers, each {bounds.words()}, got {_shown(numbers.tolist())}")
    return tuple(float(v) for v in numbers)


def _numbers(name: str, value: object, shape: tuple[int, ...], what: str) -> Matrix:
    """``value`` as an array of ``shape`` floats (JSON's nested lists, a tuple, an array); booleans are no numbers."""
    try:
        raw = np.array(value, dtype=object)
    except ValueError:
        raw = np.array(None, dtype=object)
    numeric = all(isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool) for v in raw.ravel())
    if raw.shape != shape or not numeric:
        raise CommandRefused(f"{name} must be {what}, got {_shown(value)}")
    return raw.astype(float)


def _pose(name: str, value: object) -> tuple[tuple[float, ...], ...]:
    """A 4 x 4 rigid pose: a rotation (orthonormal, det +1), a translation within POSE_TRANSLATION_M, 0 0 0 1 below."""
    M = _numbers(name, value, (4, 4), "a 4 x 4 pose")
    t = M[:3, 3]
    if not all(POSE_TRANSLATION_M.low <= v <= POSE_TRANSLATION_M.high for v in t):
        raise CommandRefused(f"{name}: its translation must be {POSE_TRANSLATION_M.words()} each, got {_shown(t.tolist())}")
    R = M[:3, :3]
    rigid = (
        np.all(np.isfinite(R))
        and np.abs(R.T @ R - np.eye(3)).max() <= ROTATION_TOLERANCE
        and np.linalg.det(R) > 0
        and np.array_equal(M[3], [0.0, 0.0, 0.0, 1.0])
    )
    if not rigid:
        raise CommandRefused(
            f"{name} must be a rigid pose: a rotation (orthonormal, entries from -1 to 1) and 0 0 0 1 "
            f"as its last row, got {_shown(M.ravel().tolist())}"
        )
    return tuple(tuple(float(v) for v in row) for row in M)


def _text(name: str, value: object, limit: int = MAX_TEXT) -> str:
    if not isinstance(value, str) or len(value) > limit:
        raise CommandRefused(f"{name} must be text of at most {limit} characters, got {_shown(value)}")
    return value


def _job_name(name: str, value: object) -> str:
    if not isinstance(value, str) or not JOB_NAME.match(value):
        raise CommandRefused(f"{name} must be {JOB_NAME_WORDS}, got {_shown(value)}")
    return value


def _flag(name: str, value: object) -> bool:
    if not isinstance(value, bool):
        raise CommandRefused(f"{name} must be true or false, got {_shown(value)}")
    return value


def _snake(name: str) -> str:
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower()


@dataclass(frozen=True)
class Command:
    """The base of every command; subclasses are frozen dataclasses and register by their name."""

    command_name: ClassVar[str]  # on the channel, and the controller's method
    result_type: ClassVar[Any] = None  # what the reply carries (None: nothing)

    def __init_subclass__(cls, register: bool = True, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if register:
            cls.command_name = _snake(cls.__name__)
            COMMANDS[cls.command_name] = cls

    def _set(self, name: str, value: object) -> None:
        object.__setattr__(self, name, value)

    def arguments(self) -> dict[str, Any]:
        """The fields, as the controller's method takes them."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def carry_out(self, controller: Any) -> Any:
        """Carry the command out on the controller (in the controller process): its method of this name."""
        return getattr(controller, self.command_name)(**self.arguments())

    def reply_value(self, result: Any) -> Any:
        """What the reply carries of the method's result (JSON)."""
        return None if self.result_type is None else to_json(result)

    def result(self, raw: Any) -> Any:
        """The reply's result, typed (at the app)."""
        return None if self.result_type is None else from_json(self.result_type, raw, f"{self.command_name}'s result")


COMMANDS: dict[str, type[Command]] = {}


def command_message(command: Command) -> dict[str, Any]:
    """The command's name and its fields as JSON arguments."""
    return {"name": command.command_name, "args": to_json(command)}


def command_from(name: object, args: object) -> Command:
    """The command a message names, its fields checked; CommandRefused naming what is wrong."""
    kind = COMMANDS.get(name) if isinstance(name, str) else None
    if kind is None:
        raise CommandRefused(f"unknown command {_shown(name)}")
    if not isinstance(args, dict):
        raise CommandRefused(f"{name}: the arguments must be an object of names, got {_shown(args)}")
    fields = dataclasses.fields(kind)
    known = [f.name for f in fields]
    unknown = sorted(str(key) for key in args if key not in known)
    if unknown:
        raise CommandRefused(f"{name} takes {', '.join(known) or 'no arguments'}, not {', '.join(unknown)}")
    needed = [f.name for f in fields if f.default is dataclasses.MISSING and f.name not in args]
    if needed:
        raise CommandRefused(f"{name} needs {', '.join(needed)}")
    return kind(**args)


# -- the arm --------------------------------------------------------------------------------


class JogFrame(StrEnum):
    BASE = "base"
    TOOL = "tool"


@dataclass(frozen=True)
class Jog(Command):
    """Move the flange by a small step: a translation (m) and a rotation (rad) in the base or tool frame."""

    translation_m: Numbers = (0.0, 0.0, 0.0)
    rotation_rad: Numbers = (0.0, 0.0, 0.0)
    frame: JogFrame | str = JogFrame.BASE

    def __post_init__(self) -> None:
        self._set("translation_m", _vector("translation_m", self.translation_m, 3, JOG_TRANSLATION_M))
        self._set("rotation_rad", _vector("rotation_rad", self.rotation_rad, 3, JOG_ROTATION_RAD))
        if self.frame not in tuple(JogFrame):
            raise CommandRefused(f"frame must be base or tool, got {_shown(self.frame)}")
        self._set("frame", JogFrame(self.frame))


@dataclass(frozen=True)
class MoveTo(Command):
    """A linear move of the flange to bMe_target (a pose in the base frame, m)."""

    bMe_target: Rows

    def __post_init__(self) -> None:
        self._set("bMe_target", _pose("bMe_target", self.bMe_target))


@dataclass(frozen=True)
class MoveJoint(Command):
    """A move of the flange to bMe_target on a joint-space path (where the straight line cannot go)."""

    bMe_target: Rows

    def __post_init__(self) -> None:
        self._set("bMe_target", _pose("bMe_target", self.bMe_target))


@dataclass(frozen=True)
class GoHome(Command):
    """To the cell file's home joints, on a joint-space path."""


@dataclass(frozen=True)
class GoSurvey(Command):
    """The camera over the table where parts are presented, on a joint-space path."""


@dataclass(frozen=True)
class EnterManual(Command):
    """Manual mode: jogs and typed moves act until the operator leaves it."""


@dataclass(frozen=True)
class LeaveManual(Command):
    pass


@dataclass(frozen=True)
class PresentPart(Command):
    """A new part on the table: with its top face's centre at centre_mm (X, Y in the base
    frame) turned turn_deg about the vertical, or near where ``job``'s part was taught, or
    near where the cell's feeder puts parts."""

    centre_mm: Numbers | None = None
    turn_deg: float = 0.0
    job: str | None = None

    def __post_init__(self) -> None:
        if self.job is not None:
            _job_name("job", self.job)
        if self.centre_mm is not None:
            self._set("centre_mm", _vector("centre_mm", self.centre_mm, 2, PART_CENTRE_MM))
        self._set("turn_deg", PART_TURN_DEG.check("turn_deg", self.turn_deg))


@dataclass(frozen=True)
class Estop(Command):
    """Hold the robot now; carried out the moment it arrives, from any browser."""


@dataclass(frozen=True)
class Reset(Command):
    """Clear an e-stop, a fault or a finished run: back to idle."""


# -- teaching -----------------------------------------------------------------------------


@dataclass(frozen=True)
class BeginTeach(Command):
    """Start teaching a job, from scratch or from a stored job's poses and settings."""

    template: str | None = None

    def __post_init__(self) -> None:
        if self.template is not None:
            _job_name("template", self.template)


@dataclass(frozen=True)
class CaptureDesired(Command):
    """Take the desired image here; the reply carries its corners (px)."""

    result_type: ClassVar[Any] = Matrix

    def reply_value(self, result: Any) -> Any:
        return np.asarray(result.corners_px).tolist()  # the controller's DesiredImage


@dataclass(frozen=True)
class CaptureCheckView(Command):
    """Take the check view here; the reply carries its corners (px)."""

    result_type: ClassVar[Any] = Matrix

    def reply_value(self, result: Any) -> Any:
        return np.asarray(result.corners_px).tolist()  # the controller's CheckView


@dataclass(frozen=True)
class SetStartPose(Command):
    pass


@dataclass(frozen=True)
class SetPickPose(Command):
    pass


@dataclass(frozen=True)
class SetPlacePose(Command):
    pass


@dataclass(frozen=True)
class Suction(Command):
    """Switch the cup's suction; the reply says whether the vacuum sensor then feels a part."""

    on: bool
    result_type: ClassVar[Any] = bool

    def __post_init__(self) -> None:
        _flag("on", self.on)


@dataclass(frozen=True)
class ViewPart(Command):
    """Bring the camera over the part the camera sees, by the image alone
    (core/production/part_view.py): the desired view on a cell never commissioned."""


@dataclass(frozen=True)
class CentreCup(Command):
    """Put the cup on the middle of the part the camera sees, by the camera and the vacuum
    sensor alone (core/production/cup_centring.py): the pick pose on a cell never commissioned."""


@dataclass(frozen=True)
class TestPick(Command):
    """Try the pick here as a run will; the reply says whether the part held."""

    result_type: ClassVar[Any] = bool
    __test__ = False  # not a pytest class


@dataclass(frozen=True)
class SetSettings(Command):
    """The job's run settings; the placement tolerance is kept unless given."""

    threshold_px: float
    gain: float
    approach_m: float
    placement_tolerance_mm: float | None = None

    def __post_init__(self) -> None:
        self._set("threshold_px", THRESHOLD_PX.check("threshold_px", self.threshold_px))
        self._set("gain", GAIN.check("gain", self.gain))
        self._set("approach_m", APPROACH_M.check("approach_m", self.approach_m))
        if self.placement_tolerance_mm is not None:
            tolerance = PLACEMENT_TOLERANCE_MM.check("placement_tolerance_mm", self.placement_tolerance_mm)
            self._set("placement_tolerance_mm", tolerance)


@dataclass(frozen=True)
class JobSettings:
    """A job's run settings: the servo's threshold (px) and gain, the approach height (m), the placement tolerance (mm)."""

    threshold_px: float
    gain: float
    approach_m: float
    placement_tolerance_mm: float


NEW_JOB_SETTINGS = JobSettings(threshold_px=1.0, gain=1.0, approach_m=0.04, placement_tolerance_mm=1.0)  # a new job's draft


@dataclass(frozen=True)
class SaveJob(Command):
    """Save the job taught; the reply carries its name."""

    name: str
    description: str = ""
    result_type: ClassVar[Any] = str

    def __post_init__(self) -> None:
        _job_name("name", self.name)
        _text("description", self.description)

    def reply_value(self, result: Any) -> Any:
        return result.name  # the controller's Job


@dataclass(frozen=True)
class CancelTeach(Command):
    pass


# -- runs and commissioning -------------------------------------------------------------------


@dataclass(frozen=True)
class Start(Command):
    """Start one assembly of the job, its run recording the part's ID when given; the reply carries the run's id."""

    job_name: str
    part_id: str | None = None
    result_type: ClassVar[Any] = int

    def __post_init__(self) -> None:
        _job_name("job_name", self.job_name)
        if self.part_id is not None and not (isinstance(self.part_id, str) and PART_ID.fullmatch(self.part_id)):
            raise CommandRefused(f"part_id must be {PART_ID_WORDS}, got {_shown(self.part_id)}")


@dataclass(frozen=True)
class Commission(Command):
    """Commission the cell on its board: the steps (None: all); the reply carries the file Apply writes."""

    steps: Sequence[CommissionStep | str] | None = None
    out_path: str | None = None
    result_type: ClassVar[Any] = str

    def __post_init__(self) -> None:
        if self.steps is not None:
            if not isinstance(self.steps, list | tuple) or not all(s in tuple(CommissionStep) for s in self.steps):
                names = ", ".join(CommissionStep)
                raise CommandRefused(f"steps must be a list of commissioning steps from {names}, got {_shown(self.steps)}")
            self._set("steps", tuple(CommissionStep(s) for s in self.steps))
        if self.out_path is not None:
            _text("out_path", self.out_path)

    def reply_value(self, result: Any) -> Any:
        return str(result)


@dataclass(frozen=True)
class ApplyCommissioning(Command):
    """Write the commissioned cell file and run on it; the reply carries its path."""

    result_type: ClassVar[Any] = str

    def reply_value(self, result: Any) -> Any:
        return str(result)


# -- queries: the job store ---------------------------------------------------------------------


class JobStore(Protocol):
    """What a query reads: the controller's store (core/production/storage.py)."""

    def list_jobs(self) -> Any: ...

    def list_runs(self, limit: int) -> Any: ...

    def load_job(self, name: str) -> Any: ...


@dataclass(frozen=True)
class Query(Command, register=False):
    """A command that only reads the store; any browser may send it."""

    def carry_out(self, controller: Any) -> Any:
        return self.answer(controller.store)

    def answer(self, store: JobStore) -> Any:
        raise NotImplementedError


@dataclass(frozen=True)
class JobEntry:
    """A stored job as listed: its name, when it was saved, why it cannot be loaded (if so)."""

    name: str
    saved_at: float
    problem: str | None = None
    shipped: bool = False


@dataclass(frozen=True)
class StageCount:
    stage: str  # the stage's code (a Stage's value), as the run's record keeps it
    iterations: int


@dataclass(frozen=True)
class RunEntry:
    """One stored assembly attempt; outcome None while it runs."""

    id: int
    job: str
    backend: str
    started_at: float
    finished_at: float | None = None
    outcome: Outcome | None = None
    reason: str | None = None
    final_error_px: float | None = None
    placement_error_mm: float | None = None
    duration_s: float | None = None
    stages: tuple[StageCount, ...] = ()
    recording: str | None = None  # its folder, None when not recorded or removed by the retention
    part_id: str | None = None  # the part's ID, when the run was given one
    recording_removed_at: float | None = None  # when the retention ([recordings] of the cell file) removed its recording


@dataclass(frozen=True, eq=False)
class JobDetail:
    """A stored job's poses (base frame, m) and settings: what the Teach tab goes to and keeps."""

    name: str
    part_side_m: float
    taught_bMe: Matrix
    start_bMe: Matrix
    bMe_place: Matrix
    check_bMe: Matrix | None
    threshold_px: float
    gain: float
    approach_m: float
    placement_tolerance_mm: float


@dataclass(frozen=True)
class ListJobs(Query):
    result_type: ClassVar[Any] = tuple[JobEntry, ...]

    def answer(self, store: JobStore) -> tuple[JobEntry, ...]:
        return tuple(store.list_jobs())


@dataclass(frozen=True)
class ListRuns(Query):
    limit: int = 50
    result_type: ClassVar[Any] = tuple[RunEntry, ...]

    def __post_init__(self) -> None:
        whole = isinstance(self.limit, int) and not isinstance(self.limit, bool)
        if not whole or not LIST_LIMIT.low <= self.limit <= LIST_LIMIT.high:
            raise CommandRefused(f"limit must be a whole number {LIST_LIMIT.words()}, got {_shown(self.limit)}")

    def answer(self, store: JobStore) -> tuple[RunEntry, ...]:
        return tuple(from_json(RunEntry, to_json(record)) for record in store.list_runs(self.limit))


@dataclass(frozen=True)
class GetJob(Query):
    name: str
    result_type: ClassVar[Any] = JobDetail

    def __post_init__(self) -> None:
        _job_name("name", self.name)

    def answer(self, store: JobStore) -> JobDetail:
        job = store.load_job(self.name)
        return JobDetail(
            name=job.name,
            part_side_m=job.part_side_m,
            taught_bMe=job.taught_bMe,
            start_bMe=job.start_bMe,
            bMe_place=job.bMe_place,
            check_bMe=None if job.check is None else job.check.check_bMe,
            threshold_px=job.threshold_px,
            gain=job.gain,
            approach_m=job.approach_m,
            placement_tolerance_mm=job.placement_tolerance_mm,
        )
