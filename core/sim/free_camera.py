"""A free-flying camera: the robot of a simulated cell whose camera no arm carries.

To study a control law alone (ViSP's and Corke's free-camera simulations), the camera
goes where the law sends it: no joints, no joint limits, no workspace, no settling. It
is a robot backend like the arm's, so the loop, the laws and the step policies run the
same code on it. A velocity step (hold the twist for dt) lands the flange at
bMe exp(dt eVe), the exact integral of a constant body twist; a position step lands it
on its target, taking as long as the arm's linear move at the same speed would.
"""

from __future__ import annotations

import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.robot.backend import RobotBackend
from vservo.core.sim import Arm
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.plant import SimulatedCell


class FreeCameraBackend(SimulatedBackend):
    """The free camera of a cell built with ``Arm.NONE``, behind the robot backend protocol."""

    name = "free camera"

    def move_to(self, bMe_target: Matrix, speed_m_s: float) -> None:
        self._require_ready()
        self.cell.fly(np.asarray(bMe_target, dtype=float), self.cell.travel_time_s(bMe_target, speed_m_s))

    def move_timed(self, bMe_target: Matrix, duration_s: float) -> None:
        self._require_ready()
        self.cell.fly(np.asarray(bMe_target, dtype=float), duration_s)


def simulated_robot(cell: SimulatedCell) -> RobotBackend:
    """The connected, enabled robot that moves a simulated cell: its arm, or its free camera."""
    backend = FreeCameraBackend if cell.arm is Arm.NONE else SimulatedBackend
    return backend.enabled(cell)
