"""The one interface through which the loop and the app move a robot.

A backend is what a robot controller offers a host (docs/robot-link.md): read the flange
pose it computes with its own model, servo power, linear moves to Cartesian targets
(absolute and incremental) that it executes on its own, the end of a motion, hold and
alarms. The kinematic simulator and the JRC link implement it alike, so the loop, the
safety layer and the app never know which robot they drive.

Poses are flange poses bMe in the robot's base frame, SI units (m, rad) as everywhere
inside vservo; a backend converts to its controller's units at its edge.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix
from vservo.core.robot.commands import RobotCommand, StreamedTwist, VelocityCommand


class RobotError(VservoError):
    """The robot refused or failed a request; the message says what and why."""


class RobotNotReady(RobotError):
    """A move asked of a robot that is held, in alarm or without servo power."""


@dataclass(frozen=True)
class RobotStatus:
    """The controller's state as RSTATS reports it (d2 bits), in words."""

    servo_on: bool
    running: bool
    held: bool
    alarm: bool
    detail: str = ""

    @property
    def ready(self) -> bool:
        """Whether a move would be accepted now."""
        return self.servo_on and not self.held and not self.alarm

    def describe(self) -> str:
        """The state in words, for errors and the operator: 'held (pendant hold), servo on'."""
        words = [
            "in alarm" if self.alarm else "",
            "held" if self.held else "",
            "servo on" if self.servo_on else "servo off",
            "running" if self.running else "",
        ]
        text = ", ".join(word for word in words if word)
        return f"{text} ({self.detail})" if self.detail else text


class RobotBackend(Protocol):
    """What the loop, the safety layer and the app ask of a robot controller.

    Moves only start the motion; ``wait_motion`` blocks until it ends. A backend that
    cannot do something raises RobotError (or UnreachableTarget) saying what and why.
    """

    name: str

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def status(self) -> RobotStatus: ...
    def read_pose(self) -> Matrix:
        """The flange pose bMe as the controller computes it."""
        ...

    def servo(self, on: bool) -> None: ...
    def move_to(self, bMe_target: Matrix, speed_m_s: float) -> None:
        """Start a linear move to bMe_target (MOVL). Raises UnreachableTarget or RobotError."""
        ...

    def move_by(self, bMe_increment: Matrix, speed_m_s: float) -> None:
        """Start a linear move by an increment in the base frame (IMOV): translation added,
        rotation composed on the left."""
        ...

    def move_timed(self, bMe_target: Matrix, duration_s: float) -> None:
        """Start a linear move to bMe_target that lasts duration_s: one control period of a
        velocity-controlled robot (a twist held for duration_s). A controller that takes
        position steps only (the JRC) refuses it with RobotError."""
        ...

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        """Block until the motion ends (JWAIT): True when it finished, False when it was
        stopped for another reason (hold, alarm, servo off)."""
        ...

    def hold(self, on: bool) -> None: ...
    def reset_alarms(self) -> None: ...
    def clock_s(self) -> float:
        """The robot's clock in s: the plant's simulated time, or the host's monotonic time
        for a real controller. Only differences of it mean anything."""
        ...

    def cell_clock_s(self) -> float:
        """How long the real cell would have taken, as a clock: the plant's time for the
        simulator; on a real JRC the wall clock; for an emulated one the emulator's count of
        each motion's duration and each exchange's bytes at the line's rate, with the host's
        dwells (core/sim/controller_clock.py). Only differences mean anything."""
        ...

    def dwell(self, seconds: float) -> None:
        """Let ``seconds`` of the cell clock pass with the robot standing still (the rest of
        a sampling period; an emulated controller's time_scale times faster on the wall)."""
        ...


@runtime_checkable
class StreamingBackend(Protocol):
    """A velocity-controlled robot that takes a twist at any time (a UR's speedl)."""

    def stream_twist(self, eVe: Matrix, hold_s: float) -> None:
        """Move the flange at the body twist eVe from now on, without waiting; the controller
        holds it for hold_s at most, then stops the arm, unless the next twist comes first."""
        ...

    def stop_motion(self) -> None:
        """Bring the streamed motion to a standstill and wait for it."""
        ...


@dataclass(frozen=True)
class JointLine:
    """A joint-space line the safety layer has checked whole (SafetyLayer.joint_path): the
    joints at its ends (rad, the arm model's joints; ``q_from`` where the controller reported
    its joints) and, for the controller's timing, the peak over the line of |dp/ds|, the
    flange's speed per unit of the line's parameter s in [0, 1] (m, over the checked samples;
    at least the flange's path length)."""

    q_from: Matrix
    q_to: Matrix
    tcp_peak_m: float


@runtime_checkable
class JointMotionBackend(Protocol):
    """A robot that runs a checked joint-space line to joint targets as one motion (a UR's
    movej), where the others (the JRC, the kinematic simulator) follow it as short linear
    moves, each sent and waited for."""

    def read_joints(self) -> Matrix:
        """The joints as the controller reports them (rad, the arm model's joints)."""
        ...

    def move_joints(self, line: JointLine, speed_m_s: float) -> None:
        """Start the move of every joint on the straight line from where they stand to
        line.q_to, timed so that the flange's speed along it stays within speed_m_s;
        ``wait_motion`` waits for its end."""
        ...


class MotionStopped(RobotError):
    """A motion ended before its target: held, in alarm or without servo power."""


def carry_out(robot: RobotBackend, command: RobotCommand, bMe: Matrix) -> float:
    """Carry out one step policy command from the flange pose bMe and wait for its end.

    A velocity step moves for its control period. A position step (the JRC style,
    section 5.3) moves to its target, waits for the end of the motion, then for the rest
    of the sampling period, so the next target is sent one period after this one (on the
    cell clock: the period is the real cell's, and so is the dwell).
    Returns the robot's clock when the motion ended (before that rest): a frame exposed
    since then shows where the robot stopped. A streamed twist goes out and is not waited
    for: the robot moves on while the next frame is taken; its clock then is returned.
    Raises MotionStopped when the robot stops short (hold, alarm, servo off).
    """
    if isinstance(command, StreamedTwist):
        if not isinstance(robot, StreamingBackend):
            raise RobotError(f"the {robot.name} robot takes no streamed twist: it is not velocity-controlled")
        robot.stream_twist(command.eVe, command.hold_s)
        return robot.clock_s()
    if isinstance(command, VelocityCommand):
        robot.move_timed(command.target(bMe), command.dt_s)
        wait_for_the_end(robot)
        return robot.clock_s()
    if command.period_s <= 0.0:  # no sampling wait (the fast policy): no clock to read
        move_and_wait(robot, command.bMe_target, command.speed_m_s)
        return robot.clock_s()
    started_s = robot.cell_clock_s()
    move_and_wait(robot, command.bMe_target, command.speed_m_s)
    ended_s = robot.clock_s()
    robot.dwell(command.period_s - (robot.cell_clock_s() - started_s))
    return ended_s


def move_and_wait(robot: RobotBackend, bMe_target: Matrix, speed_m_s: float) -> None:
    """One linear move to bMe_target, waited for; raises MotionStopped if it stops short."""
    robot.move_to(bMe_target, speed_m_s)
    wait_for_the_end(robot)


def wait_for_the_end(robot: RobotBackend) -> None:
    """Wait for the motion under way to end; raises MotionStopped if it stops short."""
    if not robot.wait_motion():
        raise MotionStopped(f"the robot stopped before the end of its move: {robot.status().describe()}")


def apply_increment(bMe: Matrix, bMe_increment: Matrix) -> Matrix:
    """Where an incremental move (IMOV) lands: the increment's translation added to the
    flange's, its rotation composed on the left (both in the base frame)."""
    bMe_increment = np.asarray(bMe_increment, dtype=float)
    target = np.eye(4)
    target[:3, :3] = bMe_increment[:3, :3] @ bMe[:3, :3]
    target[:3, 3] = bMe[:3, 3] + bMe_increment[:3, 3]
    return target


__all__ = [
    "JointLine",
    "JointMotionBackend",
    "MotionStopped",
    "RobotBackend",
    "RobotError",
    "RobotNotReady",
    "RobotStatus",
    "StreamingBackend",
    "UnreachableTarget",
    "apply_increment",
    "carry_out",
    "move_and_wait",
    "wait_for_the_end",
]
