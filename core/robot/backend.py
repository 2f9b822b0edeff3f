"""The one interface through which the loop and the app move a robot.

A backend is what a robot controller offers a host (JRC-PROTOCOL.md): read the flange
pose it computes with its own model, servo power, linear moves to Cartesian targets
(absolute and incremental) that it executes on its own, the end of a motion, hold and
alarms. The kinematic simulator and the JRC link implement it alike, so the loop, the
safety layer and the app never know which robot they drive.

Poses are flange poses bMe in the robot's base frame, SI units (m, rad) as everywhere
inside vservo; a backend converts to its controller's units at its edge.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from core.kinematics import UnreachableTarget
from core.simulator import SimulatedCell
from core.spatial import Matrix
from core.step_policy import PositionCommand


def apply_increment(bMe_increment: Matrix, bMe: Matrix) -> Matrix:
    """The flange pose after a base-frame increment (IMOV): translation added, rotation
    composed on the left, about the flange's own origin."""
    target = np.eye(4)
    target[:3, :3] = bMe_increment[:3, :3] @ bMe[:3, :3]
    target[:3, 3] = bMe[:3, 3] + bMe_increment[:3, 3]
    return target


class RobotError(Exception):
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


class RobotBackend(Protocol):
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
    def wait_motion(self, timeout_s: float | None = None) -> bool:
        """Block until the motion ends (JWAIT): True when it finished, False when it was
        stopped for another reason (hold, alarm, servo off)."""
        ...
    def hold(self, on: bool) -> None: ...
    def reset_alarms(self) -> None: ...


class SimulatedBackend:
    """The kinematic simulator as a robot: moves complete at once, in simulated time.

    The plant (SimulatedCell) executes each move through the controller's nominal IK and
    advances its clock by the move's duration at the commanded speed; a move the IK
    cannot reach raises UnreachableTarget and leaves the arm where it was.
    """

    name = "sim"

    def __init__(self, cell: SimulatedCell) -> None:
        self.cell = cell
        self._servo_on = False
        self._held = False
        self._connected = False

    def connect(self) -> None:
        self._connected = True

    def close(self) -> None:
        self._connected = False

    def status(self) -> RobotStatus:
        return RobotStatus(servo_on=self._servo_on, running=False, held=self._held, alarm=False)

    def read_pose(self) -> Matrix:
        self._require_connection()
        return self.cell.controller_arm.fk(self.cell.state.q)

    def servo(self, on: bool) -> None:
        self._require_connection()
        self._servo_on = on

    def hold(self, on: bool) -> None:
        self._require_connection()
        self._held = on

    def reset_alarms(self) -> None:
        self._require_connection()

    def move_to(self, bMe_target: Matrix, speed_m_s: float) -> None:
        self._require_ready()
        bMe_target = np.asarray(bMe_target, dtype=float)
        self.cell.execute(PositionCommand(bMe_target, speed_m_s, 0.0))

    def move_by(self, bMe_increment: Matrix, speed_m_s: float) -> None:
        self.move_to(apply_increment(np.asarray(bMe_increment, dtype=float), self.read_pose()), speed_m_s)

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        self._require_connection()
        return self._servo_on and not self._held

    def _require_connection(self) -> None:
        if not self._connected:
            raise RobotError("the simulated robot is not connected: call connect() first")

    def _require_ready(self) -> None:
        self._require_connection()
        state = self.status()
        if not state.ready:
            why = "servo power is off" if not state.servo_on else "the robot is held"
            raise RobotNotReady(f"move refused: {why}")


__all__ = ["apply_increment", "RobotBackend", "RobotError", "RobotNotReady", "RobotStatus", "SimulatedBackend",
           "UnreachableTarget"]
