"""The cell's devices as the controller process owns them: robot, vacuum, camera, vision.

A ``Rig`` is built from the cell file by ``build_rig`` (core/production/cell_rig.py, where
the real cell's devices are made; the simulated cell's are in
core/production/simulated_rig.py). The controller sees only the
interfaces real hardware has, plus what only a test cell offers (a gauge for where a
released part ended, a new part presented on the table or put at a given place, the
calibration checkerboard laid on the table or taken away), None where the cell cannot.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from vservo.core.cell.config import CellConfig
from vservo.core.cell.scene import Cube
from vservo.core.perception.camera_source import FrameSource
from vservo.core.perception.vision.pipeline import CameraPerception, ImageFeatureExtractor, front_winding
from vservo.core.production.assembly import PlacementReport
from vservo.core.production.locate import PartLocator
from vservo.core.robot.gripper import VacuumGripper
from vservo.core.robot.safety import SafetyLayer
from vservo.core.servo.step_policy import StepPolicy

if TYPE_CHECKING:
    from vservo.core.sim.jrc_emulator import JrcEmulator
    from vservo.core.sim.plant import SimulatedCell


@dataclass
class Rig:
    config: CellConfig
    robot: SafetyLayer
    gripper: VacuumGripper
    camera: FrameSource
    extractor: ImageFeatureExtractor
    policy: StepPolicy
    measure_placement: Callable[[], PlacementReport | None]
    # The test cell's hooks (their answers, a fixture's reply, go unread: object).
    present_part: Callable[[np.random.Generator], object] | None = None
    # The checkerboard laid (True: the table cleared of the parts) or taken away (False).
    lay_board: Callable[[bool], object] | None = None
    # The part put down with its frame O at (x_m, y_m) in the base frame, turned yaw_rad.
    place_part: Callable[[float, float, float], object] | None = None
    # The chapter 2 network of a commissioned cell, for jobs that locate their part; None before.
    locator: PartLocator | None = None
    cell: SimulatedCell | None = None  # the plant, for the 3D view and evaluation; None on a real cell
    emulator: JrcEmulator | None = None  # the JRC emulator the robot link talks to, if any
    # Opens the camera of the cell file again, for one lost with its device; None: it cannot be lost.
    reopen_camera: Callable[[], FrameSource] | None = None

    def perception(self) -> CameraPerception:
        """A fresh tracker on the rig's camera (nothing carried over from an earlier run)."""
        return CameraPerception(self.camera, self.extractor)

    def reconnect(self) -> None:
        """Open again what was lost with its device (the robot link, a live camera), so a
        device that is back serves without restarting the controller. Raises the device's
        own error (RobotError, CameraSourceError) naming it when it is still gone."""
        self.robot.connect()  # opens a lost port anew; asks an open one for its status
        if self.camera.lost is not None and self.reopen_camera is not None:
            self.camera.close()
            self.camera = self.reopen_camera()

    def close(self) -> None:
        self.camera.close()
        self.robot.close()
        if self.emulator is not None:
            self.emulator.stop()


def extractor_for(config: CellConfig) -> ImageFeatureExtractor:
    """The detectors on the NOMINAL camera and laser, for the cube's top face."""
    model = config.nominal
    return ImageFeatureExtractor(model.camera, model.laser, front_winding(Cube(np.eye(4)).corners_o))
