"""A measurement: one sample of everything the cell's sensors report in one look."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import ImageFeatures, ObjectRegion, laser_depth


@dataclass(frozen=True)
class Measurement:
    """One sample of everything the cell's sensors report.

    corners_px holds the four top-face corners in feature order, NaN where a corner is
    outside the image or hidden; laser_spot_px is NaN when the spot is not seen; region
    is the part of the top face inside the image (area and centroid, eqs. 4-33 .. 4-35).
    corner_depths_m comes from the simulator's ideal range sensor (the exact depths the
    thesis gave its classic-IBVS baseline); reference_px is the cube's bottom corner
    below corner 0, the non-coplanar fifth point of DeMenthon's POSIT, NaN when hidden.
    """

    time_s: float
    q: Matrix
    bMe: Matrix
    corners_px: Matrix
    laser_spot_px: Matrix
    region: ObjectRegion
    corner_depths_m: Matrix
    reference_px: Matrix

    @classmethod
    def flange_only(cls, time_s: float, q: Matrix, bMe: Matrix) -> Measurement:
        """The robot's readings with nothing seen: a frame's image is measured apart (or not at all)."""
        unseen = np.full(2, np.nan)
        return cls(time_s, q, bMe, np.full((4, 2), np.nan), unseen, ObjectRegion(0.0, unseen), np.full(4, np.nan), unseen)

    @property
    def corners_visible(self) -> NDArray[np.bool_]:
        return ~np.any(np.isnan(self.corners_px), axis=1)

    @property
    def laser_visible(self) -> bool:
        return not bool(np.isnan(self.laser_spot_px).any())


def features_from_measurement(measurement: Measurement, camera: CameraModel, laser: LaserPointer) -> ImageFeatures:
    """The features of one simulated measurement, with the laser depth from the NOMINAL model."""
    return ImageFeatures(
        corners_px=measurement.corners_px,
        laser_spot_px=measurement.laser_spot_px,
        laser_depth_m=laser_depth(laser, camera, measurement.laser_spot_px),
        region=measurement.region,
        corner_depths_m=measurement.corner_depths_m,
        reference_px=measurement.reference_px,
    )
