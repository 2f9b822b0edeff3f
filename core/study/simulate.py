"""``vservo simulate``: one run of the simulation study, from the command line's terms."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from vservo.core.cell.config import CellConfig, ConfigError, parse_cell, read_cell_data_with_truth
from vservo.core.cell.kinematics import ArmKinematics
from vservo.core.geometry.spatial import Matrix, matrix_from_pose
from vservo.core.servo.methods import LaserLaw
from vservo.core.sim import Arm
from vservo.core.study.run import RunResult, RunSettings, run_task
from vservo.core.study.tasks import ServoTask, Table53Reading, find_placement, robustness_cell, servo_task
from vservo.robot_models.loader import load_arm


def simulate(
    cell_path: str | Path | None = None,
    task_number: int | None = None,
    method: str = "laser",
    robust: Table53Reading | None = None,
    seed: int | None = None,
    initial: Matrix | None = None,
    desired: Matrix | None = None,
    gain: float = 1.0,
    max_iterations: int = 3000,
    dt_s: float = 0.1,
    features: str = "projected",
    record_to: str | None = None,
    arm: Arm = Arm.UPJ,
    truth: str | Path | None = None,
    laser_law: LaserLaw = LaserLaw.THESIS,
) -> RunResult:
    """Run a task (default task 2) or a scene given by its poses; see ``vservo simulate --help``."""
    config = study_cell(cell_path, robust, truth)
    task = servo_task(task_number or 2, robust is not None)
    if initial is not None or desired is not None:
        task = _scene_task(task, initial, desired, config, arm)
    settings = RunSettings(
        method=method,
        gain=gain,
        dt_s=dt_s,
        max_iterations=max_iterations,
        features=features,
        record_to=record_to,
        arm=arm,
        laser_law=laser_law,
    )
    return run_task(config, task, settings, seed)


def study_cell(cell_path: str | Path | None, robust: Table53Reading | None, truth: str | Path | None) -> CellConfig:
    """The cell of a study run: the ``cell_path`` file (the shipped cell by default) with
    the ``truth`` file's [simulation.truth.*], or turned into the robustness test of
    Table 5-3 as ``robust`` reads it (which sets the model and the truth both)."""
    if robust is not None and truth is not None:
        raise ConfigError("--robust sets the true cell itself (Table 5-3): give it or --truth, not both")
    data, source = read_cell_data_with_truth(cell_path, truth)
    if robust is not None:
        data, source = robustness_cell(data, robust), f"{source} with the errors of Table 5-3 ({robust} reading)"
    return parse_cell(data, source)


def _scene_task(task: ServoTask, initial: Matrix | None, desired: Matrix | None, config, arm: Arm) -> ServoTask:
    """The task with its poses replaced, placed where the arm can serve it (a free camera
    serves the task's own placement)."""
    initial_cMo = matrix_from_pose(initial) if initial is not None else task.initial_cMo
    desired_cMo = matrix_from_pose(desired) if desired is not None else task.desired_cMo
    placement = task.placement
    if arm is Arm.UPJ:
        kinematics = ArmKinematics(load_arm(config.arm), config.nominal.mount)
        scene = config.plant().scene
        placement, _ = find_placement(
            kinematics,
            config.home_q,
            scene.table_height_m,
            scene.cube.side_m,
            initial_cMo,
            desired_cMo,
            config.plant().truth.eMc,
        )
    return replace(
        task,
        name="scene",
        initial_cMo=initial_cMo,
        desired_cMo=desired_cMo,
        placement=placement,
        description="poses given on the command line",
    )
