"""The ``vservo`` command line."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from core.config import CellConfig, ConfigError, load_cell
from core.kinematics import ArmKinematics, KinematicsError
from core.spatial import pose_from_matrix, pose_to_mm_deg
from robot_models.loader import load_arm


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
        "motion": {
            "mode": config.motion.mode,
            "divide_factor": config.motion.divide_factor,
            "sampling_period_s": config.motion.sampling_period_s,
            "speed_mm_s": config.motion.speed_m_s * 1000.0,
        },
    }


def _cmd_info(args: argparse.Namespace) -> int:
    info = cell_info(load_cell(args.cell))
    if args.json:
        print(json.dumps(info))
    else:
        for section, values in info.items():
            if isinstance(values, dict):
                print(f"{section}:")
                for key, value in values.items():
                    print(f"  {key}: {value}")
            else:
                print(f"{section}: {values}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from core.demo import run_demo

    report = run_demo(load_cell(args.cell), seed=args.seed)
    print(json.dumps(report) if args.json else report_text(report))
    return 0


def report_text(report: dict[str, Any]) -> str:
    lines = []
    for step in report["steps"]:
        lines.append(f"- {step['what']}")
        for key, value in step.items():
            if key != "what":
                lines.append(f"    {key}: {value}")
    return "\n".join([report["title"], *lines])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vservo",
        description="Vision-guided robotic assembly: a camera and a laser pointer on an industrial arm.",
    )
    parser.add_argument("--cell", metavar="FILE", help="cell configuration (TOML); default: the shipped cell")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    info = commands.add_parser("info", help="print the loaded robot, camera and laser settings")
    info.add_argument("--json", action="store_true", help="one JSON object")
    info.set_defaults(run=_cmd_info)

    demo = commands.add_parser("demo", help="a tour of the simulated cell: arm, camera, laser, JRC-style steps")
    demo.add_argument("--seed", type=int, default=None, help="seed of the simulated cell (default: the cell's)")
    demo.add_argument("--json", action="store_true", help="one JSON object")
    demo.set_defaults(run=_cmd_demo)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (ConfigError, KinematicsError, ValueError, OSError) as exc:
        print(f"vservo {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
