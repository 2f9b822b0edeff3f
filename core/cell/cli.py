"""``vservo info``: the loaded robot, camera and laser settings."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from vservo.core.cell.config import CellConfig, load_cell
from vservo.core.cell.kinematics import ArmKinematics
from vservo.core.geometry.spatial import pose_from_matrix, pose_to_mm_deg
from vservo.core.terminal.command_line import print_result
from vservo.robot_models.loader import load_arm


def _round(values: Any, digits: int = 4) -> Any:
    return (np.round(np.asarray(values, dtype=float), digits) + 0.0).tolist()  # + 0.0: no "-0.0"


def cell_info(config: CellConfig) -> dict[str, Any]:
    """The loaded robot, camera and laser, as one JSON-ready dict (``vservo info``)."""
    arm = ArmKinematics(load_arm(config.arm), config.nominal.mount)
    intrinsics = config.nominal.camera.intrinsics
    laser = config.nominal.laser
    origin, direction = laser.origin_c, laser.direction_c
    # The angle alpha of Fig. 4-2: between the beam and the baseline from laser to camera.
    alpha = float(np.degrees(np.arccos(np.clip(direction @ (-origin / np.linalg.norm(origin)), -1.0, 1.0))))
    return {
        "cell": config.source,
        "robot": {
            "name": arm.name,
            "dof": arm.dof,
            "joint_limits_deg": _round(np.degrees(np.stack([arm.lower, arm.upper], axis=1)), 3),
            "frames": list(arm.frame_names),
            "home_joints_deg": _round(np.degrees(config.home_q), 3),
            "home_flange_pose_mm_deg": _round(pose_to_mm_deg(pose_from_matrix(arm.fk(config.home_q))), 3),
        },
        "camera": {
            "fx_px": round(intrinsics.fx, 4),
            "fy_px": round(intrinsics.fy, 4),
            "principal_point_px": [intrinsics.u0, intrinsics.v0],
            "image_size_px": [intrinsics.width, intrinsics.height],
            "distortion_k1_k2_p1_p2_k3": _round(config.nominal.camera.distortion.as_opencv(), 8),
            "eMc_mm_deg": _round(pose_to_mm_deg(pose_from_matrix(config.nominal.eMc)), 3),
        },
        "laser": {
            "cMl_mm_deg": _round(pose_to_mm_deg(pose_from_matrix(laser.cMl)), 3),
            "baseline_mm": round(float(np.linalg.norm(origin)) * 1000.0, 3),
            "alpha_deg": round(alpha, 3),
            "direction_c": _round(direction, 6),
        },
        "link": {
            "backend": config.robot_backend,
            **config.jrc.in_use(),
        },
        "safety": {
            "workspace_min_mm": _round(config.safety.workspace_min_m * 1000.0, 3),
            "workspace_max_mm": _round(config.safety.workspace_max_m * 1000.0, 3),
            "max_step_mm": round(config.safety.max_step_m * 1000.0, 3),
            "max_step_deg": round(float(np.degrees(config.safety.max_step_rad)), 3),
            "max_speed_mm_s": round(config.safety.max_speed_m_s * 1000.0, 3),
            "joint_margin_deg": round(float(np.degrees(config.safety.joint_margin_rad)), 3),
            "watchdog_s": config.safety.watchdog_s,
        },
        "motion": {
            "mode": config.motion.mode,
            "divide_factor": config.motion.divide_factor,
            "sampling_period_s": config.motion.sampling_period_s,
            "speed_mm_s": config.motion.speed_m_s * 1000.0,
        },
    }


def _cmd_info(args: argparse.Namespace) -> int:
    print_result(cell_info(load_cell(args.cell)), args.json)
    return 0


def add_info_command(commands: argparse._SubParsersAction) -> None:
    """Register ``vservo info`` on the top-level subcommands."""
    info = commands.add_parser("info", help="print the loaded robot, camera and laser settings")
    info.add_argument("--json", action="store_true", help="one JSON object")
    info.set_defaults(run=_cmd_info)


def _cmd_password_hash(args: argparse.Namespace) -> int:
    import getpass
    import sys

    from vservo.core.cell.line import PasswordHash

    if sys.stdin.isatty():
        password = getpass.getpass("password: ")
        if getpass.getpass("again: ") != password:
            print("vservo password-hash: error: the two passwords differ", file=sys.stderr)
            return 2
    else:
        password = sys.stdin.readline().rstrip("\r\n")
    print(PasswordHash.of(password).text())
    return 0


def add_password_hash_command(commands: argparse._SubParsersAction) -> None:
    """Register ``vservo password-hash`` on the top-level subcommands."""
    command = commands.add_parser(
        "password-hash",
        help="hash an OPC UA user's password for the cell file's [line.opcua.users.NAME] password_hash",
        description="Reads the password from the terminal (twice) or one line of standard input, never from "
        "the command line, and prints its salted PBKDF2-SHA256 hash for password_hash (docs/deployment.md).",
    )
    command.set_defaults(run=_cmd_password_hash)
