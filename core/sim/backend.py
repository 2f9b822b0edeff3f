"""The kinematic simulator behind the robot backend protocol."""

from __future__ import annotations

import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.robot.backend import RobotError, RobotNotReady, RobotStatus, apply_increment
from vservo.core.robot.commands import PositionCommand
from vservo.core.sim.plant import SimulatedCell


class SimulatedBackend:
    """The kinematic simulator as a robot: moves complete at once, in simulated time.

    The plant (SimulatedCell) executes each move through the JRC's nominal IK and
    advances its clock by the move's duration at the commanded speed; a move the IK
    cannot reach raises UnreachableTarget and leaves the arm where it was.
    """

    name = "sim"

    def __init__(self, cell: SimulatedCell) -> None:
        self.cell = cell
        self._servo_on = False
        self._held = False
        self._connected = False

    @classmethod
    def enabled(cls, cell: SimulatedCell) -> SimulatedBackend:
        """A connected simulated robot with servo power on: what a simulation study drives."""
        robot = cls(cell)
        robot.connect()
        robot.servo(True)
        return robot

    def connect(self) -> None:
        self._connected = True

    def close(self) -> None:
        self._connected = False

    def status(self) -> RobotStatus:
        return RobotStatus(servo_on=self._servo_on, running=False, held=self._held, alarm=False)

    def read_pose(self) -> Matrix:
        self._require_connection()
        return self.cell.flange_readout()

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
        self.move_to(apply_increment(self.read_pose(), bMe_increment), speed_m_s)

    def move_timed(self, bMe_target: Matrix, duration_s: float) -> None:
        self._require_ready()
        self.cell.move(np.asarray(bMe_target, dtype=float), duration_s)

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        self._require_connection()
        return self._servo_on and not self._held

    def clock_s(self) -> float:
        return self.cell.state.time_s

    def cell_clock_s(self) -> float:
        return self.cell.state.time_s

    def dwell(self, seconds: float) -> None:
        self.cell.pass_time(seconds)

    def _require_connection(self) -> None:
        if not self._connected:
            raise RobotError("the simulated robot is not connected: call connect() first")

    def _require_ready(self) -> None:
        self._require_connection()
        state = self.status()
        if not state.ready:
            why = "servo power is off" if not state.servo_on else "the robot is held"
            raise RobotNotReady(f"move refused: {why}")
