"""The rig a cell file names: the real cell's devices, or the simulated cell's.

On a real cell (a camera that is not the simulator's; its robot and vacuum are checked
with it when the file is loaded) the rig is the robot's controller behind the safety
layer (the JRC of ``[jrc]``, or the Universal Robots controller of ``[ur]``), the camera of
``[camera.source]``, the vacuum cup on the controller's I/O or none, and
the detectors on the NOMINAL camera and laser, and a test cell's fixture
(``[fixture] url``) to present or place new parts and lay the checkerboard, if it has one. Nothing of the simulator is imported
then, and no gauge says where a released part ended: the run measures the placement
itself, by vision from the job's check view. The simulated cell's rig (core/production/simulated_rig.py) is imported only
when the file names the simulated camera.
"""

from __future__ import annotations

from vservo.core.cell.config import CameraSourceConfig, CellConfig, ConfigError
from vservo.core.perception.camera_source import FrameSource, ImageFolderSource, VideoCaptureSource, read_mono8
from vservo.core.production.fixture import FixtureClient
from vservo.core.production.locate import PartLocator
from vservo.core.production.rig import Rig, extractor_for
from vservo.core.robot.backend import RobotBackend
from vservo.core.robot.gripper import NoVacuum, VacuumGripper
from vservo.core.robot.jrc import JrcBackend
from vservo.core.robot.jrc_vacuum import JrcVacuum
from vservo.core.robot.safety import SafetyLayer
from vservo.core.servo.step_policy import PositionStepPolicy, step_policy_from_config


def build_rig(config: CellConfig, seed: int | None = None, backend: str | None = None, time_scale: float | None = None) -> Rig:
    """The devices the cell file names. ``seed``, ``backend`` (an override of [robot]
    backend) and ``time_scale`` (the simulated robot's pace: simulated_rig) apply to the
    simulated cell; a real cell has one robot, the JRC, at its own pace."""
    if not config.real:
        from vservo.core.production.simulated_rig import simulated_rig

        return simulated_rig(config, seed, backend, time_scale=time_scale)
    if backend not in (None, config.robot_backend):
        raise ConfigError(
            f"{config.source}: a real cell (camera.source.kind = {config.camera_source.kind!r}) "
            f"is driven by its {config.robot_backend!r} controller, not by the {backend!r} backend"
        )
    return real_rig(config)


def _robot_and_gripper(config: CellConfig, fixture: FixtureClient | None) -> tuple[RobotBackend, VacuumGripper]:
    """The controller of [robot] backend ("jrc" or "ur") and the vacuum cup on its I/O. A
    test cell's JRC is emulated: its fixture keeps the cell clock; a real one's is the wall
    clock (a UR's is its own, in RTDE's timestamp)."""
    vacuum = config.vacuum_device
    if config.robot_backend == "ur":
        from vservo.core.robot.ur import UrBackend
        from vservo.core.robot.ur_script import DigitalOutputs
        from vservo.core.robot.ur_vacuum import UrVacuum
        from vservo.robot_models.loader import controller_base

        ur = UrBackend(config.ur, controller_base(config.arm))
        if vacuum.device == "ur_io" and vacuum.suction_output is not None and vacuum.grip_input is not None:
            return ur, UrVacuum(ur, DigitalOutputs(vacuum.io), vacuum.suction_output, vacuum.grip_input)
        return ur, NoVacuum()
    policy = step_policy_from_config(config.motion)
    if not isinstance(policy, PositionStepPolicy):
        raise ConfigError(f'{config.source}: the JRC takes position steps; set [motion] mode = "position_steps"')
    jrc = JrcBackend(config.jrc, controller_clock=fixture.cell_time_s if fixture else None)
    return jrc, JrcVacuum(jrc, *vacuum.jrc_io()) if vacuum.device == "jrc_io" else NoVacuum()


def real_rig(config: CellConfig) -> Rig:
    """The real cell's devices: the robot's controller (a JRC, or a UR), the camera of
    [camera.source], the cup on the controller's I/O."""
    policy = step_policy_from_config(config.motion)
    model = config.nominal
    intrinsics = model.camera.intrinsics
    # A test cell's part feeder, gauge and clock, on the fixture of [fixture] url; none on a production cell.
    fixture = FixtureClient(config.fixture_url) if config.fixture_url else None
    robot, gripper = _robot_and_gripper(config, fixture)
    camera = open_camera(config.camera_source, (intrinsics.width, intrinsics.height), config.safety.watchdog_s)
    return Rig(
        config=config,
        robot=SafetyLayer.from_config(robot, config),
        gripper=gripper,
        camera=camera,
        extractor=extractor_for(config),
        policy=policy,
        # No gauge on a real cell: the assembly measures the placement by vision alone.
        measure_placement=lambda: None,
        locator=PartLocator.from_config(config),
        reopen_camera=lambda: open_camera(config.camera_source, (intrinsics.width, intrinsics.height), config.safety.watchdog_s),
        present_part=fixture.present_part if fixture else None,
        lay_board=fixture.lay_board if fixture else None,
        place_part=fixture.place_part if fixture else None,
    )


def open_camera(source: CameraSourceConfig, size: tuple[int, int], frame_timeout_s: float) -> FrameSource:
    """The camera of [camera.source] (kind "capture" or "folder"), delivering frames of ``size``
    (width, height), the size the intrinsics were calibrated at; a live camera that sends
    no frame for ``frame_timeout_s`` (the [safety] watchdog) is lost."""
    if source.kind == "capture" and source.device is not None:  # (the cell file requires a device)
        return VideoCaptureSource(
            source.device,
            expected_size=size,
            reconnect_attempts=source.reconnect_attempts,
            reconnect_delay_s=source.reconnect_delay_s,
            loop=source.loop,
            exposure_latency_s=source.exposure_latency_s,
            buffer_frames=source.buffer_frames,
            frame_timeout_s=frame_timeout_s,
        )
    if source.kind == "folder" and source.path is not None:  # (the cell file requires a path)
        folder = ImageFolderSource(source.path, source.pattern)
        # The folder checks its images against its first one; the first is checked here.
        height, width = read_mono8(folder.paths[0]).shape
        if (width, height) != size:
            folder.close()
            raise ConfigError(
                f"camera.source.path: image {str(folder.paths[0])!r} is {width}x{height}, the camera's "
                f"image_size_px is {size[0]}x{size[1]} (width x height)"
            )
        return folder
    raise ValueError(f"camera source {source.kind!r} is not a device: the simulated camera comes with the simulated rig")
