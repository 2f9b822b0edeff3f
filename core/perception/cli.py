"""``vservo detect``: the detectors run on one image file."""

from __future__ import annotations

import argparse

import numpy as np

from vservo.core.cell.config import load_cell
from vservo.core.terminal.command_line import bounded, print_result


def _cmd_detect(args: argparse.Namespace) -> int:
    from vservo.core.cell.scene import Cube
    from vservo.core.perception.camera_source import CameraSourceError, read_mono8
    from vservo.core.perception.vision.pipeline import ImageFeatureExtractor, front_winding

    try:
        image = read_mono8(args.image)
    except CameraSourceError as exc:
        raise ValueError(str(exc)) from None
    config = load_cell(args.cell)
    extractor = ImageFeatureExtractor(
        config.nominal.camera,
        config.nominal.laser,
        front_winding(Cube(np.eye(4)).corners_o),
        spot_threshold=args.spot_threshold,
        region_threshold=args.region_threshold,
    )
    features, report = extractor.extract(image)
    result = {
        "image": args.image,
        "size": [image.shape[1], image.shape[0]],
        **report.as_dict(),
        "laser_depth_mm": None if np.isnan(features.laser_depth_m) else round(features.laser_depth_m * 1000.0, 3),
    }
    print_result(result, args.json)
    return 0


def add_detect_command(commands: argparse._SubParsersAction) -> None:
    """Register ``vservo detect`` on the top-level subcommands."""
    detect = commands.add_parser("detect", help="the laser spot, the four corners and the object region found in one image file")
    detect.add_argument("image", help="image file (8- or 16-bit, grey or colour)")
    detect.add_argument(
        "--spot-threshold", type=bounded(int, 0, 255), default=250, help="fixed level of the laser spot (default 250)"
    )
    detect.add_argument(
        "--region-threshold", type=bounded(int, 0, 255), default=100, help="fixed level of the object region (default 100)"
    )
    detect.add_argument("--json", action="store_true", help="one JSON object")
    detect.set_defaults(run=_cmd_detect)
