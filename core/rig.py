"""The cell's devices as the controller process owns them: robot, vacuum, camera, vision.

``simulated_rig`` assembles them on the simulated cell: the kinematic simulator as the
robot backend, its vacuum cup, the synthetic camera and the detectors on the NOMINAL
camera and laser. The simulator's truth is reached only through ``measure_placement``
(the gauge that says where a released part ended) and ``present_part`` (a new part
arriving on the table), the two things a test cell provides that no controller reads.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from core.assembly import PlacementReport
from core.camera_source import FrameSource
from core.config import CellConfig
from core.robot.backend import RobotBackend, SimulatedBackend
from core.robot.gripper import SimulatedVacuum, VacuumGripper
from core.scene import Cube
from core.sim_camera import SimulatedCamera
from core.simulator import SimulatedCell
from core.spatial import inverse, rot_z, transform
from core.step_policy import StepPolicy, step_policy_from_config
from core.vision.pipeline import CameraPerception, ImageFeatureExtractor, front_winding


@dataclass
class Rig:
    config: CellConfig
    robot: RobotBackend
    gripper: VacuumGripper
    camera: FrameSource
    extractor: ImageFeatureExtractor
    policy: StepPolicy
    dof: int
    measure_placement: Callable[[], PlacementReport | None]
    present_part: Callable[[np.random.Generator], None] | None = None
    cell: SimulatedCell | None = None  # the plant, for the 3D view and evaluation; None on a real cell

    def perception(self) -> CameraPerception:
        """A fresh tracker on the rig's camera (nothing carried over from an earlier run)."""
        return CameraPerception(self.camera, self.extractor)

    def close(self) -> None:
        self.camera.close()
        self.robot.close()


# How far a new part may lie from where the job was taught: the servo's job is to
# absorb exactly this (the thesis's parts arrive by hand or on a feeder).
PART_OFFSET_M = 0.015
PART_YAW_RAD = np.deg2rad(20.0)


def simulated_rig(config: CellConfig, seed: int | None = None) -> Rig:
    cell = SimulatedCell(config, seed)
    model = config.nominal
    taught_bMo = config.simulation.scene.cube.bMo

    def measure_placement() -> PlacementReport:
        placement = cell.ground_truth_placement()
        return PlacementReport(placement.inside, 1000.0 * placement.error_m)

    def present_part(rng: np.random.Generator) -> None:
        """A new part on the table near where the job was taught, at a random offset and turn."""
        offset = rng.uniform(-PART_OFFSET_M, PART_OFFSET_M, 2)
        yaw = rng.uniform(-PART_YAW_RAD, PART_YAW_RAD)
        side = cell.state.scene.cube.side_m
        centre = transform(t=(side / 2, side / 2, 0.0))
        bMo = transform(t=(*offset, 0.0)) @ taught_bMo @ centre @ transform(rot_z(yaw)) @ inverse(centre)
        cell.vacuum(False)
        cell.place_cube(bMo)

    robot = SimulatedBackend(cell)
    extractor = ImageFeatureExtractor(model.camera, model.laser, front_winding(Cube(np.eye(4)).corners_o))
    return Rig(
        config=config,
        robot=robot,
        gripper=SimulatedVacuum(cell),
        camera=SimulatedCamera(cell),
        extractor=extractor,
        policy=step_policy_from_config(config.motion),
        dof=cell.controller_arm.dof,
        measure_placement=measure_placement,
        present_part=present_part,
        cell=cell,
    )
