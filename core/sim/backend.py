"""The kinematic simulator behind the robot backend protocol."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.robot.backend import RobotError, RobotNotReady, RobotStatus, apply_increment
from vservo.core.robot.commands import PositionCommand
from vservo.core.sim.plant import SimulatedCell


class CellPace:
    """Keeps the wall clock in step with a simulated cell's clock, so a run takes on screen
    the time it takes on the cell (``time_scale`` times less): each call that advances the
    cell's clock returns once the wall clock has caught up with it. The host's own work
    during the call counts toward it; a hold (``wake``) ends the wait at once."""

    def __init__(self, clock_s: Callable[[], float], time_scale: float) -> None:
        if not (np.isfinite(time_scale) and time_scale > 0):
            raise ValueError(f"the time scale must be a positive number, got {time_scale!r}")
        self.clock_s, self.time_scale = clock_s, time_scale
        self._woken = threading.Event()

    def keep(self, advance: Callable[[], object]) -> None:
        """Call ``advance`` (a move, a dwell), then wait until the wall clock has followed the cell's."""
        wall_s, cell_s = time.monotonic(), self.clock_s()
        self._woken.clear()
        try:
            advance()
        finally:
            due_s = wall_s + (self.clock_s() - cell_s) / self.time_scale
            self._woken.wait(max(0.0, due_s - time.monotonic()))

    def wake(self) -> None:
        self._woken.set()


class SimulatedBackend:
    """The kinematic simulator as a robot: moves complete at once, in simulated time.

    The plant (SimulatedCell) executes each move through the JRC's nominal IK and
    advances its clock by the move's duration at the commanded speed; a move the IK
    cannot reach raises UnreachableTarget and leaves the arm where it was. With a
    ``pace`` (CellPace) each move and dwell returns once the wall clock has followed the
    plant's: a run is watched at the real cell's pace.
    """

    name = "sim"

    def __init__(self, cell: SimulatedCell, time_scale: float | None = None) -> None:
        self.cell = cell
        self._servo_on = False
        self._held = False
        self._connected = False
        self._pace = None if time_scale is None else CellPace(lambda: self.cell.state.time_s, time_scale)

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
        if on and self._pace is not None:  # a hold ends the wait of a move under way
            self._pace.wake()

    def reset_alarms(self) -> None:
        self._require_connection()

    def _paced(self, advance: Callable[[], object]) -> None:
        if self._pace is None:
            advance()
        else:
            self._pace.keep(advance)

    def move_to(self, bMe_target: Matrix, speed_m_s: float) -> None:
        self._require_ready()
        bMe_target = np.asarray(bMe_target, dtype=float)
        self._paced(lambda: self.cell.execute(PositionCommand(bMe_target, speed_m_s, 0.0)))

    def move_by(self, bMe_increment: Matrix, speed_m_s: float) -> None:
        self.move_to(apply_increment(self.read_pose(), bMe_increment), speed_m_s)

    def move_timed(self, bMe_target: Matrix, duration_s: float) -> None:
        self._require_ready()
        self._paced(lambda: self.cell.move(np.asarray(bMe_target, dtype=float), duration_s))

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        self._require_connection()
        return self._servo_on and not self._held

    def clock_s(self) -> float:
        return self.cell.state.time_s

    def cell_clock_s(self) -> float:
        return self.cell.state.time_s

    def dwell(self, seconds: float) -> None:
        self._paced(lambda: self.cell.pass_time(seconds))

    def _require_connection(self) -> None:
        if not self._connected:
            raise RobotError("the simulated robot is not connected: call connect() first")

    def _require_ready(self) -> None:
        self._require_connection()
        state = self.status()
        if not state.ready:
            why = "servo power is off" if not state.servo_on else "the robot is held"
            raise RobotNotReady(f"move refused: {why}")
