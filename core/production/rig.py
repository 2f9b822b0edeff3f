"""The cell's devices as the controller process owns them: robot, vacuum, camera, vision.

``simulated_rig`` assembles them on the simulated cell: the robot behind the safety
layer (the kinematic simulator itself, or the JRC link over a pseudo-terminal to the
JRC emulator moving that same simulator), its vacuum cup, the synthetic camera
and the detectors on the NOMINAL camera and laser. The simulator's truth is reached only through ``measure_placement``
(the gauge that says where a released part ended) and ``present_part`` (a new part
arriving on the table), the two things a test cell provides that no JRC reads.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from vservo.core.cell.config import ROBOT_BACKENDS, CellConfig
from vservo.core.cell.scene import Cube
from vservo.core.geometry.spatial import inverse, rot_z, transform
from vservo.core.perception.camera_source import FrameSource
from vservo.core.perception.vision.pipeline import CameraPerception, ImageFeatureExtractor, front_winding
from vservo.core.production.assembly import PlacementReport
from vservo.core.robot.gripper import VacuumGripper
from vservo.core.robot.jrc import JrcBackend
from vservo.core.robot.safety import SafetyLayer
from vservo.core.servo.step_policy import DividedPositionStep, StepPolicy, step_policy_from_config
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.camera import SimulatedCamera
from vservo.core.sim.jrc_emulator import JrcEmulator
from vservo.core.sim.plant import SimulatedCell
from vservo.core.sim.vacuum import SimulatedVacuum


@dataclass
class Rig:
    config: CellConfig
    robot: SafetyLayer
    gripper: VacuumGripper
    camera: FrameSource
    extractor: ImageFeatureExtractor
    policy: StepPolicy
    dof: int
    measure_placement: Callable[[], PlacementReport | None]
    present_part: Callable[[np.random.Generator], None] | None = None
    cell: SimulatedCell | None = None  # the plant, for the 3D view and evaluation; None on a real cell
    emulator: JrcEmulator | None = None  # the JRC emulator the robot link talks to, if any

    def perception(self) -> CameraPerception:
        """A fresh tracker on the rig's camera (nothing carried over from an earlier run)."""
        return CameraPerception(self.camera, self.extractor)

    def close(self) -> None:
        self.camera.close()
        self.robot.close()
        if self.emulator is not None:
            self.emulator.stop()


# How far a new part may lie from where the job was taught: the servo's job is to
# absorb exactly this (the thesis's parts arrive by hand or on a feeder).
PART_OFFSET_M = 0.015
PART_YAW_RAD = np.deg2rad(20.0)

# The emulated JRC moves this many times faster than a real one, and the host's sampling
# period shrinks as much: a 2 s step of the thesis's cell takes 50 ms on screen.
JRC_TIME_SCALE = 40.0


def simulated_rig(config: CellConfig, seed: int | None = None, backend: str | None = None,
                  jrc_time_scale: float = JRC_TIME_SCALE) -> Rig:
    """The simulated cell's devices; ``backend`` (default: the cell file's [robot]
    backend) "sim" drives the simulator directly, "jrc" through the JRC link and an
    emulated JRC on a pseudo-terminal."""
    backend = backend or config.robot_backend
    if backend not in ROBOT_BACKENDS:
        raise ValueError(f"robot backend {backend!r}: choose one of {', '.join(ROBOT_BACKENDS)}")
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

    policy = step_policy_from_config(config.motion)
    emulator = None
    if backend == "sim":
        robot = SafetyLayer.from_config(SimulatedBackend(cell), config)
    else:
        if not isinstance(policy, DividedPositionStep):
            raise ValueError(f"{config.source}: the JRC takes position steps; set [motion] mode = \"position_steps\"")
        emulator = JrcEmulator(cell, config.jrc, time_scale=jrc_time_scale)
        robot = SafetyLayer.from_config(JrcBackend(config.jrc, emulator.start_on_pty()), config)
        policy = replace(policy, sampling_period_s=policy.sampling_period_s / jrc_time_scale)
    extractor = ImageFeatureExtractor(model.camera, model.laser, front_winding(Cube(np.eye(4)).corners_o))
    return Rig(
        config=config,
        robot=robot,
        gripper=SimulatedVacuum(cell),
        camera=SimulatedCamera(cell),
        extractor=extractor,
        policy=policy,
        dof=cell.jrc_arm.dof,
        measure_placement=measure_placement,
        present_part=present_part,
        cell=cell,
        emulator=emulator,
    )
