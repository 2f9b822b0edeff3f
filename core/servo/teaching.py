"""Teaching the desired image (Fig. C-2): from the features seen at the taught pose.

What teaching stores is what a control law may use: the taught features, the laser depth
Z* measured there, and the part's pose estimated from the taught corners with the
NOMINAL camera (PBVS and the 2.5D normal need it). Nothing here reads a simulator.
"""

from __future__ import annotations

import numpy as np

from vservo.core.cell.scene import Cube
from vservo.core.errors import VservoError
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.pose_estimation import PoseEstimationError, pose_from_planar_points
from vservo.core.perception.features import DesiredImage, ImageFeatures


class TeachError(VservoError, ValueError):
    """The view cannot be taught; the message says what is missing."""


def desired_from_features(features: ImageFeatures, camera: CameraModel, part_side_m: float) -> DesiredImage:
    """The desired image of a part of side ``part_side_m`` from the features seen at the taught pose."""
    missing = [
        name
        for name, seen in (("all four corners", features.all_corners_visible), ("the laser spot", features.laser_visible))
        if not seen
    ]
    if missing:
        raise TeachError(f"the desired view must show {' and '.join(missing)}")
    part = Cube(np.eye(4), part_side_m)
    try:
        cdMo = pose_from_planar_points(features.corners_px, part.corners_o, camera)
    except PoseEstimationError as exc:
        raise TeachError(f"cannot estimate the taught pose: {exc}") from exc
    corner_depths = (part.corners_o @ cdMo[:3, :3].T + cdMo[:3, 3])[:, 2]
    return DesiredImage(features.corners_px, features.laser_spot_px, features.laser_depth_m, cdMo, corner_depths)
