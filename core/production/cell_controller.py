"""The controller process's core: the cell's state machine, its commands and what it publishes.

It owns the rig (robot backend, vacuum, camera, vision) and the store. Commands come
from one operator at a time (the channel and the app decide who that is); every command
is checked against the current phase, and a refused one raises CommandRefused with the
reason, never moves the robot. The phases (vservo.core.production.assembly.Phase):

    idle --teach--> teaching --save/cancel--> idle   (teaching: jog, suction, test pick, present part)
    idle --start--> servoing (stages) --> picking --> placing --> done | fault
    idle --commission--> commissioning --> idle | fault
    any  --estop--> e-stopped --reset--> idle

Commissioning (core/production/commissioning.py) measures the cell's model on its board
in the background; ``apply_commissioning`` writes the commissioned cell file and runs
on it from then on: the jobs are retargeted to the new model as every run starts.

E-stop acts at once from the caller's thread: it sends hold to the robot before it
returns, so a move the assembly thread has not yet sent is refused by the robot itself
and the arm stops within the control cycle under way. Motion needs an explicit enable:
servo power is switched on by ``start`` or a jog and a reset never restarts a run.

Subscribers get ControllerState snapshots and camera frames with the features seen in
them; they are called from the cell controller's threads and must not block.
"""

from __future__ import annotations

import itertools
import logging
import re
import sqlite3
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vservo.core.cell.config import DEFAULT_CELL, CellConfig, ConfigError, load_cell, read_cell_data
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.cell.scene import Cube
from vservo.core.geometry.pose_estimation import PoseEstimationError, pose_from_planar_points
from vservo.core.geometry.spatial import Matrix, exp_twist
from vservo.core.perception.camera_source import BaseSource, CameraSourceError, Frame, FrameSource, Size
from vservo.core.perception.features import DesiredImage, ImageFeatures
from vservo.core.perception.recording import RecordingError, RunRecorder
from vservo.core.production.assembly import (
    AssemblyEvent,
    AssemblyOutcome,
    Outcome,
    Phase,
    PhaseChange,
    hold_after_fault,
    run_assembly,
)
from vservo.core.production.fixture import FixtureError
from vservo.core.production.jobs import Job, JobError, TaughtModel
from vservo.core.production.locate import PartLocator
from vservo.core.production.placement_check import CheckView
from vservo.core.production.pocket import PocketFit, flange_in_pocket, part_on_flange, pocket_fit
from vservo.core.production.retarget import retarget, retarget_note
from vservo.core.production.rig import Rig, extractor_for
from vservo.core.production.storage import Store
from vservo.core.robot.backend import MotionStopped, RobotError, apply_increment
from vservo.core.servo.laws.base import Stage
from vservo.core.servo.loop import cycle_record
from vservo.core.servo.teaching import TeachError, desired_from_features

if TYPE_CHECKING:  # commissioning's calibration (torch, the board finder) is imported when a cell is commissioned
    from vservo.core.production.commissioning import Commissioning, CommissionResult, CommissionSettings, Progress, Step

log = logging.getLogger("vservo.controller")

JOG_SPEED_M_S = 0.02
HOLD_CONFIRM_S = 1.0  # an e-stop's hold unanswered this long is reported as not confirmed
PART_SIDE_M = 0.020  # the shipped part, a 20 mm cube (section 5.3)
# A test pick lifts the part this far: enough for the vacuum sensor to feel its weight,
# little enough that a part that falls lands where it lay.
TEST_PICK_LIFT_M = 0.005
# The check view's part may lie this far from where the taught pick and place carry the
# part of the desired view before the operator is warned (deg; the position's bound is
# the job's placement tolerance): beyond it the part moved between the desired image and
# the pick, or slipped on the cup, and every run would place it so.
PLACE_TURN_WARNING_DEG = 2.0
TRAIL_LENGTH = 400  # feature positions kept for the trajectories drawn on the image
# What a commissioned file must share with the running cell for the controller to run on it
# without a restart: the devices it opened (the model is what commissioning changes).
DEVICES: dict[str, Callable[[CellConfig], object]] = {
    "[camera.source]": lambda c: c.camera_source,
    "[jrc]": lambda c: c.jrc,
    "[vacuum] device": lambda c: c.vacuum_device,
    "[robot] backend": lambda c: c.robot_backend,
    "[fixture] url": lambda c: c.fixture_url,
    "arm": lambda c: c.arm,
}


class CommandRefused(Exception):
    """A command that cannot be carried out now; the message says why."""


@dataclass(frozen=True)
class TeachDraft:
    """A job being taught: what has been captured so far."""

    template: str | None = None
    desired: DesiredImage | None = None
    taught_bMe: Matrix | None = None
    start_bMe: Matrix | None = None
    eMe_pick: Matrix | None = None
    bMe_place: Matrix | None = None
    threshold_px: float = Job.threshold_px
    gain: float = 1.0
    approach_m: float = 0.04
    check: CheckView | None = None
    placement_tolerance_mm: float = 1.0
    taught_model: TaughtModel | None = None  # what the desired image was seen through
    seen_bMo: Matrix | None = None  # the part as the desired image saw it (planar PnP, nominal camera)

    def missing(self) -> list[str]:
        """What the job cannot be saved without."""
        names = {
            "desired": "the desired image",
            "start_bMe": "the start pose",
            "eMe_pick": "the pick pose",
            "bMe_place": "the place pose",
        }
        return [text for key, text in names.items() if getattr(self, key) is None]

    def optional_missing(self) -> list[str]:
        """What the job can be saved without, at a cost the operator should know."""
        return ["the check view (without it, runs report placement unknown)"] if self.check is None else []


@dataclass(frozen=True)
class ControllerState:
    """What every screen shows; published on every change and every servo cycle."""

    phase: str = Phase.IDLE.value
    detail: str = ""
    job: str | None = None
    run_id: int | None = None
    stage: Stage | None = None
    iteration: int = 0
    error_px: float | None = None
    cVc: list[float] = field(default_factory=lambda: [0.0] * 6)
    bMe: list[list[float]] = field(default_factory=lambda: np.eye(4).tolist())
    q: list[float] = field(default_factory=list)
    holding_part: bool = False
    robot: str = ""
    backend: str = ""
    can_present_part: bool = False  # the cell can put a new part on the table (simulated, or a test fixture)
    teach_missing: list[str] = field(default_factory=list)
    teach_optional: list[str] = field(default_factory=list)
    # While teaching, the poses the Teach tab offers to go to, each once known: "view_bMe"
    # the desired view; from the cell file's [metal_part], "pocket_bMe" the flange pose that
    # sets the picked part down centred in its pocket, "place_bMo" where the taught place sets it.
    teach_poses: dict[str, list[list[float]]] = field(default_factory=dict)
    last_outcome: dict | None = None
    cell_file: str = ""  # the cell file whose model the controller runs on
    # The commissioning of this session: its steps, the file Apply writes, per step of the
    # procedure the views (or epochs) done of total and the last note, then the summary
    # (commission_summary), or the error that stopped it; "applied" once written and reloaded.
    commissioning: dict | None = None
    time_s: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FrameView:
    """A camera frame and what the vision saw in it, for the live image."""

    frame: Frame
    corners_px: Matrix | None = None
    laser_spot_px: Matrix | None = None
    desired: DesiredImage | None = None
    trail_px: Matrix | None = None  # (T, 4, 2): corner positions so far in this run


@dataclass(frozen=True)
class Commissioned:
    """A finished commissioning, waiting for Apply: what it measured and where it goes."""

    result: CommissionResult
    out_path: Path
    folder: Path
    steps: list[Step]


def _part_origin(centre_mm: Sequence[float], turn_deg: float) -> tuple[float, float]:
    """The part's frame O (a top-face corner), x and y in m, for its top face's centre at
    ``centre_mm`` turned ``turn_deg``."""
    values = [*np.asarray(centre_mm, float).ravel(), float(turn_deg)]
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise CommandRefused(f"a part is presented at a finite X, Y (mm) and turn (deg), got {values}")
    turn = np.deg2rad(turn_deg)
    half = PART_SIDE_M / 2
    corner = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]]) @ [half, half]
    x, y = np.asarray(values[:2]) / 1000.0 - corner
    return float(x), float(y)


def _finite_list(values: Matrix) -> list:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(values, dtype=float).ravel()]


class _WorkThread(threading.Thread):
    """A daemon thread that drives the cell, whose end is an Event rather than the thread's
    own lock: a Ctrl-C that interrupts ``join()`` leaves CPython 3.11 taking a running
    thread for stopped (``Thread._wait_for_tstate_lock``), and the process would then exit
    under a run still moving the robot, its end never on record."""

    def __init__(self, target: Callable[..., None], args: tuple, name: str) -> None:
        super().__init__(target=target, args=args, name=name, daemon=True)
        self.finished = threading.Event()

    def run(self) -> None:
        try:
            super().run()
        finally:
            self.finished.set()


def _closed_quietly(recorder: RunRecorder) -> None:
    """Close a recorder that failed to write; its close may fail alike (the same full disk)."""
    try:
        recorder.close({"aborted": "a write failed"})
    except (RecordingError, OSError) as exc:
        log.warning("closing the failed recording %s: %s", recorder.folder, exc)


def is_shipped_cell(source: str) -> bool:
    """Whether ``source`` names the cell file shipped in static/ (part of the installed package)."""
    shipped = Path(str(resources.files("vservo.static").joinpath(DEFAULT_CELL)))
    return source == f"static/{DEFAULT_CELL}" or Path(source).resolve() == shipped.resolve()


def commissioned_path(source: str, data_folder: Path) -> Path:
    """Where a commissioning of the cell file ``source`` is written unless told: beside it as
    ``<stem>-commissioned.toml`` (``-2``, ``-3``... when taken; a commissioned file's own
    commissioning counts on from its stem), or in the data folder when ``source`` is the
    shipped file, which belongs to the installed package."""
    folder = Path(data_folder) if is_shipped_cell(source) else Path(source).parent
    stem = re.sub(r"-commissioned(-\d+)?$", "", Path(source).stem)
    names = (f"{stem}-commissioned{'' if k == 1 else f'-{k}'}.toml" for k in itertools.count(1))
    return next(folder / name for name in names if not (folder / name).exists())


class _ShownCamera(BaseSource):
    """The rig's camera lent to commissioning: every frame it takes is shown in the live view."""

    def __init__(self, camera: FrameSource, show: Callable[[FrameView], None]) -> None:
        self._camera, self._show = camera, show

    @property
    def image_size(self) -> Size | None:
        return self._camera.image_size

    def read(self) -> Frame:
        return self._shown(self._camera.read())

    def read_after(self, t_s: float) -> Frame:
        return self._shown(self._camera.read_after(t_s))

    def _shown(self, frame: Frame) -> Frame:
        self._show(FrameView(frame))
        return frame

    def close(self) -> None:
        pass  # the controller owns the camera; commissioning only borrows it


class CellController:
    def __init__(self, rig: Rig, store: Store, *, seed: int = 0, cycle_period_s: float = 0.0) -> None:
        self.rig = rig
        self.store = store
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.cycle_period_s = cycle_period_s  # a floor on the servo cycle, so a fast simulator can be watched
        self._lock = threading.RLock()  # one command at a time; the camera and robot are shared
        self._state = ControllerState(
            backend=rig.robot.name,
            robot=rig.config.arm,
            can_present_part=rig.present_part is not None,
            cell_file=rig.config.source,
        )
        # The joints drawn in 3D: a real JRC reports the flange pose; the safety layer's arm
        # model's inverse kinematics, from the last joints shown, turns it into an arm to draw.
        self._shown_q = rig.config.home_q.copy()
        self._draft: TeachDraft | None = None
        self._estop = threading.Event()
        self._estop_reason = "e-stop pressed"
        self._jogging = threading.Event()  # a jog or a gizmo move is under way
        self._run_thread: _WorkThread | None = None  # an assembly run's, or commissioning's
        self._work = "an assembly run"  # what the thread does, for the refusals while it runs
        self._commissioned: Commissioned | None = None
        self._trail: list[Matrix] = []
        self._desired: DesiredImage | None = None  # drawn over the live image
        self._desired_image: np.ndarray | None = None
        self._check_image: np.ndarray | None = None
        self.last_outcome: AssemblyOutcome | None = None
        self.state_subscribers: list[Callable[[ControllerState], None]] = []
        self.frame_subscribers: list[Callable[[FrameView], None]] = []
        interrupted = store.close_unfinished_runs()
        if interrupted:
            log.warning("runs %s were found unfinished (their controller died): marked interrupted", interrupted)
        self.rig.robot.connect()
        self._state = replace(self._state, **self._robot_readout())  # the first state shows the real pose
        status = self.rig.robot.status()
        if status.held:  # an earlier session's e-stop or fault: motion only after an explicit reset
            self._state = replace(
                self._state,
                phase=Phase.FAULT.value,
                detail=f"the robot is {status.describe()} since before this controller started: Reset releases it",
            )
        self._publish_state()

    # -- publishing ------------------------------------------------------------------

    @property
    def state(self) -> ControllerState:
        return self._state

    def _update(self, **changes) -> None:
        self._state = replace(self._state, time_s=time.time(), **changes)
        self._publish_state()

    def _publish_state(self) -> None:
        for subscriber in list(self.state_subscribers):
            subscriber(self._state)

    def _publish_frame(self, view: FrameView) -> None:
        for subscriber in list(self.frame_subscribers):
            subscriber(view)

    def _robot_readout(self, bMe: Matrix | None = None) -> dict:
        """Flange pose (read from the robot unless given), joints and vacuum sensor for the state."""
        try:
            bMe = self.rig.robot.read_pose() if bMe is None else bMe
            holding = self.rig.gripper.holding()
        except RobotError as exc:  # the link is down: the state says so, the last readout stands
            log.warning("robot readout failed: %s", exc)
            return {}
        return {"bMe": bMe.tolist(), "q": self._joints_shown(bMe).tolist(), "holding_part": holding}

    def _joints_shown(self, bMe: Matrix) -> Matrix:
        if self.rig.cell is not None:  # the simulated cell's plant: its true joints
            return self.rig.cell.state.q
        try:
            self._shown_q = self.rig.robot.arm.ik(bMe, self._shown_q, tolerance_m=1e-6, tolerance_rad=1e-5, restarts=0).q
        except UnreachableTarget:
            log.debug("no joints found for the reported flange pose; the 3D arm keeps its last pose")
        return self._shown_q

    def look(self, fresh: bool = False) -> tuple[Frame, ImageFeatures]:
        """Grab one frame, detect in it and publish it (the live view while no run owns the camera).

        fresh: a frame exposed after this moment, never one a camera's buffer held through
          the last jog (docs/vision.md, "No stale frames"). Between commands the robot
          stands still, so such a frame shows where it stopped: what a capture needs, at
          the cost of the camera's latency, which the live view does not pay.
        """
        with self._lock:
            if self.running:
                raise CommandRefused(f"{self._work} owns the camera")
            camera = self.rig.camera
            frame = camera.read_after(self.rig.robot.clock_s()) if fresh else camera.read()
        features, _ = self.rig.extractor.extract(frame.image)
        self._publish_frame(FrameView(frame, features.corners_px, features.laser_spot_px, self._desired, None))
        return frame, features

    # -- guards ------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._run_thread is not None and not self._run_thread.finished.is_set()

    @property
    def in_motion(self) -> bool:
        """A run or a jog is moving the robot (the channel holds it if its last app goes away)."""
        return self.running or self._jogging.is_set()

    def _require(self, *phases: Phase) -> None:
        if self._estop.is_set():
            raise CommandRefused("e-stop is active: reset it first")
        if self.running:
            raise CommandRefused(f"{self._work} is under way")
        if Phase(self._state.phase) not in phases:
            allowed = " or ".join(p.value for p in phases)
            raise CommandRefused(f"not possible while {self._state.phase} (only when {allowed})")

    def _enable_motion(self) -> None:
        status = self.rig.robot.status()
        if status.alarm:
            raise CommandRefused(f"the robot is in alarm: {status.detail or 'reset the alarm on the JRC'}")
        if not status.servo_on:
            self.rig.robot.servo(True)

    # -- jogging and teaching ----------------------------------------------------------

    def jog(self, translation_m: Matrix, rotation_rad: Matrix = (0.0, 0.0, 0.0), frame: str = "base") -> None:
        """Move the flange by a small step: translation and rotation (rad) in the base or tool frame."""
        with self._lock:
            self._require(Phase.IDLE, Phase.TEACHING, Phase.DONE, Phase.FAULT)
            step = np.concatenate([np.asarray(translation_m, float), np.asarray(rotation_rad, float)])
            if step.shape != (6,) or not np.all(np.isfinite(step)):
                raise CommandRefused(f"a jog takes 3 finite translations and 3 rotations, got {step.tolist()}")
            if frame not in ("base", "tool"):
                raise CommandRefused(f"jog frame {frame!r}: choose base or tool")
            bMe = self.rig.robot.read_pose()
            # In the base frame: translation added, rotation about the flange's own origin.
            increment = exp_twist(np.concatenate([np.zeros(3), step[3:]]))
            increment[:3, 3] = step[:3]
            target = bMe @ exp_twist(step) if frame == "tool" else apply_increment(bMe, increment)
            self.move_to(target)

    def move_to(self, bMe_target: Matrix) -> None:
        """A linear move to a flange pose (the 3D gizmo, or a jog)."""
        with self._lock:
            self._require(Phase.IDLE, Phase.TEACHING, Phase.DONE, Phase.FAULT)
            self._enable_motion()
            self._jogging.set()
            try:
                self.rig.robot.move_linear(np.asarray(bMe_target, float), JOG_SPEED_M_S)
            except MotionStopped as exc:
                raise CommandRefused(f"the move was stopped: {exc}") from exc
            except (RobotError, UnreachableTarget) as exc:
                raise CommandRefused(f"move refused: {exc}") from exc
            finally:
                self._jogging.clear()
            self._update(**self._robot_readout())

    def begin_teach(self, template: str | None = None) -> None:
        """Start teaching a job, from scratch or from an existing job's poses and settings."""
        with self._lock:
            self._require(Phase.IDLE, Phase.DONE, Phase.FAULT)
            draft = TeachDraft()
            if template:
                job = self.store.load_job(template)
                # The images are captured again (the check view's goes with the desired one).
                draft = TeachDraft(
                    template,
                    None,
                    None,
                    job.start_bMe,
                    job.eMe_pick,
                    job.bMe_place,
                    job.threshold_px,
                    job.gain,
                    job.approach_m,
                    placement_tolerance_mm=job.placement_tolerance_mm,
                )
            self._draft = draft
            self._check_image = None
            # The job shown is the template taught from; a new job has none until it is saved.
            self._desired = None  # the last job's desired corners are no part of the new one
            self._update(
                phase=Phase.TEACHING.value,
                detail="jog to the desired view and capture it",
                job=template or None,
                teach_missing=draft.missing(),
                teach_optional=draft.optional_missing(),
                teach_poses=self._teach_poses(),
            )

    def _set_draft(self, detail: str, **changes) -> None:
        self._draft = replace(self._draft, **changes)
        self._update(
            detail=detail,
            teach_missing=self._draft.missing(),
            teach_optional=self._draft.optional_missing(),
            teach_poses=self._teach_poses(),
        )

    def _pocket_fit(self) -> PocketFit | None:
        """Where the taught pick and place set the desired image's part down, against the
        cell file's pocket; None until all three are taught, or without a [metal_part]."""
        draft, pocket = self._draft, self.rig.config.metal_part
        if pocket is None or draft.seen_bMo is None or draft.eMe_pick is None or draft.bMe_place is None:
            return None
        return pocket_fit(draft.bMe_place @ part_on_flange(draft.taught_bMe, draft.eMe_pick, draft.seen_bMo), pocket, PART_SIDE_M)

    def _teach_poses(self) -> dict:
        """The state's teach_poses for the draft."""
        draft, pocket = self._draft, self.rig.config.metal_part
        poses = {} if draft.taught_bMe is None else {"view_bMe": draft.taught_bMe.tolist()}
        if pocket is None or draft.seen_bMo is None or draft.eMe_pick is None:
            return poses
        eMo = part_on_flange(draft.taught_bMe, draft.eMe_pick, draft.seen_bMo)
        poses["pocket_bMe"] = flange_in_pocket(eMo, pocket, PART_SIDE_M, draft.seen_bMo).tolist()
        fit = self._pocket_fit()
        if fit is not None:
            poses["place_bMo"] = fit.bMo.tolist()
        return poses

    def _place_words(self) -> str:
        """The place check (said as soon as the place is taught): how far off the pocket's
        centre and how turned, modulo the part's quarter turns, every run will set the part
        down; a warning beyond the placement tolerance or PLACE_TURN_WARNING_DEG."""
        if self.rig.config.metal_part is None:
            return " (the cell file has no [metal_part]: no place check)"
        fit = self._pocket_fit()
        if fit is None:
            return ""
        if abs(fit.turn_deg) > PLACE_TURN_WARNING_DEG:
            return (
                f"; WARNING: {fit.words()}: the part in the desired image is turned {fit.turn_deg:+.1f} deg from "
                "how it must sit in the pocket; turn the cup by the opposite at the place, or teach the desired "
                "image with the part turned as the pocket is"
            )
        if fit.offset_mm > self._draft.placement_tolerance_mm:
            return f"; WARNING: {fit.words()}: beyond the placement tolerance; move the cup over the pocket's centre"
        return f": {fit.words()}"

    def capture_desired(self, part_side_m: float = PART_SIDE_M) -> DesiredImage:
        """Take the desired image here (Fig. C-2): the four corners and the laser spot must be seen."""
        with self._lock:
            self._require(Phase.TEACHING)
            frame, features = self.look(fresh=True)
            try:
                desired = desired_from_features(features, self.rig.config.nominal.camera, part_side_m)
            except TeachError as exc:
                raise CommandRefused(str(exc)) from exc
            self._desired = desired
            self._desired_image = frame.image
            taught_bMe = self.rig.robot.read_pose()
            self._set_draft(
                f"desired image captured, laser depth {1000 * desired.depth_m:.1f} mm",
                desired=desired,
                taught_bMe=taught_bMe,
                taught_model=TaughtModel.of(self.rig.config.nominal),
                seen_bMo=self._part_seen(taught_bMe, features.corners_px, part_side_m),
            )
            return desired

    def capture_check_view(self) -> CheckView:
        """Take the check view here: the part placed in the metal part, the camera over it
        seeing its four top-face corners. After each run the arm comes back here and the
        part's displacement from these corners is its placement error."""
        with self._lock:
            self._require(Phase.TEACHING)
            frame, features = self.look(fresh=True)
            if not features.all_corners_visible:
                raise CommandRefused(
                    "the check view must show the part's four top-face corners: put the part in "
                    "the metal part and the camera over it"
                )
            check = CheckView(check_bMe=self.rig.robot.read_pose(), corners_px=features.corners_px)
            self._check_image = frame.image
            self._set_draft(f"check view captured{self._place_check(check)}", check=check)
            return check

    def _part_seen(self, bMe: Matrix, corners_px: Matrix, side_m: float = PART_SIDE_M) -> Matrix | None:
        """bMo of the part from its four corners seen from bMe (None when the pose cannot be had)."""
        model = self.rig.config.nominal
        try:
            return bMe @ model.eMc @ pose_from_planar_points(corners_px, Cube(np.eye(4), side_m).corners_o, model.camera)
        except PoseEstimationError:
            return None

    def _place_check(self, check: CheckView) -> str:
        """The check view's part against where the taught pick and place put the part the
        desired image saw: the words to add to the state (a warning beyond the bounds)."""
        draft = self._draft
        if draft.seen_bMo is None or draft.eMe_pick is None or draft.bMe_place is None:
            return ""
        placed = self._part_seen(check.check_bMe, check.corners_px)
        if placed is None:
            return ""
        # The part held as the pick found it, set down by the place pose.
        expected = draft.bMe_place @ part_on_flange(draft.taught_bMe, draft.eMe_pick, draft.seen_bMo)
        offset_mm = 1000.0 * float(np.linalg.norm(placed[:2, 3] - expected[:2, 3]))
        turn = np.arctan2(placed[1, 0], placed[0, 0]) - np.arctan2(expected[1, 0], expected[0, 0])
        turn_deg = float(np.rad2deg(np.angle(np.exp(1j * turn))))
        where = f"the part lies {offset_mm:.1f} mm and {turn_deg:+.1f} deg from where the taught pick and place put it"
        if offset_mm > draft.placement_tolerance_mm or abs(turn_deg) > PLACE_TURN_WARNING_DEG:
            return (
                f"; WARNING: {where}: the part moved between the desired image and the pick, or slipped on "
                "the cup; teach the desired image, the pick and the place again on one part left where it lies"
            )
        return f": {where}"

    def set_start_pose(self) -> None:
        with self._lock:
            self._require(Phase.TEACHING)
            self._set_draft("start pose set here", start_bMe=self.rig.robot.read_pose())

    def set_pick_pose(self) -> None:
        """The cup is on the part now: store the motion from the desired view to here."""
        with self._lock:
            self._require(Phase.TEACHING)
            if self._draft.taught_bMe is None:
                raise CommandRefused("capture the desired image first: the pick is taught relative to it")
            eMe_pick = np.linalg.inv(self._draft.taught_bMe) @ self.rig.robot.read_pose()
            self._set_draft("pick pose set here", eMe_pick=eMe_pick)

    def set_place_pose(self) -> None:
        """The cup has carried the part into the metal part: the place pose is taught only
        with the part on the cup, so the vacuum sensor must say so."""
        with self._lock:
            self._require(Phase.TEACHING)
            if not self._holding():
                raise CommandRefused(
                    "the place pose is taught with the part on the cup, and the vacuum sensor "
                    "reports none: at the pick, Suction on, then carry the part into the metal part"
                )
            self._draft = replace(self._draft, bMe_place=self.rig.robot.read_pose())
            self._set_draft(f"place pose set here{self._place_words()}")

    def _holding(self) -> bool:
        try:
            return self.rig.gripper.holding()
        except RobotError as exc:
            raise CommandRefused(f"the vacuum sensor cannot be read: {exc}") from exc

    def suction(self, on: bool) -> bool:
        """Switch the cup's suction while teaching; whether the vacuum sensor then reports a part."""
        with self._lock:
            self._require(Phase.TEACHING)
            try:
                self.rig.gripper.set_vacuum(on)
            except RobotError as exc:
                raise CommandRefused(f"suction {'on' if on else 'off'}: {exc}") from exc
            holding = self._holding()
            sensor = "a part on the cup" if holding else "no part on the cup"
            self._update(detail=f"suction {'on' if on else 'off'}: the vacuum sensor reports {sensor}", **self._robot_readout())
            return holding

    def test_pick(self) -> bool:
        """Try the pick here, the way a run will: suction on, lift TEST_PICK_LIFT_M, read the
        vacuum sensor, put the part back down where it was and release it. Whether it held."""
        with self._lock:
            self._require(Phase.TEACHING)
            if self._holding():
                raise CommandRefused("the cup holds a part already: Suction off first")
            bMe = self.rig.robot.read_pose()
            lifted = bMe.copy()
            lifted[2, 3] += TEST_PICK_LIFT_M
            gripped = self.suction(True)
            held = False
            try:
                if gripped:
                    self.move_to(lifted)
                    held = self._holding()
                    self.move_to(bMe)
            finally:
                self.rig.gripper.set_vacuum(False)
            lift = f"{1000 * TEST_PICK_LIFT_M:.0f} mm"
            detail = (
                f"test pick: the part held through a {lift} lift and is back down: grip good"
                if held
                else f"test pick: the part fell during the {lift} lift: grip weak"
                if gripped
                else "test pick: no grip: the vacuum sensor reports no part after suction on "
                "(put the cup on the middle of the part's top face, pressed a few mm)"
            )
            self._update(detail=detail, **self._robot_readout())
            return held

    def set_settings(
        self, threshold_px: float, gain: float, approach_m: float, placement_tolerance_mm: float | None = None
    ) -> None:
        """The run's settings; the placement tolerance is kept unless given."""
        with self._lock:
            self._require(Phase.TEACHING)
            tolerance = self._draft.placement_tolerance_mm if placement_tolerance_mm is None else placement_tolerance_mm
            for name, value in (
                ("threshold_px", threshold_px),
                ("gain", gain),
                ("approach_m", approach_m),
                ("placement_tolerance_mm", tolerance),
            ):
                if not (np.isfinite(value) and value > 0):
                    raise CommandRefused(f"{name} must be a positive number, got {value!r}")
            self._set_draft(
                "settings changed", threshold_px=threshold_px, gain=gain, approach_m=approach_m, placement_tolerance_mm=tolerance
            )

    def save_job(self, name: str, description: str = "", part_side_m: float = PART_SIDE_M) -> Job:
        with self._lock:
            self._require(Phase.TEACHING)
            draft = self._draft
            if draft.missing():
                raise CommandRefused(f"cannot save yet: teach {', '.join(draft.missing())}")
            try:
                job = Job(
                    name=name,
                    description=description,
                    part_side_m=part_side_m,
                    desired=draft.desired,
                    taught_bMe=draft.taught_bMe,
                    start_bMe=draft.start_bMe,
                    eMe_pick=draft.eMe_pick,
                    bMe_place=draft.bMe_place,
                    approach_m=draft.approach_m,
                    threshold_px=draft.threshold_px,
                    gain=draft.gain,
                    check=draft.check,
                    placement_tolerance_mm=draft.placement_tolerance_mm,
                    taught_model=draft.taught_model,
                )
            except JobError as exc:
                raise CommandRefused(str(exc)) from exc
            self.store.save_job(job, self._desired_image, self._check_image if draft.check is not None else None)
            self._draft = None
            self._update(phase=Phase.IDLE.value, detail=f"job {name!r} saved", job=name, teach_missing=[], teach_optional=[])
            return job

    def cancel_teach(self) -> None:
        with self._lock:
            self._require(Phase.TEACHING)
            self._draft = None
            self._update(phase=Phase.IDLE.value, detail="teaching cancelled", teach_missing=[], teach_optional=[])

    def present_part(self, centre_mm: Sequence[float] | None = None, turn_deg: float = 0.0) -> None:
        """A new part on the table where the cell can (the simulated cell, or a test cell's
        fixture), whenever no run or commissioning moves the robot, teaching included: near
        where the demo job was taught, or with its top face's centre at ``centre_mm`` (X, Y
        in the base frame) turned ``turn_deg`` about the vertical. The cup lets go of a part
        it held."""
        with self._lock:
            self._require(Phase.IDLE, Phase.TEACHING, Phase.DONE, Phase.FAULT)
            hook = self.rig.present_part if centre_mm is None else self.rig.place_part
            if hook is None:
                raise CommandRefused("this cell has no part fixture: parts arrive by hand")
            try:
                if centre_mm is None:
                    self.rig.present_part(self.rng)
                else:
                    x, y = _part_origin(centre_mm, turn_deg)
                    self.rig.place_part(x, y, np.deg2rad(turn_deg))
            except (FixtureError, ValueError) as exc:
                raise CommandRefused(str(exc)) from None
            self._update(detail="a new part is on the table", **self._robot_readout())

    # -- assembly ------------------------------------------------------------------------

    def start(self, job_name: str, record: bool = True) -> int:
        """Start one assembly of ``job_name`` in the background; returns the run's id.

        The job is first retargeted to the cell file's model (core/production/retarget.py):
        a job taught through another calibration of the camera, hand-eye or laser sees
        the same part through this one."""
        with self._lock:
            self._require(Phase.IDLE, Phase.DONE, Phase.FAULT)
            model = self.rig.config.nominal
            try:
                stored = self.store.load_job(job_name)
                job = retarget(stored, model)
            except JobError as exc:
                raise CommandRefused(str(exc)) from exc
            note = retarget_note(stored, model)
            if note:
                log.info("job %r: %s", job.name, note)
            self._enable_motion()
            self._work = "an assembly run"
            run_id = self.store.start_run(job.name, self.rig.robot.name)
            self._desired, self._trail = job.desired, []
            self._update(
                phase=Phase.SERVOING.value,
                detail="starting",
                job=job.name,
                run_id=run_id,
                stage=None,
                iteration=0,
                error_px=None,
                last_outcome=None,
            )
            self._run_thread = _WorkThread(self._run, (job, run_id, record, note), "assembly")
            self._run_thread.start()
            return run_id

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until the run under way (if any) ends."""
        thread = self._run_thread
        if thread is not None:
            thread.finished.wait(timeout_s)

    def _run(self, job: Job, run_id: int, record: bool, note: str | None) -> None:
        """One run of ``job``, already retargeted to the cell's model; ``note`` says how (None: as taught)."""
        folder = self.store.run_folder(run_id)
        recorder, recording_note, recorded_to = None, None, None
        if record:
            try:
                recorder = RunRecorder(folder, {"job": job.name, "run": run_id, "desired": job.desired})
                recorded_to = folder
            except (RecordingError, OSError) as exc:  # a full disk, a leftover folder: run, and say so
                recording_note = f"not recorded: {exc}"
                log.error("run %d: %s", run_id, recording_note)
        perception = self.rig.perception()
        last_cycle_at = time.monotonic()

        def on_event(event: AssemblyEvent) -> None:
            nonlocal last_cycle_at, recorder, recording_note
            if isinstance(event, PhaseChange):
                if event.phase not in (Phase.DONE, Phase.FAULT, Phase.ESTOPPED):
                    self._update(phase=event.phase.value, detail=event.detail, **self._robot_readout())
                return
            cycle = event.cycle
            frame = perception.last_frame
            if recorder is not None:
                try:
                    recorder.record(frame, cycle_record(cycle))
                except (RecordingError, OSError) as exc:  # the disk filled up: the run goes on unrecorded
                    recording_note = f"recording stopped at cycle {cycle.iteration + 1}: {exc}"
                    log.error("run %d: %s", run_id, recording_note)
                    recorder = _closed_quietly(recorder)
            self._trail = (self._trail + [cycle.features.corners_px])[-TRAIL_LENGTH:]
            self._update(
                stage=cycle.output.stage,
                iteration=cycle.iteration + 1,
                error_px=float(cycle.output.error_px) if np.isfinite(cycle.output.error_px) else None,
                cVc=_finite_list(cycle.output.cVc),
                detail=cycle.output.note or self._state.detail,
                **self._robot_readout(cycle.measurement.bMe),
            )
            if frame is not None:
                self._publish_frame(
                    FrameView(frame, cycle.features.corners_px, cycle.features.laser_spot_px, job.desired, np.array(self._trail))
                )
            if self.cycle_period_s:
                time.sleep(max(0.0, self.cycle_period_s - (time.monotonic() - last_cycle_at)))
            last_cycle_at = time.monotonic()

        try:
            outcome = run_assembly(
                job,
                self.rig.robot,
                self.rig.gripper,
                perception,
                self.rig.config.nominal,
                self.rig.policy,
                speed_m_s=self.rig.config.motion.move_speed_m_s,
                on_event=on_event,
                measure_placement=self.rig.measure_placement,
                estopped=self._estop.is_set,
                locator=self.rig.locator,
            )
        except CameraSourceError as exc:
            outcome = AssemblyOutcome(
                Outcome.FAULT, f"camera: {exc}{hold_after_fault(self.rig.robot)}", float("nan"), None, 0.0, [], 0
            )
        except Exception as exc:  # a bug must still leave the robot held and the run on record
            log.exception("assembly run %d crashed", run_id)
            outcome = AssemblyOutcome(
                Outcome.FAULT, f"internal error: {exc!r}{hold_after_fault(self.rig.robot)}", float("nan"), None, 0.0, [], 0
            )
        if outcome.outcome is Outcome.ESTOPPED:
            outcome = replace(outcome, reason=self._estop_reason)
        if note:
            outcome = replace(outcome, notes=(*outcome.notes, note))
        if recorder is not None:
            try:
                recorder.close(outcome.summary())
            except (RecordingError, OSError) as exc:
                recording_note = f"the recording's summary was not written: {exc}"
        if recording_note:
            outcome = replace(outcome, notes=(*outcome.notes, recording_note))
        try:
            self.store.finish_run(
                run_id,
                outcome.outcome,
                outcome.reason,
                outcome.final_error_px,
                outcome.placement_error_mm,
                outcome.duration_s,
                outcome.stages,
                recorded_to,
            )
        except (sqlite3.Error, OSError) as exc:  # the next start marks it interrupted; the operator learns now
            log.error("run %d: its end could not be stored: %s", run_id, exc)
            outcome = replace(outcome, notes=(*outcome.notes, f"its end could not be stored: {exc}"))
        phase = Phase.ESTOPPED if self._estop.is_set() else Phase.FAULT if outcome.outcome is Outcome.FAULT else Phase.DONE
        self._update(phase=phase.value, detail=outcome.reason, last_outcome=outcome.summary(), **self._robot_readout())
        self.last_outcome = outcome

    # -- commissioning -----------------------------------------------------------------------

    def commission(
        self,
        steps: Sequence[Step | str] | None = None,
        out_path: str | Path | None = None,
        settings: CommissionSettings | None = None,
    ) -> Path:
        """Commission the cell in the background: the robot shows the camera the board and the
        chosen steps (default: all) measure the model (docs/commissioning.md). Progress, then
        the summary, are published in the state's ``commissioning``; the e-stop stops it
        between views (and any move under way at once). Returns the cell file Apply will
        write (default: ``commissioned_path``)."""
        from vservo.core.production.commissioning import ALL_STEPS, Commissioning, CommissionSettings, Step

        with self._lock:
            self._require(Phase.IDLE, Phase.DONE, Phase.FAULT)
            steps = ALL_STEPS if steps is None else steps
            try:
                chosen = [Step(step) for step in steps]
            except ValueError:
                raise CommandRefused(f"commissioning steps {list(steps)!r}: choose from {', '.join(Step)}") from None
            if not chosen:
                raise CommandRefused("choose at least one step to commission")
            out = Path(out_path) if out_path else commissioned_path(self.rig.config.source, self.store.root)
            if out.exists():
                raise CommandRefused(f"{out} exists: commissioning writes a new cell file, never over another")
            folder = out.with_name(out.stem + "-commissioning")
            rig = replace(self.rig, camera=_ShownCamera(self.rig.camera, self._publish_frame))
            try:
                commissioning = Commissioning(
                    rig, folder, settings or CommissionSettings(seed=self.seed), self._on_commission_progress, self._estop.is_set
                )
            except ConfigError as exc:
                raise CommandRefused(str(exc)) from exc
            self._enable_motion()
            self._commissioned, self._work = None, "commissioning"
            self._update(
                phase=Phase.COMMISSIONING.value,
                detail=f"commissioning {', '.join(chosen)}",
                commissioning={
                    "steps": [str(step) for step in chosen],
                    "out": str(out),
                    "step": None,
                    "progress": {},
                    "summary": None,
                    "error": None,
                    "applied": None,
                },
            )
            self._run_thread = _WorkThread(self._commission, (commissioning, chosen, out, folder), "commissioning")
            self._run_thread.start()
            return out

    def _on_commission_progress(self, progress: Progress) -> None:
        record = self._state.commissioning
        line = {"done": progress.done, "total": progress.total, "note": progress.note}
        self._update(
            detail=f"commissioning: {progress.step} {progress.done}/{progress.total}",
            commissioning={**record, "step": progress.step, "progress": {**record["progress"], progress.step: line}},
            **self._robot_readout(),
        )

    def _commission(self, commissioning: Commissioning, steps: list[Step], out: Path, folder: Path) -> None:
        """The commissioning thread: on success the result waits for Apply; any failure
        leaves the robot held, and the state says why."""
        from vservo.core.production.commissioning import CommissioningError, commission_summary

        try:
            result = commissioning.run(steps)
        except Exception as exc:  # a bug as much as a stop must leave the robot held
            if self._estop.is_set():
                error, phase = self._estop_reason, Phase.ESTOPPED
            else:
                if not isinstance(exc, CommissioningError):
                    log.exception("commissioning crashed")
                error, phase = f"{exc}{hold_after_fault(self.rig.robot)}", Phase.FAULT
            self._update(
                phase=phase.value,
                detail=f"commissioning stopped: {error}",
                commissioning={**self._state.commissioning, "error": error},
                **self._robot_readout(),
            )
            return
        self._commissioned = Commissioned(result, out, folder, steps)
        retakes = [str(step) for step, step_result in result.steps.items() if not step_result.verdict.good]
        detail = (
            f"commissioned: every step good; Apply writes {out}"
            if not retakes
            else f"commissioned: {', '.join(retakes)} say{'s' if len(retakes) == 1 else ''} retake"
        )
        self._update(
            phase=Phase.IDLE.value,
            detail=detail,
            commissioning={**self._state.commissioning, "summary": commission_summary(result)},
            **self._robot_readout(),
        )

    def apply_commissioning(self) -> Path:
        """Write the commissioned cell file and run on its model from now on: the cell's
        model, the feature extractor and the part locator are rebuilt from it. Refused when
        a step says retake or nothing was commissioned; a file whose devices differ from
        the running ones is written, but the controller must be restarted on it."""
        from vservo.core.production.commissioned_file import commissioned_tables, write_commissioned_cell

        with self._lock:
            self._require(Phase.IDLE, Phase.DONE, Phase.FAULT)
            done = self._commissioned
            if done is None:
                raise CommandRefused("nothing to apply: commission the cell first (a commissioning is applied once)")
            retakes = [f"{step}: {r.verdict.reason}" for step, r in done.result.steps.items() if not r.verdict.good]
            if retakes:
                raise CommandRefused("a step says retake; commission it again: " + "; ".join(retakes))
            running = self.rig.config
            try:
                tables, _ = read_cell_data(None if is_shipped_cell(running.source) else running.source)
                write_commissioned_cell(
                    running.source,
                    commissioned_tables(tables, done.result, done.out_path, done.folder, done.steps),
                    done.out_path,
                )
                self._commissioned = None
                config = load_cell(done.out_path)
                changed = [name for name, device in DEVICES.items() if device(config) != device(running)]
                if changed:
                    raise CommandRefused(
                        f"{done.out_path} is written, but its {', '.join(changed)} differ from the "
                        f"running cell's: restart the controller with --cell {done.out_path}"
                    )
                locator = PartLocator.from_config(config)
            except (ConfigError, OSError) as exc:
                raise CommandRefused(f"apply: {exc}") from exc
            self.rig.config, self.rig.extractor, self.rig.locator = config, extractor_for(config), locator
            self._update(
                cell_file=config.source,
                detail=f"the controller's model is now {config.source}",
                commissioning={**self._state.commissioning, "applied": config.source},
            )
            return done.out_path

    # -- safety ----------------------------------------------------------------------------

    def estop(self, why: str = "e-stop pressed") -> None:
        """Hold the robot now and refuse every move until reset (never waits for a lock, never raises).

        ``why`` is what the state, the log and the run's record say stopped it. The hold
        goes out from its own thread: a link that went silent in the middle of another
        thread's request keeps the line until that request's timers run out (tens of
        seconds on the factory timers), and the operator must not wait for it. After
        HOLD_CONFIRM_S without the JRC's answer the state says the hold is not confirmed
        and why; it says "robot held" (or that the hold failed) once the answer comes.
        """
        self._estop_reason = why
        self._estop.set()
        pending = (
            f"{why}: hold NOT confirmed after {HOLD_CONFIRM_S:g} s (the robot link is silent or busy): use the pendant's e-stop"
        )
        settled = threading.Lock()  # the answer and the timeout: whichever comes first writes the state
        answer: dict[str, str | bool] = {}
        answered = threading.Event()

        def send_hold() -> None:
            try:
                self.rig.robot.emergency_stop(why)
                detail = f"{why}: robot held"
            except RobotError as exc:
                detail = f"{why}: hold could not be sent ({exc}); use the pendant's e-stop"
            except Exception as exc:  # a bug must not hide that the hold was not sent
                log.exception("e-stop: sending the hold failed")
                detail = f"{why}: hold could not be sent ({exc!r}); use the pendant's e-stop"
            log.warning(detail)
            with settled:
                answer["detail"] = detail
                answered.set()
                if answer.get("late") and self._state.detail == pending:  # nothing newer said since
                    self._update(phase=Phase.ESTOPPED.value, detail=detail)

        threading.Thread(target=send_hold, name="estop-hold", daemon=True).start()
        answered.wait(HOLD_CONFIRM_S)
        with settled:
            if "detail" not in answer:
                answer["late"] = True
                log.error(pending)
            self._update(phase=Phase.ESTOPPED.value, detail=str(answer.get("detail", pending)))

    def reset(self) -> None:
        """Clear an e-stop or a fault once the run has stopped: open again a device lost
        with the fault (the robot's port, the camera), release the hold, back to idle."""
        if self.running:
            raise CommandRefused("the run is still stopping; try again")
        with self._lock:
            if Phase(self._state.phase) not in (Phase.ESTOPPED, Phase.FAULT, Phase.DONE):
                raise CommandRefused(f"nothing to reset while {self._state.phase}")
            try:
                self.rig.reconnect()
            except RobotError as exc:
                raise CommandRefused(f"reset failed: the robot link: {exc}") from exc
            except CameraSourceError as exc:
                raise CommandRefused(f"reset failed: the camera: {exc}") from exc
            try:
                self.rig.robot.reset_emergency_stop()
                self.rig.robot.reset_alarms()
                self.rig.robot.hold(False)
            except RobotError as exc:
                raise CommandRefused(f"reset failed: {exc}") from exc
            self._estop.clear()
            self._update(phase=Phase.IDLE.value, detail="reset: ready", **self._robot_readout())

    def close(self) -> None:
        """Stop: hold the robot if a run is under way, then release the devices."""
        if self.running:
            self.estop("e-stop: the controller process is stopping")
            self.wait(10.0)
        self.rig.close()


def run_job_once(controller: CellController, job_name: str) -> dict:
    """One headless assembly (``vservo run``): a new part where the cell can present one,
    start, wait. The command is the operator's explicit go: a hold left by an earlier
    session's fault is released first, as its Reset would."""
    if controller.state.phase == Phase.FAULT.value:
        controller.reset()
    if controller.rig.present_part is not None:
        controller.present_part()
    run_id = controller.start(job_name)
    controller.wait()
    return {**controller.last_outcome.summary(), "job": job_name, "run_id": run_id}
