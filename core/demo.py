"""A guided tour of the simulated cell (``vservo demo``).

It stands in for an operator at the teach pendant: the arm is jogged to the thesis's
desired pose above the cube (Table 5-1, task 1), the camera and laser are read and the
depth triangulated with the NOMINAL camera and laser, then a few JRC-style steps move
the camera. Only the positioning for teaching reads the simulated layout, as an
operator's eyes would; every reported measurement comes from the plant's sensors.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from core.config import CellConfig
from core.simulator import SimulatedCell
from core.spatial import (
    Pose6,
    exp_twist,
    inverse,
    matrix_from_pose,
    pose_error,
    pose_from_matrix,
    pose_to_mm_deg,
    twist_transform,
)
from core.step_policy import DividedPositionStep, PositionCommand

# Task 1 of Table 5-1: the desired pose of the cube in the camera frame (m, rad).
TEACH_cMo = matrix_from_pose(Pose6(0.011, -0.01, 0.162, np.pi, 0.0, -np.pi))
# A slow sideways and twisting camera motion for the step demonstration (m/s, rad/s).
DEMO_cVc = np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.1])


def _mm_deg(bMx: np.ndarray) -> list[float]:
    return (np.round(pose_to_mm_deg(pose_from_matrix(bMx)), 2) + 0.0).tolist()  # + 0.0: no "-0.0"


def _px(uv: np.ndarray) -> list[Any]:
    return [None if np.isnan(p).any() else np.round(p, 2).tolist() for p in np.atleast_2d(uv)]


def run_demo(config: CellConfig, seed: int | None = None, steps: int = 5) -> dict[str, Any]:
    cell = SimulatedCell(config, seed)
    arm = cell.controller_arm
    nominal = config.nominal
    report: list[dict[str, Any]] = []

    home = cell.measure()
    report.append({
        "what": f"{arm.name} arm at home, {arm.dof} joints",
        "joints_deg": np.round(np.degrees(home.q), 2).tolist(),
        "flange_pose_mm_deg": _mm_deg(home.bMe),
        "corners_seen": int(home.corners_visible.sum()),
    })

    # Teach: put the camera at the task-1 desired pose over the cube.
    bMc_teach = config.simulation.scene.cube.bMo @ inverse(TEACH_cMo)
    move = cell.execute(PositionCommand(bMc_teach @ inverse(nominal.eMc), config.motion.speed_m_s, 0.0))
    teach = cell.measure()
    depth = nominal.laser.triangulate(nominal.camera, teach.laser_spot_px)
    true_depth = cell.ground_truth_cMo()[2, 3]
    report.append({
        "what": "jogged to the teach pose of task 1 (cube 162 mm below the camera)",
        "move_duration_s": round(move.duration_s, 2),
        "flange_pose_mm_deg": _mm_deg(teach.bMe),
        "corners_px": _px(teach.corners_px),
        "laser_spot_px": _px(teach.laser_spot_px)[0],
        "laser_depth_mm": round(depth.depth_m * 1000.0, 3),
        "true_depth_of_cube_face_mm": round(true_depth * 1000.0, 3),
    })

    # JRC style: each control step divided by the factor, one target per sampling period.
    policy = DividedPositionStep(config.motion.divide_factor, config.motion.sampling_period_s,
                                 config.motion.speed_m_s)
    eVe = twist_transform(nominal.eMc) @ DEMO_cVc
    start = cell.measure()
    for _ in range(steps):
        cell.execute(policy.command(cell.measure().bMe, eVe))
    end = cell.measure()
    expected = start.bMe
    for _ in range(steps):
        expected = expected @ exp_twist(eVe / config.motion.divide_factor)
    translation, rotation = pose_error(end.bMe, expected)
    report.append({
        "what": f"{steps} JRC-style steps of the camera twist {DEMO_cVc.tolist()} divided by "
                f"{config.motion.divide_factor:g}, one per {config.motion.sampling_period_s:g} s",
        "elapsed_s": round(end.time_s - start.time_s, 2),
        "flange_moved_mm": round(float(np.linalg.norm(end.bMe[:3, 3] - start.bMe[:3, 3])) * 1000.0, 3),
        "deviation_from_commanded_mm": round(translation * 1000.0, 6),
        "deviation_from_commanded_deg": round(float(np.degrees(rotation)), 6),
        "laser_spot_px": _px(end.laser_spot_px)[0],
    })
    return {"title": f"vservo demo: simulated cell from {config.source}", "steps": report}
