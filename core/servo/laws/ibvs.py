"""Classic image-based visual servoing on the four corners (section 4.2).

v = -lambda L^+ (s - s*) with the point interaction matrix in pixels (eq. 4-14, in the
OpenCV sign convention), evaluated at the current features, at the desired ones, or the
mean of the two (Chaumette & Hutchinson 2006). At the current features the depth of
each point is exact (the thesis's baseline, section 5.2.3: an ideal range sensor), the
laser depth for every point, or the constant taught depth Z*.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.interaction import pixel_interaction_matrix
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import DesiredImage, ImageFeatures
from vservo.core.servo.laws.base import (
    ControlOutput,
    Failure,
    SingularJacobian,
    Stage,
    checked_pinv,
    feature_error_px,
    verdict_on_all_corners,
)

INTERACTIONS = ("current", "desired", "mean")
DEPTHS = ("exact", "laser", "constant")


def corner_depths(features: ImageFeatures, desired: DesiredImage, depth: str) -> Matrix:
    """Depth of each corner for L(s, Z) as the chosen source gives it."""
    if depth == "exact":
        return features.corner_depths_m
    if depth == "laser":
        return np.full(4, features.laser_depth_m)
    return np.full(4, desired.depth_m)


@dataclass(frozen=True)
class ClassicIbvs:
    camera: CameraModel
    gain: float = 1.0
    interaction: str = "current"
    depth: str = "exact"
    final_threshold_px: float = 1.0
    name: str = "ibvs"

    def __post_init__(self) -> None:
        if self.interaction not in INTERACTIONS:
            raise ValueError(f"interaction must be one of {INTERACTIONS}, got {self.interaction!r}")
        if self.depth not in DEPTHS:
            raise ValueError(f"depth must be one of {DEPTHS}, got {self.depth!r}")

    def interaction_matrix(self, features: ImageFeatures, desired: DesiredImage) -> Matrix:
        """The 8x6 interaction matrix the law inverts."""
        L_desired = pixel_interaction_matrix(self.camera, desired.corners_px, np.full(4, desired.depth_m))
        if self.interaction == "desired":
            return L_desired
        L_current = pixel_interaction_matrix(self.camera, features.corners_px, corner_depths(features, desired, self.depth))
        return L_current if self.interaction == "current" else 0.5 * (L_current + L_desired)

    def step(self, features: ImageFeatures, desired: DesiredImage, stage: Stage | None) -> ControlOutput:
        error_px = feature_error_px(features, desired)
        verdict = verdict_on_all_corners(Stage.IBVS, features, error_px, self.final_threshold_px)
        if verdict is not None:
            return verdict
        if self.interaction != "desired" and self.depth != "constant":
            depths = corner_depths(features, desired, self.depth)
            if not np.all(np.isfinite(depths) & (depths > 0)):
                return ControlOutput.stop(Stage.IBVS, error_px, Failure.FEATURES_LOST, f"no {self.depth} depth")
        try:
            L_pinv = checked_pinv(self.interaction_matrix(features, desired))
        except SingularJacobian as exc:
            return ControlOutput.stop(Stage.IBVS, error_px, Failure.SINGULAR_JACOBIAN, str(exc))
        e = (features.corners_px - desired.corners_px).ravel()
        return ControlOutput(-self.gain * L_pinv @ e, Stage.IBVS, error_px, error_px)
