"""Position-based visual servoing (thesis section 5.2.3, Chaumette & Hutchinson 2006).

The object pose cMo is estimated in every frame from the corners with the nominal
camera: by OpenCV's planar PnP on the four coplanar corners, or by DeMenthon's POSIT
with the fifth, non-coplanar model point as the thesis did. With the taught cdMo, the
current camera in the desired one is c*Mc = c*Mo cMo^-1 and the law on s = (c*t_c, theta u)

    v = -lambda c*Rc^T c*t_c,    w = -lambda theta u(c*Rc)

drives the camera centre along a straight line, which may take the object out of view
(Fig. 5-7): the run then stops with the features lost, as a real cell would.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vservo.core.cell.scene import Cube
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.pose_estimation import PoseEstimationError, pose_from_planar_points, pose_from_posit
from vservo.core.geometry.spatial import Matrix, inverse, theta_u
from vservo.core.perception.features import DesiredImage, ImageFeatures
from vservo.core.servo.laws.base import ControlOutput, Failure, Stage, feature_error_px, verdict_on_all_corners

POSE_ESTIMATORS = ("pnp", "posit")


@dataclass(frozen=True)
class Pbvs:
    camera: CameraModel
    gain: float = 1.0
    pose: str = "pnp"
    final_threshold_px: float = 1.0
    cube_side_m: float = 0.020
    name: str = "pbvs"

    def __post_init__(self) -> None:
        if self.pose not in POSE_ESTIMATORS:
            raise ValueError(f"pose must be one of {POSE_ESTIMATORS}, got {self.pose!r}")

    def estimate_cMo(self, features: ImageFeatures) -> Matrix:
        """Object pose from this frame's corners (and the fifth point for POSIT)."""
        model = Cube(np.eye(4), self.cube_side_m)
        if self.pose == "pnp":
            return pose_from_planar_points(features.corners_px, model.corners_o, self.camera)
        if np.isnan(features.reference_px).any():
            raise PoseEstimationError("the fifth, non-coplanar point is not seen")
        image = np.vstack([features.corners_px, features.reference_px])
        return pose_from_posit(image, np.vstack([model.corners_o, model.reference_b]), self.camera)

    def step(self, features: ImageFeatures, desired: DesiredImage, stage: Stage | None) -> ControlOutput:
        error_px = feature_error_px(features, desired)
        verdict = verdict_on_all_corners(Stage.PBVS, features, error_px, self.final_threshold_px)
        if verdict is not None:
            return verdict
        try:
            cMo = self.estimate_cMo(features)
        except PoseEstimationError as exc:
            return ControlOutput.stop(Stage.PBVS, error_px, Failure.FEATURES_LOST, f"no pose: {exc}")
        cdMc = desired.cdMo @ inverse(cMo)
        v = -self.gain * cdMc[:3, :3].T @ cdMc[:3, 3]
        w = -self.gain * theta_u(cdMc[:3, :3])
        return ControlOutput(np.concatenate([v, w]), Stage.PBVS, error_px, error_px)
