"""Synthetic features and desired images for control-law tests: a square face seen by the XC55."""

import numpy as np

from vservo.core.geometry.camera import sony_xc55
from vservo.core.geometry.spatial import Pose6, matrix_from_pose
from vservo.core.perception.features import DesiredImage, ImageFeatures
from vservo.core.sim.plant import visible_region

CAMERA = sony_xc55()
SIDE = 0.02
CORNERS_O = np.array([[0.0, 0.0, 0.0], [SIDE, 0.0, 0.0], [SIDE, SIDE, 0.0], [0.0, SIDE, 0.0]])
# The desired pose of task 1 (Table 5-1): the face 0.162 m in front, centred near the spot.
DESIRED_cMo = matrix_from_pose(Pose6(0.011, -0.01, 0.162, np.pi, 0.0, -np.pi))
DESIRED_SPOT = np.array([327.2, 240.0])


def project(cMo, points_o=CORNERS_O, camera=CAMERA):
    return camera.project(points_o @ cMo[:3, :3].T + cMo[:3, 3])


def desired_image(cMo=DESIRED_cMo):
    corners = project(cMo)
    depths = (CORNERS_O @ cMo[:3, :3].T + cMo[:3, 3])[:, 2]
    return DesiredImage(corners, DESIRED_SPOT.copy(), float(depths.mean()), cMo, depths)


def features(corners_px, spot_px=DESIRED_SPOT, depth=0.162, corner_depths=None, region=None):
    """Features of corners in pixels (NaN rows unseen); the region defaults to their polygon."""
    corners_px = np.asarray(corners_px, dtype=float)
    if region is None:
        region = visible_region(corners_px, CAMERA.image_size)
    return ImageFeatures(
        corners_px=corners_px,
        laser_spot_px=np.asarray(spot_px, dtype=float),
        laser_depth_m=depth,
        region=region,
        corner_depths_m=np.full(4, depth) if corner_depths is None else np.asarray(corner_depths, dtype=float),
        reference_px=np.full(2, np.nan),
    )


def rotate_about(points_px, centre, angle):
    c, s = np.cos(angle), np.sin(angle)
    R = np.array([[c, -s], [s, c]])
    return (np.asarray(points_px) - centre) @ R.T + centre
