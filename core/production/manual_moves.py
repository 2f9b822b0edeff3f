"""Moving the arm by hand: where Home and Survey go, and why a target is refused, in words.

Home is the cell file's ``[robot] home_joints_deg`` (tool down over the work area);
Survey puts the camera straight down over the middle of the table where parts are
presented (the cell file's ``[board]``, laid there to commission the cell), high enough
to see a part anywhere a few centimetres around it. Both are reached on a joint-space
path (SafetyLayer.move_joint, every step checked): the straight line from wherever the
arm stands, over the metal part after a run say, may cut through the hole in the arm's
tool-down shell.

A typed target the safety layer refuses is explained by its kind (protocol/catalogue.py):
a straight line that a joint-space path can make is offered as such; a target no joints
reach names the joint left at its limit and the way to move the target so that joint
comes off it (the flange's motion as that joint turns back: a column of the Jacobian).
"""

from __future__ import annotations

import numpy as np

from vservo.core.cell.config import CellConfig
from vservo.core.cell.kinematics import ArmKinematics, UnreachableTarget
from vservo.core.geometry.spatial import Matrix, Pose6, inverse, matrix_from_pose, transform
from vservo.core.production.protocol import CommandRefused
from vservo.core.production.protocol.catalogue import Refusal
from vservo.core.robot.backend import MotionStopped, RobotError, RobotNotReady
from vservo.core.robot.safety import (
    BeyondJointLimits,
    JointsDisagree,
    OutsideWorkspace,
    SafetyLayer,
    SafetyRefusal,
    SafetyStopActive,
    StepTooLarge,
    TooFast,
)

# The camera this high over the table in the survey (the desired view's is 162 mm over a
# part's top face, 20 mm above the table): it sees the table some 40 mm around the middle.
# Turned as the demo job's desired view is (its cMo), looking straight down at the table.
SURVEY_HEIGHT_M = 0.25
SURVEY_cMt = matrix_from_pose(Pose6(0.0, 0.0, SURVEY_HEIGHT_M, np.pi, 0.0, -np.pi))  # t: the table's middle
# A base axis is named in the advice when it carries at least this share of the motion.
AXIS_SHARE = 0.35

# The safety layer's refusals by kind (a subclass not listed is explained as a robot fault).
SAFETY_REFUSALS: dict[type[SafetyRefusal], Refusal] = {
    OutsideWorkspace: Refusal.OUTSIDE_WORKSPACE,
    BeyondJointLimits: Refusal.UNREACHABLE,
    StepTooLarge: Refusal.STEP_TOO_LARGE,
    TooFast: Refusal.TOO_FAST,
    SafetyStopActive: Refusal.ESTOP_ACTIVE,
    JointsDisagree: Refusal.JOINTS_DISAGREE,
}


def home_bMe(arm: ArmKinematics, config: CellConfig) -> Matrix:
    """The flange at the cell file's home joints."""
    return arm.fk(config.home_q)


def survey_bMe(config: CellConfig) -> Matrix | None:
    """The flange that puts the camera SURVEY_HEIGHT_M straight over the middle of the
    cell file's [board] (where parts are presented), turned as the desired view is; None
    without a [board]."""
    board = config.board
    if board is None:
        return None
    middle = board.bMboard @ np.append(board.corners_board().mean(axis=0), 1.0)
    return transform(t=middle[:3]) @ inverse(SURVEY_cMt) @ inverse(config.nominal.eMc)


def _directions(v: Matrix) -> str:
    """A base-frame direction as the jog buttons name it: '-X and +Z'."""
    size = float(np.linalg.norm(v))
    axes = [f"{'+' if v[k] > 0 else '-'}{'XYZ'[k]}" for k in np.argsort(-np.abs(v)) if abs(v[k]) >= AXIS_SHARE * size]
    return " and ".join(axes)


def reach_advice(arm: ArmKinematics, bMe_target: Matrix, q_seed: Matrix) -> str:
    """Which joint keeps the arm from bMe_target and which way to move the target: the
    joint closest to its limit in the IK's best attempt, and the flange's motion in the
    base frame as that joint turns back from it."""
    q: Matrix | None
    try:
        q = arm.ik(bMe_target, q_seed, tolerance_m=1e-6, tolerance_rad=1e-6).q
    except UnreachableTarget as exc:
        q = exc.best_q
    if q is None:
        return "The target is beyond the arm's reach: bring it nearer the arm's base."
    to_upper, to_lower = arm.upper - q, q - arm.lower
    joint = int(np.argmin(np.minimum(to_upper, to_lower)))
    upper = to_upper[joint] < to_lower[joint]
    bMe = arm.fk(q)
    v = bMe[:3, :3] @ arm.jacobian(q)[:3, joint] * (-1.0 if upper else 1.0)
    name = arm.joint_names[joint]
    return f"{name} stops at its {'upper' if upper else 'lower'} limit: move the target toward {_directions(v)}."


def move_refused(robot: SafetyLayer, exc: Exception, bMe_target: Matrix, speed_m_s: float) -> CommandRefused:
    """The refusal of a straight move to bMe_target that ``exc`` stopped, by kind: a joint
    limit on the line that a joint-space path avoids is LINE_BLOCKED; one no path avoids,
    UNREACHABLE with the joint and the way to go."""
    detail = str(exc)
    if isinstance(exc, MotionStopped):
        return CommandRefused(f"the move was stopped: {detail}", Refusal.MOVE_STOPPED)
    if isinstance(exc, BeyondJointLimits | UnreachableTarget):
        bMe_now = robot.read_pose()
        try:
            robot.joint_path(bMe_now, bMe_target, speed_m_s)
        except (SafetyRefusal, UnreachableTarget):
            q_now = robot.model_joints(bMe_now)
            q_seed = q_now if np.all(np.isfinite(q_now)) else (robot.arm.lower + robot.arm.upper) / 2
            advice = reach_advice(robot.arm, bMe_target, q_seed)
            return CommandRefused(detail, Refusal.UNREACHABLE, advice)
        return CommandRefused(detail, Refusal.LINE_BLOCKED)
    if isinstance(exc, SafetyRefusal):
        return CommandRefused(detail, SAFETY_REFUSALS.get(type(exc), Refusal.MOVE_STOPPED))
    if isinstance(exc, RobotNotReady):
        return CommandRefused(detail, Refusal.ROBOT_HELD)
    if isinstance(exc, RobotError):
        return CommandRefused(detail, Refusal.MOVE_STOPPED)
    raise exc
