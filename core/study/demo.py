"""A guided tour of the simulated cell (``vservo demo``).

It stands in for an operator at the teach pendant: the arm is jogged to the thesis's
desired pose above the cube (Table 5-1, task 1), the camera and laser are read and the
depth triangulated with the NOMINAL camera and laser, then a few JRC-style steps move
the camera. Only the positioning for teaching reads the simulated layout, as an
operator's eyes would; every reported measurement comes from the plant's sensors.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from vservo.core.cell.config import CellConfig, StepPolicyKind
from vservo.core.geometry.spatial import (
    Matrix,
    Pose6,
    inverse,
    matrix_from_pose,
    pose_error,
    pose_from_matrix,
    pose_to_mm_deg,
    twist_transform,
)
from vservo.core.perception.features import pixel_or_none
from vservo.core.robot.commands import PositionCommand
from vservo.core.servo.step_policy import step_policy_from_config
from vservo.core.sim.plant import SimulatedCell

# Task 1 of Table 5-1: the desired pose of the cube in the camera frame (m, rad).
TEACH_cMo = matrix_from_pose(Pose6(0.011, -0.01, 0.162, np.pi, 0.0, -np.pi))
# A slow sideways and twisting camera motion for the step demonstration (m/s, rad/s).
DEMO_cVc = np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.1])


def _mm_deg(bMx: Matrix) -> list[float]:
    return (np.round(pose_to_mm_deg(pose_from_matrix(bMx)), 2) + 0.0).tolist()  # + 0.0: no "-0.0"


def run_demo(config: CellConfig, seed: int | None = None, steps: int = 5) -> dict[str, Any]:
    cell = SimulatedCell(config, seed)
    arm = cell.jrc_arm
    nominal = config.nominal
    report: list[dict[str, Any]] = []

    home = cell.measure()
    report.append(
        {
            "what": f"{arm.name} arm at home, {arm.dof} joints",
            "joints_deg": np.round(np.degrees(home.q), 2).tolist(),
            "flange_pose_mm_deg": _mm_deg(home.bMe),
            "corners_seen": int(home.corners_visible.sum()),
        }
    )

    # Teach: put the camera at the task-1 desired pose over the cube.
    bMc_teach = config.plant().scene.cube.bMo @ inverse(TEACH_cMo)
    move = cell.execute(PositionCommand(bMc_teach @ inverse(nominal.eMc), config.motion.speed_m_s, 0.0))
    teach = cell.measure()
    depth = nominal.laser.triangulate(nominal.camera, teach.laser_spot_px)
    true_depth = cell.ground_truth_cMo()[2, 3]
    report.append(
        {
            "what": "jogged to the teach pose of task 1 (cube 162 mm below the camera)",
            "move_duration_s": round(move.duration_s, 2),
            "flange_pose_mm_deg": _mm_deg(teach.bMe),
            "corners_px": [pixel_or_none(corner, 2) for corner in teach.corners_px],
            "laser_spot_px": pixel_or_none(teach.laser_spot_px, 2),
            "laser_depth_mm": round(depth.depth_m * 1000.0, 3),
            "true_depth_of_cube_face_mm": round(true_depth * 1000.0, 3),
        }
    )

    # Steps through the cell's motion mode with the thesis's policy, whichever the cell
    # servos with: on the JRC, each control step divided by the factor and one target per
    # sampling period (section 5.3).
    motion = replace(config.motion, policy=StepPolicyKind.THESIS)
    policy = step_policy_from_config(motion)
    eVe = twist_transform(nominal.eMc) @ DEMO_cVc
    start = cell.measure()
    for _ in range(steps):
        bMe = cell.measure().bMe
        command = policy.command(bMe, eVe)
        target = command.target(bMe)
        cell.execute(command)
    end = cell.measure()
    translation, rotation = pose_error(end.bMe, target)
    how = (
        f"JRC-style steps divided by {motion.divide_factor:g}, one per {motion.sampling_period_s:g} s"
        if motion.mode == "position_steps"
        else f"velocity steps of {motion.dt_s:g} s"
    )
    report.append(
        {
            "what": f"{steps} {how}, camera twist {DEMO_cVc.tolist()}",
            "elapsed_s": round(end.time_s - start.time_s, 2),
            "flange_moved_mm": round(float(np.linalg.norm(end.bMe[:3, 3] - start.bMe[:3, 3])) * 1000.0, 3),
            "deviation_from_last_target_mm": round(translation * 1000.0, 6),
            "deviation_from_last_target_deg": round(float(np.degrees(rotation)), 6),
            "laser_spot_px": pixel_or_none(end.laser_spot_px, 2),
        }
    )
    return {"title": f"vservo demo: simulated cell from {config.source}", "steps": report}
