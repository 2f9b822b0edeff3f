"""One servo run of the simulation study: teach, start, servo, evaluate (chapter 5).

The run follows the thesis's procedure on the simulated cell: the camera is put at the
task's desired pose and the desired image is taught from what it sees (features, laser
depth Z*, a pose estimate for the methods that need one); the camera is put at the
initial pose; the control law servoes with the NOMINAL cell model. Only the evaluation
(end-effector path, final pose error) reads the simulator's truth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from vservo.core.cell.config import CellConfig, CellModel
from vservo.core.cell.kinematics import ArmKinematics
from vservo.core.geometry.spatial import Matrix, inverse, pose_error
from vservo.core.perception.camera_source import FrameSource
from vservo.core.perception.features import DesiredImage
from vservo.core.perception.recording import RunRecorder
from vservo.core.perception.vision.pipeline import CameraPerception, ImageFeatureExtractor, front_winding
from vservo.core.robot.backend import RobotBackend
from vservo.core.servo.joint_limits import JointLimitedSteps
from vservo.core.servo.laws.base import Stage
from vservo.core.servo.loop import Cycle, LoopLimits, Perception, ProjectedPerception, ServoOutcome, cycle_record, run_servo
from vservo.core.servo.methods import LawSettings, build_law
from vservo.core.servo.step_policy import IntegratedVelocity, StepPolicy
from vservo.core.servo.teaching import desired_from_features
from vservo.core.sim import Arm
from vservo.core.sim.camera import SimulatedCamera
from vservo.core.sim.free_camera import simulated_robot
from vservo.core.sim.plant import SimulatedCell
from vservo.core.sim.render_settings import RenderSettings
from vservo.core.study.tasks import ServoTask
from vservo.robot_models.loader import load_arm


@dataclass(frozen=True)
class RunSettings(LawSettings):
    """What a study run may change: the control law's settings and the run's own; the
    defaults are the thesis's (all gains 1)."""

    dt_s: float = 0.1
    max_iterations: int = 3000
    features: str = "projected"  # or "rendered": detected in the simulated camera's images
    render: RenderSettings = RenderSettings()
    record_to: str | None = None  # a folder for the run's recording (frames and cycles)
    arm: Arm = Arm.UPJ  # what carries the camera: the cell's arm, or nothing (a free camera)


def perception_for(cell: SimulatedCell, model: CellModel, settings: RunSettings, camera: FrameSource | None = None) -> Perception:
    """The features the run's control law sees: projected points, or detections in rendered
    frames (of ``camera``, by default the cell's simulated camera with ``settings.render``)."""
    if settings.features == "projected":
        return ProjectedPerception(model.camera, model.laser)
    if settings.features == "rendered":
        extractor = ImageFeatureExtractor(model.camera, model.laser, front_winding(cell.state.scene.cube.corners_o))
        return CameraPerception(camera or SimulatedCamera(cell, settings.render), extractor)
    raise ValueError(f"unknown features {settings.features!r}: choose projected or rendered")


def teach(cell: SimulatedCell, cdMo_true: Matrix, model: CellModel, perception: Perception | None = None) -> DesiredImage:
    """Teach the desired image at the true pose cdMo_true (Fig. C-2), with the nominal model."""
    perception = perception or ProjectedPerception(model.camera, model.laser)
    cell.place_camera(cdMo_true)
    seen = perception.perceive(cell.measure(), cell.state.time_s)  # a view of the camera just placed
    return desired_from_features(seen, model.camera, cell.state.scene.cube.side_m)


@dataclass(frozen=True)
class RunTrace:
    """Per-cycle arrays of one run, for figures; truth columns are for evaluation only."""

    time_s: Matrix  # (T,)
    corners_px: Matrix  # (T, 4, 2)
    laser_px: Matrix  # (T, 2)
    cVc: Matrix  # (T, 6)
    error_px: Matrix  # (T,)
    stages: tuple[Stage, ...]
    bMe_position_true: Matrix  # (T + 1, 3): the end-effector path, after every move
    pose_error_true: Matrix  # (T, 2): the camera's translation m, rotation rad to its desired pose


@dataclass(frozen=True)
class RunResult:
    task: str
    method: str
    outcome: ServoOutcome
    desired: DesiredImage
    trace: RunTrace
    path_length_m: float
    straight_line_m: float
    final_translation_m: float
    final_rotation_rad: float

    def summary(self) -> dict[str, Any]:
        """The JSON object of ``vservo simulate --json``."""
        outcome = self.outcome
        return {
            "task": self.task,
            "method": self.method,
            "converged": outcome.converged,
            "failure": outcome.failure.value if outcome.failure else None,
            "reason": outcome.reason,
            "iterations": outcome.iterations,
            "final_error_px": _finite_or_none(outcome.final_error_px),
            "path_length_m": round(self.path_length_m, 6),
            "straight_line_m": round(self.straight_line_m, 6),
            "final_pose_error": {
                "translation_m": round(self.final_translation_m, 6),
                "rotation_rad": round(self.final_rotation_rad, 6),
            },
            "stages": outcome.stages,
        }


def camera_pose_error(cMo: Matrix, cdMo: Matrix) -> tuple[float, float]:
    """(m, rad) between the camera's pose and its desired pose, both seen from the object."""
    return pose_error(inverse(cMo), inverse(cdMo))


def run_task(
    config: CellConfig,
    task: ServoTask,
    settings: RunSettings,
    seed: int | None = None,
    on_cycle: Callable[[Cycle], None] | None = None,
    robot: Callable[[SimulatedCell], RobotBackend] | None = None,
    policy: StepPolicy | None = None,
    camera: Callable[[SimulatedCell], FrameSource] | None = None,
) -> RunResult:
    """Teach ``task``'s desired image, start at its initial pose and servo with ``settings``.

    ``on_cycle`` sees every cycle as the loop does (for benchmarks and recordings).
    ``robot(cell)`` returns the connected, enabled robot that moves the simulated cell
    (say the JRC link to an emulator of it, behind the safety layer); by default the loop
    drives the simulator directly (the arm, or the free camera of ``settings.arm`` none).
    ``policy`` replaces the study's velocity steps of ``settings.dt_s`` (the JRC takes
    position steps). ``camera`` makes the servo's frame
    source on the cell for rendered features (a camera that drops frames, one that times
    them).
    """
    cell = SimulatedCell(config, seed, settings.arm)
    scene = config.plant().scene
    cell.place_cube(task.placement.bMo(scene.table_height_m, scene.cube.side_m))
    model = config.nominal
    desired = teach(cell, task.desired_cMo, model, perception_for(cell, model, settings))
    cell.place_camera(task.initial_cMo)
    # A fresh tracker: nothing carried over from teaching.
    perception = perception_for(cell, model, settings, camera(cell) if camera else None)

    recorder = None
    if settings.record_to is not None:
        meta = {"task": task.name, "cell": config.source, "settings": settings, "desired": desired}
        recorder = RunRecorder(settings.record_to, meta)

    # Evaluation only: the true end-effector path and pose error, read at every cycle
    # (before its move) and once more after the last move.
    path: list[Matrix] = []
    pose_errors: list[tuple[float, float]] = []

    def record(cycle: Cycle) -> None:
        path.append(cell.ground_truth_bMe()[:3, 3])
        pose_errors.append(camera_pose_error(cell.ground_truth_cMo(), task.desired_cMo))
        if recorder is not None:
            recorder.record(getattr(perception, "last_frame", None), cycle_record(cycle))
        if on_cycle is not None:
            on_cycle(cycle)

    outcome = run_servo(
        cell,
        build_law(model, settings),
        desired,
        model,
        policy or IntegratedVelocity(settings.dt_s),
        LoopLimits(max_iterations=settings.max_iterations),
        on_cycle=record,
        perception=perception,
        robot=(robot or simulated_robot)(cell),
        # The arm's limits, on the controller's model of it; a free camera has none.
        joint_limits=JointLimitedSteps(ArmKinematics(load_arm(config.arm), model.mount)) if settings.arm is Arm.UPJ else None,
    )
    path.append(cell.ground_truth_bMe()[:3, 3])
    if recorder is not None:
        recorder.close({"converged": outcome.converged, "failure": outcome.failure, "reason": outcome.reason})
    trace = RunTrace(
        time_s=np.array([c.measurement.time_s for c in outcome.cycles]),
        corners_px=np.array([c.features.corners_px for c in outcome.cycles]),
        laser_px=np.array([c.features.laser_spot_px for c in outcome.cycles]),
        cVc=np.array([c.output.cVc for c in outcome.cycles]),
        error_px=np.array([c.output.error_px for c in outcome.cycles]),
        stages=tuple(c.output.stage for c in outcome.cycles),
        bMe_position_true=np.array(path),
        pose_error_true=np.array(pose_errors),
    )
    positions = trace.bMe_position_true
    translation, rotation = camera_pose_error(cell.ground_truth_cMo(), task.desired_cMo)
    return RunResult(
        task=task.name,
        method=settings.method,
        outcome=outcome,
        desired=desired,
        trace=trace,
        path_length_m=float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()),
        straight_line_m=float(np.linalg.norm(positions[-1] - positions[0])),
        final_translation_m=translation,
        final_rotation_rad=rotation,
    )


def _finite_or_none(value: float) -> float | None:
    return round(float(value), 6) if np.isfinite(value) else None
