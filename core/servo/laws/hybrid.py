"""2.5D visual servoing (Malis, Chaumette & Boudet 1999), the thesis's second baseline.

From the homography between the desired and the current corners (normalized
coordinates), decomposed into c*Rc, t/d* and the plane normal n*, the features are

    e = (x - x*, y - y*, log(Z / Z*), theta u(c*Rc))

for a reference point of the plane (the point whose desired image is the corners'
centroid): x, y its current image, Z/Z* = (H m*)_z its depth ratio. The rotation is
decoupled, w = -lambda theta u, and the translation cancels the rest:

    v = -L_v^-1 (lambda e_v + L_vw w)   (translation_interaction gives L_v, L_vw)

with Z = (Z / Z*) Z* and Z* the laser depth taught at the desired pose. Of the two
physically valid decompositions, the one whose normal is closest to the taught normal
(from the pose estimated at teaching) is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.pose_estimation import PoseEstimationError, decompose_homography, euclidean_homography
from vservo.core.geometry.spatial import Matrix, theta_u
from vservo.core.perception.features import DesiredImage, ImageFeatures
from vservo.core.servo.laws.base import ControlOutput, Failure, Stage, feature_error_px, verdict_on_all_corners


def translation_interaction(x: float, y: float, Z: float) -> tuple[Matrix, Matrix]:
    """(L_v, L_vw): e_v = (x, y, log Z) of a point moves as L_v v + L_vw w (Malis 1999)."""
    L_v = np.array([[-1.0, 0.0, x], [0.0, -1.0, y], [0.0, 0.0, -1.0]]) / Z
    L_vw = np.array([[x * y, -(1.0 + x * x), y], [1.0 + y * y, -x * y, -x], [-y, x, 0.0]])
    return L_v, L_vw


@dataclass(frozen=True)
class Hybrid25D:
    camera: CameraModel
    gain: float = 1.0
    final_threshold_px: float = 1.0
    name: str = "2.5d"

    def step(self, features: ImageFeatures, desired: DesiredImage, stage: Stage | None) -> ControlOutput:
        error_px = feature_error_px(features, desired)
        verdict = verdict_on_all_corners(Stage.HYBRID_25D, features, error_px, self.final_threshold_px)
        if verdict is not None:
            return verdict

        desired_xn = self.camera.pixel_to_normalized(desired.corners_px)
        current_xn = self.camera.pixel_to_normalized(features.corners_px)
        # The taught plane normal, from the camera towards the face: -z of O in C*.
        normal_hint = -desired.cdMo[:3, 2]
        try:
            motion = decompose_homography(euclidean_homography(desired_xn, current_xn), desired_xn, normal_hint)
        except PoseEstimationError as exc:
            return ControlOutput.stop(Stage.HYBRID_25D, error_px, Failure.SINGULAR_JACOBIAN, f"no homography: {exc}")

        m_star = np.append(desired_xn.mean(axis=0), 1.0)
        p = motion.H @ m_star
        rho = p[2]  # Z / Z*
        x, y = p[:2] / p[2]
        x_star, y_star = m_star[:2]
        Z = rho * desired.depth_m
        e_v = np.array([x - x_star, y - y_star, np.log(rho)])
        w = -self.gain * theta_u(motion.cRcd.T)
        L_v, L_vw = translation_interaction(x, y, Z)
        v = -np.linalg.solve(L_v, self.gain * e_v + L_vw @ w)
        return ControlOutput(np.concatenate([v, w]), Stage.HYBRID_25D, error_px, error_px)
