"""One-click assembly (Fig. C-3): servo on the taught image, pick the part, place it.

The sequence, as the thesis's cell ran it: move to the job's start pose (the part's
area in view), servo with the job's control law until the feature error is below the
taught threshold (3 px), move the fixed taught transform eMe_pick so the vacuum cup
meets the part, suction on (the vacuum sensor must confirm the grip), lift, move over
the taught place pose, lower into the metal part, release, retreat. A part turned from
its taught orientation is served on the taught view turned by the quarter turns its
symmetry allows that turn the camera least, decided in the image (core/production/grasp.py);
the pick and the place are then the taught ones, so nothing from the servo's end to the
release rests on the hand-eye or the intrinsics: the end effector ends at the taught pose
relative to the part, turned with it, and the pick is "a fixed transformation for any
object position" (section 5.3.2). When the job has a
check view, move to its check pose and measure the placement from a frame exposed after
that move (core/production/placement_check.py): the part is placed when it is seen within
the job's tolerance, missed beyond it or when it is not seen at all.

Every motion goes through the safety layer to a RobotBackend, so the same sequence
drives the simulator and the JRC. The run reports its phase changes and servo cycles to ``on_event``; it
never decides on its own to move after a fault: any refusal or failure ends it with the
robot held. An e-stop holds the robot from outside (the controller process does it at
once); the next move is then refused and the run ends as e-stopped (``Outcome.ESTOPPED``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from vservo.core.cell.config import CellModel
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.cell.scene import Cube
from vservo.core.geometry.pose_estimation import PoseEstimationError, pose_from_planar_points
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import DesiredImage, ImageFeatures
from vservo.core.perception.measurement import Measurement
from vservo.core.perception.vision.pipeline import CameraPerception
from vservo.core.production.exposure_matched import ExposureMatchedCamera
from vservo.core.production.grasp import GraspChoice, ViewTurn, grasp_choice, turned_desired, turned_goal, view_turns
from vservo.core.production.jobs import Job, TaughtModel
from vservo.core.production.locate import LocateError, PartLocator
from vservo.core.production.placement_check import CheckView, PlacementCheck, check_placement
from vservo.core.production.protocol.catalogue import RunEnd
from vservo.core.production.protocol.state import Outcome, Phase, RunOutcome
from vservo.core.production.retarget import desired_view_for_part, start_pose_for_part
from vservo.core.robot.backend import RobotBackend, RobotError
from vservo.core.robot.gripper import VacuumGripper
from vservo.core.robot.safety import SafetyLayer, SafetyRefusal
from vservo.core.servo.joint_limits import JointLimitedSteps, JointLimitSettings
from vservo.core.servo.laws.base import Failure
from vservo.core.servo.loop import Cycle, LoopLimits, MeasurementSource, Perception, ServoOutcome, run_servo
from vservo.core.servo.methods import LawSettings, build_law
from vservo.core.servo.step_policy import StepPolicy, StreamedVelocity

log = logging.getLogger("vservo.assembly")
# A miss seen by the check view is confirmed on a frame exposed this long after it (host
# seconds): a frame that waited in the camera stream's buffers for longer than that while
# the host was too busy to read it is beyond what a cell's PC is expected to do.
CONFIRMING_LOOK_AFTER_S = 1.0


@dataclass(frozen=True)
class PhaseChange:
    phase: Phase
    detail: str


@dataclass(frozen=True)
class ServoCycle:
    cycle: Cycle


AssemblyEvent = PhaseChange | ServoCycle


@dataclass(frozen=True)
class AssemblyOutcome:
    """How a run ended, and why.

    placement_error_mm is where the part ended as the camera saw it from the job's check
    pose (None when the job has no check view or the run did not get that far; NaN when
    the part was not found there). The gauge figures are a test cell's own measure of the
    same (the simulated cell's truth), None on a cell without one: they decide the
    outcome only for a job without a check view.
    """

    outcome: Outcome
    reason: str
    final_error_px: float
    placement_error_mm: float | None
    duration_s: float
    stages: list[dict]
    iterations: int
    gauge_placement_error_mm: float | None = None
    gauge_inside: bool | None = None
    notes: tuple[str, ...] = ()  # what the operator should know of how the job was run (retargeting)
    cell_time_s: float | None = None  # the cell clock's time for the run (RobotBackend.cell_clock_s)
    cell_time_by_phase_s: dict[str, float] | None = None  # the same, split by CellTimePhase (the phases run)
    end: RunEnd | None = None  # why, as the catalogue explains it to the operator (protocol/catalogue.py)

    def summary(self) -> dict:
        """The JSON object of ``vservo run --json``."""
        return {
            "outcome": self.outcome,
            "reason": self.reason,
            "final_error_px": _rounded(self.final_error_px),
            "placement_error_mm": _rounded(self.placement_error_mm),
            "gauge_placement_error_mm": _rounded(self.gauge_placement_error_mm),
            "gauge_inside": self.gauge_inside,
            "duration_s": round(self.duration_s, 3),
            "cell_time_s": _rounded(self.cell_time_s),
            "cell_time_by_phase_s": None
            if self.cell_time_by_phase_s is None
            else {phase: _rounded(seconds) for phase, seconds in self.cell_time_by_phase_s.items()},
            "iterations": self.iterations,
            "stages": self.stages,
            "notes": list(self.notes),
        }

    def record(self) -> RunOutcome:
        """How the run ended, as the controller publishes it (the figures rounded as in ``summary``)."""
        return RunOutcome(
            self.outcome,
            self.reason,
            final_error_px=_rounded(self.final_error_px),
            placement_error_mm=_rounded(self.placement_error_mm),
            duration_s=round(self.duration_s, 3),
            iterations=self.iterations,
            notes=self.notes,
            end=self.end,
            cell_time_s=_rounded(self.cell_time_s),
        )


def _rounded(value: float | None) -> float | None:
    return None if value is None or not np.isfinite(value) else round(float(value), 4)


class CellTimePhase(StrEnum):
    """The parts of a run its cell time is split into (``cell_time_by_phase_s``)."""

    LOCATE = "locate"  # the survey move and its frame
    START = "start"  # the move to the start pose
    SERVO = "servo"
    PICK = "pick"  # down onto the part, suction, up
    PLACE = "place"  # over the metal part, down, release, up
    CHECK = "check"  # the move to the check pose and its frame


class CellTimer:
    """The cell clock's time spent in each CellTimePhase, in the order they ran; they add
    up to the run's."""

    def __init__(self, robot: RobotBackend) -> None:
        self.robot = robot
        self.started_s = robot.cell_clock_s()
        self._phase: CellTimePhase | None = None
        self._since_s = self.started_s
        self.by_phase: dict[str, float] = {}

    def enter(self, phase: CellTimePhase) -> None:
        self._close()
        self._phase = phase

    def total_s(self) -> float:
        self._close()
        return self._since_s - self.started_s

    def _close(self) -> None:
        if self._phase is None:  # before the first phase: its time counts in the first
            return
        now_s = self.robot.cell_clock_s()
        self.by_phase[self._phase.value] = self.by_phase.get(self._phase.value, 0.0) + now_s - self._since_s
        self._since_s = now_s


@dataclass(frozen=True)
class PlacementReport:
    """What the cell measures of a placed part: inside the pocket, and by how much it is off."""

    inside: bool
    error_mm: float


@dataclass(frozen=True)
class FlangeReadout:
    """The servo loop's measurement on a cell whose features come from camera frames:
    the flange pose as the JRC reports it (SafetyLayer.pose: the target of the last move,
    which it reported done, without a reading), the joints the arm's model puts it at (for
    the joint limits in the law), nothing projected."""

    robot: SafetyLayer

    def measure(self, look: bool = False) -> Measurement:
        bMe = self.robot.pose()
        return Measurement.flange_only(self.robot.clock_s(), self.robot.model_joints(bMe), bMe)


def joint_limited_steps(robot: SafetyLayer) -> JointLimitedSteps:
    """The servo's steps bent around the joint limits of the safety layer's arm model,
    stopping the joints outside its [safety] joint margin (whose check they must pass)."""
    defaults, margin_rad = JointLimitSettings(), robot.limits.joint_margin_rad
    return JointLimitedSteps(
        robot.arm, JointLimitSettings(band_rad=defaults.band_rad + margin_rad, margin_rad=defaults.margin_rad + margin_rad)
    )


def lifted(bMe: Matrix, height_m: float) -> Matrix:
    """The pose ``height_m`` straight above bMe (base z up)."""
    above = np.array(bMe, dtype=float)
    above[2, 3] += height_m
    return above


# A move that turns the flange about the vertical by more than this may go either way round
# (the straight move's turn is the shorter one, and a half turn has two): the arm's model and
# the controller may then part on which, and the wrist wind a turn without either saying so.
AMBIGUOUS_TURN_RAD = np.radians(150.0)


def winds_up(poses: list[Matrix | None]) -> bool:
    """Whether straight moves through ``poses`` (None skipped) and back to the first turn the
    flange a full turn about the vertical, or may (a move near a half turn): each move turns
    it the shorter way, so the turns add up to a multiple of 360 deg, and a run that adds one
    winds the wrist towards joint 6's limit run after run (the arm's model follows its joints
    continuously)."""
    yaws = [float(np.arctan2(bMe[1, 0], bMe[0, 0])) for bMe in poses if bMe is not None]
    if not yaws:
        return False
    turns = np.diff(np.unwrap(np.array([*yaws, yaws[0]])))
    return abs(float(turns.sum())) > np.pi or bool(np.any(np.abs(turns) > AMBIGUOUS_TURN_RAD))


def _grasp_detail(grasp: GraspChoice, symmetry: int) -> str:
    turned = (
        f"the taught grasp turned {grasp.quarter_turns * 90} deg about the cup" if grasp.quarter_turns else "the taught grasp"
    )
    skipped = f"; {len(grasp.refused_nearer)} nearer out of reach" if grasp.refused_nearer else ""
    turning = f"the flange turning {np.degrees(grasp.turn_rad):.0f} deg"
    return f"picking and placing at {turned} (grasp symmetry {symmetry}), {turning}{skipped}"


def _turn_detail(turn: ViewTurn, symmetry: int) -> str:
    view = f"the taught view turned {turn.quarter_turns * 90} deg" if turn.quarter_turns else "the taught view"
    seen = "" if np.isnan(turn.image_turn_rad) else f", the camera to turn about {np.degrees(turn.image_turn_rad):.0f} deg"
    return f"servoing on {view} (grasp symmetry {symmetry}){seen}"


def hold_after_fault(robot: RobotBackend) -> str:
    """Hold the robot after a run failed; what to add to the fault's reason when even the
    hold fails (the link went with the fault), the reason itself standing."""
    try:
        robot.hold(True)
    except RobotError as exc:
        log.error("hold after a fault failed: %s", exc)
        return f"; the robot could not be held ({exc}): use the pendant's e-stop"
    return ""


@dataclass(frozen=True)
class RunSettings:
    """What a run takes besides the job and the rig: the taught moves' speed (approach and
    press at half), the servo's limits, and the cell's hooks."""

    speed_m_s: float = 0.05
    limits: LoopLimits = LoopLimits()
    on_event: Callable[[AssemblyEvent], None] = lambda event: None
    measure_placement: Callable[[], PlacementReport | None] = lambda: None
    estopped: Callable[[], bool] = lambda: False
    locator: PartLocator | None = None


def run_assembly(
    job: Job,
    robot: SafetyLayer,
    gripper: VacuumGripper,
    perception: Perception,
    model: CellModel,
    policy: StepPolicy,
    *,
    speed_m_s: float = 0.05,
    limits: LoopLimits = LoopLimits(),
    on_event: Callable[[AssemblyEvent], None] = lambda event: None,
    measure_placement: Callable[[], PlacementReport | None] = lambda: None,
    estopped: Callable[[], bool] = lambda: False,
    locator: PartLocator | None = None,
) -> AssemblyOutcome:
    """Run the job once; the robot must be connected with servo power on.

    Taught moves (start, pick, place, check) go out as one linear move each, checked along
    their whole line first (SafetyLayer.move_linear), a locating job's moves to its survey pose and on to the
    located part's start pose as joint moves (SafetyLayer.move_joint); the servo's steps
    as the step policy makes them.
    """
    settings = RunSettings(speed_m_s, limits, on_event, measure_placement, estopped, locator)
    return AssemblySequence(job, robot, gripper, perception, model, policy, settings).run()


class AssemblySequence:
    """One run of a job, a method per step of Fig. C-3: locate (a locating job), the start
    pose, the servo, the pick, the place, the check view, the verdict. A step that can end
    the run returns its AssemblyOutcome, or what the next step needs."""

    def __init__(
        self,
        job: Job,
        robot: SafetyLayer,
        gripper: VacuumGripper,
        perception: Perception,
        model: CellModel,
        policy: StepPolicy,
        settings: RunSettings,
    ) -> None:
        self.job, self.robot, self.gripper, self.perception = job, robot, gripper, perception
        self.model, self.policy, self.settings = model, policy, settings
        self.started_s = time.monotonic()
        self.timer = CellTimer(robot)
        self.servo: ServoOutcome | None = None
        self.start_bMe: Matrix | None = None  # where this run started from (the next starts there again)

    def run(self) -> AssemblyOutcome:
        seen = None
        try:
            # Read where the arm stands once: it may have been moved since the last run (the
            # pendant, another program); from here on each move's end is its target.
            self.robot.read_pose()
            start_bMe = self.job.start_bMe
            if self.job.survey_bMe is not None:
                located = self._locate(self.job.survey_bMe)
                if isinstance(located, AssemblyOutcome):
                    return located
                start_bMe = located
            self._to_start(start_bMe)
            desired = self._turned_view()
            if isinstance(desired, AssemblyOutcome):
                return desired
            servo = self._servo(desired)
            if isinstance(servo, AssemblyOutcome):
                return servo
            grasp = self._pick(servo)
            if isinstance(grasp, AssemblyOutcome):
                return grasp
            self._place(grasp)
            if self.job.check is not None:
                seen = self._look_at_the_placed_part(self.job.check)
        except (RobotError, UnreachableTarget) as exc:
            return self._end(Outcome.FAULT, f"robot: {exc}", RunEnd.ROBOT_FAULT)
        return self._verdict(seen)

    def _say(self, phase: Phase, detail: str) -> None:
        self.settings.on_event(PhaseChange(phase, detail))

    def _move(self, target: Matrix, speed_m_s: float | None = None) -> None:
        self.robot.move_linear(target, self.settings.speed_m_s if speed_m_s is None else speed_m_s)

    def _locate(self, survey_bMe: Matrix) -> Matrix | AssemblyOutcome:
        """Survey the table, locate the part and check the servo's goal over it is reachable:
        the start pose for the part where it lies."""
        job, robot, speed_m_s = self.job, self.robot, self.settings.speed_m_s
        if self.settings.locator is None:
            return self._end(
                Outcome.FAULT,
                "the job locates its part and this cell has no network to locate it with: "
                "commission the nn step (docs/commissioning.md)",
                RunEnd.NO_NETWORK,
            )
        self.timer.enter(CellTimePhase.LOCATE)
        self._say(Phase.SERVOING, "surveying the table for the part")
        # Transfers over the table on the joint-space line: the straight one between two far
        # tool-down poses can leave the arm's thin tool-down shell (SafetyLayer.joint_path).
        robot.move_joint(survey_bMe, speed_m_s)
        # A frame exposed after the move ended, from the pose the robot reports.
        survey = self.perception.perceive(FlangeReadout(robot).measure(), robot.clock_s())
        try:
            located = self.settings.locator.locate(survey.corners_px, robot.pose(), job.part_side_m)
        except LocateError as exc:
            return self._end(Outcome.FAULT, f"locate: {exc}", RunEnd.LOCATE_FAILED)
        taught = job.taught_model or TaughtModel.of(self.model)
        where = f"part located at ({1000 * located.bMo[0, 3]:.1f}, {1000 * located.bMo[1, 3]:.1f}) mm"
        try:  # a goal out of reach would servo until stuck against a joint limit
            goal_bMe = desired_view_for_part(job, taught, located.bMo)
            robot.check_target(goal_bMe, speed_m_s, bMe_now=goal_bMe)
        except (SafetyRefusal, UnreachableTarget) as exc:
            refused = f"{where}, out of the arm's reach: the servo's goal over it is refused ({exc})"
            return self._end(Outcome.FAULT, refused, RunEnd.GOAL_OUT_OF_REACH)
        self._say(Phase.SERVOING, where)
        return start_pose_for_part(job, taught, located.bMo)

    def _to_start(self, start_bMe: Matrix) -> None:
        self.start_bMe = start_bMe
        self.timer.enter(CellTimePhase.START)
        self._say(Phase.SERVOING, "moving to the start pose")
        # A wrist wound a turn by the runs before would meet its limit in the servo's turn.
        wound = self.robot.wound(start_bMe)
        if self.job.survey_bMe is None and not wound:
            self._move(start_bMe)
        else:
            self.robot.move_joint(start_bMe, self.settings.speed_m_s, unwind=wound)

    def _turned_view(self) -> DesiredImage | AssemblyOutcome:
        """The taught view turned as the part's symmetry allows to turn the camera least,
        decided from a frame at the start pose (core/production/grasp.py); of those whose
        servo goal, pick and place the arm's model predicts in reach, the first. The
        prediction rests on the model (the part's pose from the corners seen, through the
        nominal camera and hand-eye): it only chooses and refuses, it positions nothing."""
        job = self.job
        self.timer.enter(CellTimePhase.SERVO)  # choosing the servo's goal is the servo's work
        features = self.perception.perceive(FlangeReadout(self.robot).measure(), self.robot.clock_s())
        turns = view_turns(features.corners_px, job.desired, job.part_side_m, job.grasp_symmetry)
        refusals = []
        for turn in turns:
            desired = turned_desired(job.desired, job.part_side_m, turn.quarter_turns)
            refusal = self._goal_refusal(features, turn.quarter_turns)
            if refusal is None:
                self._say(Phase.SERVOING, _turn_detail(turn, job.grasp_symmetry))
                return desired
            refusals.append(f"turned {turn.quarter_turns * 90} deg: {refusal}")
        turned = "" if np.isnan(turns[0].image_turn_rad) else f" (seen turned {np.degrees(turns[0].image_turn_rad):.0f} deg)"
        return self._end(
            Outcome.FAULT,
            f"refused before moving on: the part{turned} cannot be picked at any of the taught view's turns its grasp "
            f"symmetry {job.grasp_symmetry} allows, the arm cannot reach them ({'; '.join(refusals)}): "
            "present the part nearer its taught place and turn",
            RunEnd.GRASP_OUT_OF_REACH,
        )

    def _goal_refusal(self, features: ImageFeatures, quarter_turns: int) -> str | None:
        """Why the servo's goal at the taught view turned ``quarter_turns``, or the pick and
        place from there, is out of the arm's reach as predicted (grasp.turned_goal); None when
        in reach or not predictable (a corner unseen: the check after the servo still
        refuses before the pick)."""
        job = self.job
        if not features.all_corners_visible:
            return None
        taught = job.taught_model or TaughtModel.of(self.model)
        model = self.model
        try:
            cMo = pose_from_planar_points(features.corners_px, Cube(np.eye(4), job.part_side_m).corners_o, model.camera)
        except PoseEstimationError:
            return None
        bMo_now = self.robot.pose() @ model.eMc @ cMo
        bMo_taught = job.taught_bMe @ taught.eMc @ job.desired.cdMo
        bMe_goal = turned_goal(job.taught_bMe, bMo_taught, bMo_now, job.part_side_m, quarter_turns)
        try:
            self.robot.check_target(bMe_goal, self.settings.speed_m_s, bMe_now=bMe_goal)
        except (SafetyRefusal, UnreachableTarget) as exc:
            return f"the servo's goal is refused ({exc})"
        choice, refused = self._grasp(bMe_goal)
        return None if choice is not None else "; ".join(refused)

    def _grasp(self, bMe_end: Matrix) -> tuple[GraspChoice | None, tuple[str, ...]]:
        """The grasp from the servo's end at bMe_end that turns the flange least and that the
        arm can make (grasp.grasp_choice), or None and why none can be made; of those, one
        whose turns through the run add up to none (``winds_up``) where there is one."""
        job = self.job
        bMe_check = None if job.check is None else job.check.check_bMe

        def choose(unwound: bool) -> tuple[GraspChoice | None, tuple[str, ...]]:
            def refusal(bMe_pick: Matrix, bMe_place: Matrix) -> str | None:
                if unwound and winds_up([self.start_bMe, bMe_end, bMe_pick, bMe_place, bMe_check]):
                    return "it would wind the wrist a full turn over the run, or may (a move near a half turn)"
                return self._pick_and_place_refusal(bMe_end, bMe_pick, bMe_place, bMe_check)

            return grasp_choice(
                bMe_end, job.eMe_pick, job.bMe_place, self.model.eMv, job.grasp_symmetry, refusal, bMe_next=bMe_check
            )

        chosen = choose(unwound=self.start_bMe is not None)
        return chosen if chosen[0] is not None else choose(unwound=False)

    def _pick_and_place_refusal(
        self, bMe_end: Matrix, bMe_pick: Matrix, bMe_place: Matrix, bMe_check: Matrix | None
    ) -> str | None:
        """Why the moves from the servo's end at bMe_end to the pick, on to the place and the
        check pose do not pass the safety layer's checks (the arm's kinematic model only);
        None when they do."""
        approach_m, speed_m_s = self.job.approach_m, self.settings.speed_m_s
        legs = [
            ("the pick", [bMe_end, lifted(bMe_pick, approach_m), bMe_pick], [speed_m_s, speed_m_s / 2]),
            (
                "the place",
                [lifted(bMe_pick, approach_m), lifted(bMe_place, approach_m), bMe_place],
                [speed_m_s, speed_m_s / 2],
            ),
        ]
        if bMe_check is not None:
            legs.append(("the check view", [lifted(bMe_place, approach_m), bMe_check], [speed_m_s]))
        for name, poses, speeds in legs:
            try:
                for bMe_from, bMe_to, speed in zip(poses, poses[1:], speeds):
                    self.robot.linear_path(bMe_from, bMe_to, speed)
            except (SafetyRefusal, UnreachableTarget) as exc:
                return f"{name} is refused ({exc})"
        return None

    def _servo(self, desired: DesiredImage) -> ServoOutcome | AssemblyOutcome:
        """Servo on the (turned) taught image until the feature error is below the job's threshold."""
        job = self.job
        self.timer.enter(CellTimePhase.SERVO)
        self._say(Phase.SERVOING, f"servoing with the {job.method} method")
        settings = LawSettings(method=job.method, gain=job.gain, final_threshold_px=job.threshold_px, laser_law=job.laser_law)
        law = build_law(self.model, settings)
        cell: MeasurementSource = FlangeReadout(self.robot)
        perception = self.perception
        streamed = isinstance(self.policy, StreamedVelocity)
        if streamed:  # frame after frame with the pose at each exposure (core/production/exposure_matched.py)
            if not isinstance(perception, CameraPerception):
                raise RobotError("a streamed servo needs the camera's frames: this rig's perception has none")
            cell = perception = ExposureMatchedCamera(perception, self.robot)
        self.servo = run_servo(
            cell,
            law,
            desired,
            self.model,
            self.policy,
            self.settings.limits,
            on_cycle=lambda cycle: self.settings.on_event(ServoCycle(cycle)),
            perception=perception,
            robot=self.robot,
            joint_limits=joint_limited_steps(self.robot),
        )
        if streamed and not self.settings.estopped():
            self.robot.stop_motion()  # the last twist may still be held: the pick starts from a standing arm
        if self.servo.converged:
            return self.servo
        failure = self.servo.failure or Failure.ROBOT_STOPPED  # a servo that neither converged nor said why was stopped
        return self._end(Outcome.FAULT, f"servo failed: {failure.value} ({self.servo.reason})", RunEnd(failure.value))

    def _pick(self, servo: ServoOutcome) -> GraspChoice | AssemblyOutcome:
        """Down onto the part at the taught transform from the servo's end (turned about the
        cup as the part's symmetry allows, to turn the flange least), suction on, the grip
        confirmed, up; refused before it moves when the arm can make no such pick and place."""
        job = self.job
        self.timer.enter(CellTimePhase.PICK)
        self._say(Phase.PICKING, f"servo converged, feature error {servo.final_error_px:.2f} px")
        grasp, refused = self._grasp(self.robot.pose())
        if grasp is None:
            return self._end(
                Outcome.FAULT,
                f"refused before the pick, the arm cannot reach it: {'; '.join(refused)}: "
                "present the part nearer its taught place and turn",
                RunEnd.GRASP_OUT_OF_REACH,
            )
        self._say(Phase.PICKING, _grasp_detail(grasp, job.grasp_symmetry))
        self._move(lifted(grasp.bMe_pick, job.approach_m))
        self._move(grasp.bMe_pick, self.settings.speed_m_s / 2)
        self.gripper.set_vacuum(True)
        if not self.gripper.holding():
            self.gripper.set_vacuum(False)
            return self._end(Outcome.FAULT, "the vacuum sensor reports no part on the cup after suction on", RunEnd.NO_GRIP)
        self._move(lifted(grasp.bMe_pick, job.approach_m))
        return grasp

    def _place(self, grasp: GraspChoice) -> None:
        """Over the metal part, down at the taught place pose (turned about the cup as the pick
        was), release, up."""
        job, speed_m_s = self.job, self.settings.speed_m_s
        self.timer.enter(CellTimePhase.PLACE)
        self._say(Phase.PLACING, "carrying the part to the metal part")
        self._move(lifted(grasp.bMe_place, job.approach_m))
        self._move(grasp.bMe_place, speed_m_s / 2)
        self.gripper.set_vacuum(False)
        self._move(lifted(grasp.bMe_place, job.approach_m))

    def _look_at_the_placed_part(self, check: CheckView) -> PlacementCheck:
        """The placement as the check view sees it; a miss only once a second look agrees.

        The first look takes a frame exposed after the move ended (read_after). A host that
        read the camera late (its reader starved while frames waited in the stream's buffers)
        can still hand over one from before the move, and a miss stops the line: so a part
        not found or beyond the tolerance is looked at again on a frame exposed at least
        CONFIRMING_LOOK_AFTER_S of the host's time later, which is the one that counts."""
        self.timer.enter(CellTimePhase.CHECK)
        self._say(Phase.PLACING, "looking at the placed part from the check pose")
        self._move(check.check_bMe)
        # A frame exposed after the move ended: the part as it lies, seen from where it was taught.
        seen = self._placement_seen(check)
        if seen.found and seen.error_mm <= self.job.placement_tolerance_mm:
            return seen
        log.info("check view: %s; looking again", "part not found" if not seen.found else f"{seen.error_mm:.2f} mm off")
        # The host's own clock (not the robot's, which an emulator may run faster): what a
        # late reader needs to catch up with the camera.
        time.sleep(CONFIRMING_LOOK_AFTER_S)
        return self._placement_seen(check)

    def _placement_seen(self, check: CheckView) -> PlacementCheck:
        """The check view's verdict on a frame exposed after now (the robot standing still)."""
        features = self.perception.perceive(FlangeReadout(self.robot).measure(), self.robot.clock_s())
        return check_placement(check, features.corners_px, self.model.camera, self.job.part_side_m)

    def _verdict(self, seen: PlacementCheck | None) -> AssemblyOutcome:
        """Placed or missed: by the check view where the job has one, else by the cell's gauge."""
        gauge = self.settings.measure_placement()
        if seen is None:  # no check view: the gauge decides where a cell has one
            if gauge is None:
                return self._end(
                    Outcome.PLACED,
                    "part released in the metal part (no check view in this job, no placement gauge on this cell: "
                    "placement unknown)",
                    RunEnd.PLACED,
                )
            if gauge.inside:
                inside = f"part in the metal part, {gauge.error_mm:.2f} mm off centre (gauge)"
                return self._end(Outcome.PLACED, inside, RunEnd.PLACED, gauge=gauge)
            outside = f"part outside the pocket, {gauge.error_mm:.2f} mm off centre (gauge)"
            return self._end(Outcome.MISSED, outside, RunEnd.OUTSIDE_POCKET, gauge=gauge)
        if not seen.found:
            return self._end(Outcome.MISSED, "part not found at the check pose", RunEnd.NOT_FOUND_AT_CHECK, seen, gauge)
        tolerance = self.job.placement_tolerance_mm
        if seen.error_mm <= tolerance:
            return self._end(
                Outcome.PLACED,
                f"part seen {seen.error_mm:.2f} mm from its taught place (tolerance {tolerance:g} mm)",
                RunEnd.PLACED,
                seen,
                gauge,
            )
        return self._end(
            Outcome.MISSED,
            f"part seen {seen.error_mm:.2f} mm from its taught place, beyond the {tolerance:g} mm tolerance",
            RunEnd.BEYOND_TOLERANCE,
            seen,
            gauge,
        )

    def _end(
        self,
        outcome: Outcome,
        reason: str,
        end: RunEnd,
        seen: PlacementCheck | None = None,
        gauge: PlacementReport | None = None,
    ) -> AssemblyOutcome:
        """The run's outcome, said once; a fault or an e-stop first holds the robot.
        A fault met while the e-stop is latched ends the run as e-stopped: the hold made
        the step fail (a refused move, a refused goal, a stopped servo), whichever noticed."""
        if outcome is Outcome.FAULT and self.settings.estopped():
            outcome, reason, end = Outcome.ESTOPPED, "e-stop pressed", RunEnd.ESTOPPED
        if outcome in (Outcome.FAULT, Outcome.ESTOPPED):
            reason += hold_after_fault(self.robot)
            self._say(Phase.ESTOPPED if outcome is Outcome.ESTOPPED else Phase.FAULT, reason)
        else:
            self._say(Phase.DONE, reason)
        log.info("assembly %s: %s", outcome, reason)
        servo = self.servo
        return AssemblyOutcome(
            outcome=outcome,
            reason=reason,
            final_error_px=servo.final_error_px if servo else float("nan"),
            placement_error_mm=seen.error_mm if seen else None,
            duration_s=time.monotonic() - self.started_s,
            cell_time_s=self.timer.total_s(),
            cell_time_by_phase_s=dict(self.timer.by_phase),
            stages=servo.stages if servo else [],
            iterations=servo.iterations if servo else 0,
            gauge_placement_error_mm=gauge.error_mm if gauge else None,
            gauge_inside=gauge.inside if gauge else None,
            end=end,
        )
