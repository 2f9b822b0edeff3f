"""The look-and-move loop: measure, control, convert, command, and watch for failure.

One cycle (docs/architecture.md): the cell's measurement becomes image features (laser depth
from the NOMINAL laser and camera), the control law turns them into a camera twist cVc,
the nominal eVc carries it to the flange, the step policy makes it a robot command from
the flange pose the robot reports, and the robot backend (the simulator, or the JRC
link, usually behind the safety layer) carries it out. The loop watches what a cell
operator would: a shrinking image (the camera retreating), an error that stops falling
(a local minimum), a robot that cannot reach the target or refuses or stops a move, and
the iteration budget. It stops the robot (no further command) on the first failure and
names the cause. Behind a safety layer it arms the watchdog for the run and feeds it
every camera frame.

A streamed arm (a twist a frame, core/production/exposure_matched.py) moves on while a frame
is processed: a frame within the threshold is taken as the goal reached only when the twist
the arm still moves at leaves the error within it where the arm will stand; otherwise the
arm is stopped and a frame exposed once it stands decides, as look-and-move's always does.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from itertools import groupby
from typing import Any, Protocol

import numpy as np

from vservo.core.cell.config import CellModel
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.interaction import pixel_interaction_matrix
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import Matrix, inverse, theta_u, twist_transform
from vservo.core.perception.features import DesiredImage, ImageFeatures, pattern_scale, polygon_moments
from vservo.core.perception.measurement import Measurement, features_from_measurement
from vservo.core.robot.backend import RobotBackend, RobotError, StreamingBackend, carry_out
from vservo.core.robot.commands import StreamedTwist
from vservo.core.robot.safety import SafetyLayer, Watchdog
from vservo.core.servo.joint_limits import JointBound, JointLimitedSteps
from vservo.core.servo.laws.base import ControlLaw, ControlOutput, Failure, Stage
from vservo.core.servo.step_policy import StepPolicy

log = logging.getLogger("vservo.servo")


@dataclass(frozen=True)
class LoopLimits:
    """When the loop gives up.

    retreat_area_fraction: the corners' image area below this fraction of both the first
      and the desired area means the camera is backing away (IBVS's retreat, Chaumette 1998).
    retreat_distance_factor: for a law that estimates its distance to the part, that
      distance beyond this factor times both the first one and Z* is the retreat.
    progress_window / progress_fraction: a stage whose error has not fallen by this
      fraction over this many cycles is stuck in a local minimum.
    lost_hold_cycles: for how many consecutive cycles the loop holds the robot (zero
      twist, no command) while the law finds its features lost (a frame or two
      in which a detector misses them) before it stops with the features lost.
    """

    max_iterations: int = 3000
    retreat_area_fraction: float = 0.75
    retreat_distance_factor: float = 1.5
    progress_window: int = 150
    progress_fraction: float = 0.01
    lost_hold_cycles: int = 3


@dataclass(frozen=True)
class Cycle:
    """One look-and-move cycle as the loop saw it."""

    iteration: int
    measurement: Measurement
    features: ImageFeatures
    output: ControlOutput


@dataclass(frozen=True)
class ServoOutcome:
    converged: bool
    failure: Failure | None
    reason: str
    cycles: tuple[Cycle, ...]

    @property
    def iterations(self) -> int:
        return len(self.cycles)

    @property
    def final_error_px(self) -> float:
        return self.cycles[-1].output.error_px if self.cycles else float("nan")

    @property
    def stages(self) -> list[dict[str, int | Stage]]:
        """Consecutive stages in the order they ran, with their iteration counts."""
        runs = groupby(cycle.output.stage for cycle in self.cycles)
        return [{"stage": stage, "iterations": sum(1 for _ in run)} for stage, run in runs]


class MeasurementSource(Protocol):
    """What the loop samples each cycle: the simulator, or a real cell's robot readout
    (whose features then come from camera frames, see Perception)."""

    def measure(self, look: bool = True) -> Measurement: ...


class Perception(Protocol):
    """Where the loop's features come from: the measurement's projections or a camera.

    uses_projection: whether it reads the measurement's projected features at all.
    """

    @property
    def uses_projection(self) -> bool: ...

    def perceive(self, measurement: Measurement, motion_ended_s: float) -> ImageFeatures:
        """The features seen in a view exposed at or after ``motion_ended_s``, the robot's
        clock when its last motion ended (look-and-move: never a view from before or
        during that motion)."""
        ...


@dataclass(frozen=True)
class ProjectedPerception:
    """Ideal detection: the simulator's projected corners and spot (with its pixel noise)."""

    camera: CameraModel
    laser: LaserPointer
    uses_projection: bool = True

    def perceive(self, measurement: Measurement, motion_ended_s: float) -> ImageFeatures:
        # The measurement is the plant at this moment: fresh whenever the motion ended.
        return features_from_measurement(measurement, self.camera, self.laser)


def hold_spot(features: ImageFeatures, last_seen: ImageFeatures | None) -> ImageFeatures:
    """The features with a vanished laser spot replaced by its last sighting, while the
    part has moved in the image by less than its own size since.

    The spot's image position depends only on the depth it lands at, so the last sighting
    is a good estimate while it is hidden. It hides behind the part: near the part's edge
    the part's side blocks the camera's view of the table where the beam lands, and near
    the end of stage 1.A the turn moves the part across the spot by a pixel or so a
    cycle. The part cannot hide the spot once it has moved by more than its own size:
    then the spot is gone, not hidden.
    """
    if features.spot_seen or last_seen is None:
        return features
    now, then = _seen_corners(features.corners_px), _seen_corners(last_seen.corners_px)
    if not (len(now) and len(then)):
        return features  # no corner seen to tell how far the part moved
    if np.linalg.norm(now.mean(axis=0) - then.mean(axis=0)) > 2.0 * pattern_scale(then):
        return features
    return replace(features, laser_spot_px=last_seen.laser_spot_px, laser_depth_m=last_seen.laser_depth_m)


def _seen_corners(corners_px: Matrix) -> Matrix:
    """The corners seen, (n, 2), n from 0 to 4."""
    return corners_px[np.isfinite(corners_px).all(axis=1)]


def corner_area_px2(corners_px: Matrix) -> float:
    return polygon_moments(corners_px)[0] if not np.isnan(corners_px).any() else float("nan")


def error_after_px(features: ImageFeatures, desired: DesiredImage, camera: CameraModel, c0Mc1: Matrix) -> float:
    """The feature error once the camera has moved by c0Mc1 since the frame of ``features``,
    to first order (s_dot = L v, eq. 4-14: the displacement (t, theta u) taken as a twist held
    1 s; L at the frame's corners and the desired depth). An arm that passes through the goal
    is predicted past it; one gliding in, short of it."""
    L = pixel_interaction_matrix(camera, features.corners_px, desired.depth_m)
    error = (features.corners_px - desired.corners_px).ravel()
    displacement = np.concatenate((c0Mc1[:3, 3], theta_u(c0Mc1[:3, :3])))
    return float(np.linalg.norm(error + L @ displacement))


def stop_to_confirm(
    robot: RobotBackend, cycle: Cycle, eMc: Matrix, camera: CameraModel, desired: DesiredImage, threshold_px: float
) -> float | None:
    """A converged cycle on a streamed arm: None when the arm, moved on since the frame's
    exposure, is still within ``threshold_px`` (the goal reached); else the arm stopped, and
    the robot's clock from which it stands (only a frame exposed since then may confirm).

    The move since the exposure is the robot's (its pose now against the pose at the
    frame's exposure stamp, which is a bound: a camera's frames are stamped their arrival
    less the longest latency, so it counts a little of the motion before too). The stop
    that follows lands within a control period or two: at the speed of a glide-in a
    fraction of a pixel; an arm passing through the goal at speed is caught before it.
    """
    c0Mc1 = inverse(cycle.measurement.bMe @ eMc) @ robot.read_pose() @ eMc
    standing_px = error_after_px(cycle.features, desired, camera, c0Mc1)
    if standing_px <= threshold_px:
        return None
    if not isinstance(robot, StreamingBackend):
        raise RobotError(f"the {robot.name} robot took a streamed twist and cannot stop it")
    log.info(
        "converged at %.3f px on a moving arm, %.3f px where it is now: stopped to look again", cycle.output.error_px, standing_px
    )
    robot.stop_motion()
    return robot.clock_s()


class RetreatTest:
    """The camera backing away from the part (IBVS's retreat, Chaumette 1998).

    A law that estimates its distance to the part (``ControlOutput.distance_m``) is
    judged by it: retreating is that distance beyond ``retreat_distance_factor`` times
    the larger of the first one and the taught Z*. The estimate rests on the model's
    intrinsics, whose errors move it by up to a few tens of percent across the image;
    a retreat grows without bound. Otherwise the corners' image area below
    ``retreat_area_fraction`` of both the first and the desired area is the retreat.
    """

    def __init__(self, limits: LoopLimits, desired_area_px2: float, desired_depth_m: float) -> None:
        self.fraction, self.factor = limits.retreat_area_fraction, limits.retreat_distance_factor
        self.desired_area, self.desired_depth = desired_area_px2, desired_depth_m
        self.first_area, self.first_distance = float("nan"), float("nan")

    def __call__(self, features: ImageFeatures, output: ControlOutput) -> str | None:
        """Why the camera is retreating, or None."""
        if np.isfinite(output.distance_m):
            if np.isnan(self.first_distance):
                self.first_distance = output.distance_m
            limit = self.factor * max(self.first_distance, self.desired_depth)
            if output.distance_m > limit:
                return f"distance {1000 * output.distance_m:.0f} mm, first {1000 * self.first_distance:.0f} mm"
            return None
        area = corner_area_px2(features.corners_px)
        if np.isnan(self.first_area):
            self.first_area = area
        if area < self.fraction * min(self.first_area, self.desired_area):
            return f"corner area {area:.0f} px^2, first {self.first_area:.0f} px^2"
        return None


class ProgressTest:
    """A stage stuck in a local minimum: its error has not fallen by ``progress_fraction``
    over the last ``progress_window`` cycles of the stage."""

    def __init__(self, limits: LoopLimits) -> None:
        self.window, self.fraction = limits.progress_window, limits.progress_fraction
        self.errors: deque[float] = deque(maxlen=limits.progress_window + 1)  # of the current stage
        self.stage: Stage | None = None

    def __call__(self, output: ControlOutput) -> str | None:
        """Why the stage is stalled, or None."""
        if output.stage != self.stage:
            self.errors.clear()
        self.stage = output.stage
        self.errors.append(output.stage_error)
        if len(self.errors) == self.errors.maxlen and self.errors[-1] > (1.0 - self.fraction) * self.errors[0]:
            return f"stage {self.stage} error {self.errors[-1]:.2f} after {self.window} cycles"
        return None


def run_servo(
    cell: MeasurementSource,
    law: ControlLaw,
    desired: DesiredImage,
    model: CellModel,
    policy: StepPolicy,
    limits: LoopLimits = LoopLimits(),
    on_cycle: Callable[[Cycle], None] | None = None,
    perception: Perception | None = None,
    *,
    robot: RobotBackend,
    joint_limits: JointLimitedSteps | None = None,
) -> ServoOutcome:
    """Servo to the desired image with the control law ``law``; ``model`` is the nominal cell.

    ``cell`` is the camera side: its measurements feed ``perception``, by default the
    simulator's projected points. ``robot`` carries out the moves; it must be connected
    with servo power on. Behind a SafetyLayer the watchdog is armed for the run.
    ``joint_limits`` bends each step around the joint limits of the arm's model (it needs
    the measurement's joints); without it the steps go as the policy makes them.
    """
    perception = perception or ProjectedPerception(model.camera, model.laser)
    watchdog = robot.watchdog if isinstance(robot, SafetyLayer) else None
    if watchdog is not None:
        watchdog.arm()
    try:
        return _servo(cell, law, desired, model, policy, limits, on_cycle, perception, robot, watchdog, joint_limits)
    finally:
        if watchdog is not None:
            watchdog.disarm()


def _servo(
    cell: MeasurementSource,
    law: ControlLaw,
    desired: DesiredImage,
    model: CellModel,
    policy: StepPolicy,
    limits: LoopLimits,
    on_cycle: Callable[[Cycle], None] | None,
    perception: Perception,
    robot: RobotBackend,
    watchdog: Watchdog | None,
    joint_limits: JointLimitedSteps | None,
) -> ServoOutcome:
    eVc = twist_transform(model.eMc)
    retreat_test = RetreatTest(limits, corner_area_px2(desired.corners_px), desired.depth_m)
    cycles: list[Cycle] = []
    stage: Stage | None = None
    last_spot: ImageFeatures | None = None  # the last frame that saw the laser spot
    lost_for = 0  # consecutive cycles held with the features lost
    progress_test = ProgressTest(limits)
    held: tuple[JointBound, ...] = ()  # the joints the last step held at their limits
    # The robot stands still when the loop starts (its caller waited for the last move),
    # so the first frame must merely be newer than now; later ones newer than each move.
    motion_ended_s = robot.clock_s()
    streaming = False  # the arm moves at a twist not waited for
    standing_since_s = -np.inf  # the arm stopped to look again: only a frame exposed since counts

    def finish(converged: bool, failure: Failure | None, reason: str) -> ServoOutcome:
        if failure is not None:
            log.info("servo stopped at cycle %d: %s (%s)", len(cycles), failure.value, reason)
        return ServoOutcome(converged, failure, reason, tuple(cycles))

    for iteration in range(limits.max_iterations):
        measurement = cell.measure(look=perception.uses_projection)
        while measurement.time_s < standing_since_s:  # exposed before the arm stood
            measurement = cell.measure(look=perception.uses_projection)
        seen = perception.perceive(measurement, motion_ended_s)
        if watchdog is not None:
            watchdog.feed("camera")
        if seen.spot_seen:
            last_spot = seen
        features = hold_spot(seen, last_spot)
        output = law.step(features, desired, stage)
        lost_for = lost_for + 1 if output.failure is Failure.FEATURES_LOST else 0
        hold = 0 < lost_for <= limits.lost_hold_cycles
        if hold:
            output = replace(output, failure=None, note=f"holding, {output.note} ({lost_for} of {limits.lost_hold_cycles})")
        cycle = Cycle(iteration, measurement, features, output)
        cycles.append(cycle)
        if on_cycle is not None:
            on_cycle(cycle)
        if output.note:
            log.info("cycle %d: %s", iteration, output.note)
        if hold:
            continue  # no command: the next frame may see the features again
        if output.failure is not None:
            return finish(False, output.failure, output.note)
        if output.converged and streaming:
            try:
                stood_s = stop_to_confirm(robot, cycle, model.eMc, model.camera, desired, law.final_threshold_px)
            except RobotError as exc:
                return finish(False, Failure.ROBOT_STOPPED, str(exc))
            if stood_s is not None:
                streaming, standing_since_s = False, stood_s
                continue
        if output.converged:
            return finish(True, None, f"feature error {output.error_px:.3f} px")
        if not np.all(np.isfinite(output.cVc)):
            # Never send a NaN to a robot: the law broke down (a degenerate Jacobian or depth).
            return finish(False, Failure.SINGULAR_JACOBIAN, f"stage {output.stage} returned a non-finite twist")

        retreat = retreat_test(features, output)
        if retreat is not None:
            return finish(False, Failure.CAMERA_RETREAT, retreat)

        stage = output.stage
        stalled = progress_test(output)
        if stalled is not None:
            if held:
                # Stuck against the limits: the goal lies beyond what the arm can reach from here.
                return finish(False, Failure.UNREACHABLE, f"{stalled}, {', '.join(map(str, held))}")
            return finish(False, Failure.NO_PROGRESS, stalled)

        try:
            # The cycle's one reading of the flange (on a real cell FlangeReadout took it
            # from the robot): a second read would cost another RPOSC on the JRC.
            bMe = measurement.bMe
            command = policy.command(bMe, eVc @ output.cVc)
            if joint_limits is not None and np.all(np.isfinite(measurement.q)):  # NaN: no joints reach bMe
                step = joint_limits.limit(command, bMe, measurement.q)
                command, held = step.command, step.held
            motion_ended_s = carry_out(robot, command, bMe)
            streaming = isinstance(command, StreamedTwist)
        except UnreachableTarget as exc:
            return finish(False, Failure.UNREACHABLE, str(exc))
        except RobotError as exc:
            return finish(False, Failure.ROBOT_STOPPED, str(exc))
    return finish(False, Failure.ITERATION_LIMIT, f"{limits.max_iterations} cycles")


def cycle_record(cycle: Cycle) -> dict[str, Any]:
    """What a recording keeps of one cycle: what the loop saw, decided and commanded."""
    output, features = cycle.output, cycle.features
    return {
        "iteration": cycle.iteration,
        "time_s": cycle.measurement.time_s,
        "q": cycle.measurement.q,
        "bMe": cycle.measurement.bMe,
        "corners_px": features.corners_px,
        "laser_spot_px": features.laser_spot_px,
        "laser_depth_m": features.laser_depth_m,
        "region": features.region,
        "stage": output.stage,
        "cVc": output.cVc,
        "error_px": output.error_px,
        "stage_error": output.stage_error,
        "converged": output.converged,
        "failure": output.failure,
        "note": output.note,
    }
