"""Image features: what vision hands a control law, and the taught desired image.

A control law sees one ``ImageFeatures`` per cycle and the ``DesiredImage`` taught at the
desired pose; nothing else about the cell except its nominal model. Missing features
are NaN, never dropped, so every array keeps the feature order of the taught image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import Matrix


def pixel_or_none(point: Matrix, digits: int = 4) -> list[float] | None:
    """A pixel for a report: rounded, or None when unseen (NaN)."""
    return None if np.isnan(point).any() else [round(float(v), digits) for v in point]


def pattern_scale(points_px: Matrix) -> float:
    """RMS distance of a point pattern to its centroid (px)."""
    return float(np.sqrt(np.mean(np.sum((points_px - points_px.mean(axis=0)) ** 2, axis=1))))


def polygon_moments(polygon_px: Matrix) -> tuple[float, Matrix]:
    """Area m00 and centroid (m10/m00, m01/m00) of a simple polygon (eqs. 4-33 .. 4-35).

    The moments of the region inside the polygon, by Green's theorem on its edges: the
    exact value of the pixel sums of eq. 4-33 in the limit of small pixels.
    """
    x, y = polygon_px[:, 0], polygon_px[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    m00 = cross.sum() / 2.0
    if abs(m00) < 1e-12:
        return 0.0, np.full(2, np.nan)
    m10 = ((x + xn) * cross).sum() / 6.0
    m01 = ((y + yn) * cross).sum() / 6.0
    return abs(m00), np.array([m10 / m00, m01 / m00])


@dataclass(frozen=True)
class ObjectRegion:
    """The part of the object seen in the image: area m00 (px^2) and centroid (eq. 4-35)."""

    area_px2: float
    centroid_px: Matrix

    @property
    def seen(self) -> bool:
        return self.area_px2 > 0.0


@dataclass(frozen=True)
class ImageFeatures:
    """One frame's measurements as a control law receives them.

    corners_px: the four top-face corners (4, 2) in taught order, NaN where not seen.
    laser_spot_px: (2,), NaN when the spot is not seen.
    laser_depth_m: depth of the spot triangulated with the NOMINAL laser and camera
      (eqs. 4-18 .. 4-21 in general form), NaN without a spot.
    region: the visible object region (stage 1.B).
    corner_depths_m: (4,) per-corner depths from an ideal range sensor, NaN unless the
      cell has one; only the classic-IBVS baseline with "exact" depth uses it, as the
      thesis's comparison did (section 5.2.3).
    reference_px: (2,) the fifth, non-coplanar model point DeMenthon's POSIT needs, NaN
      when not seen.
    """

    corners_px: Matrix
    laser_spot_px: Matrix
    laser_depth_m: float
    region: ObjectRegion
    corner_depths_m: Matrix
    reference_px: Matrix

    @property
    def corners_visible(self) -> NDArray[np.bool_]:
        return ~np.any(np.isnan(self.corners_px), axis=1)

    @property
    def all_corners_visible(self) -> bool:
        return bool(self.corners_visible.all())

    @property
    def laser_visible(self) -> bool:
        """The spot is seen and the model triangulates it (a depth to use)."""
        return self.spot_seen and bool(np.isfinite(self.laser_depth_m))

    @property
    def spot_seen(self) -> bool:
        """The spot is seen in the image, whether or not the model can triangulate it."""
        return not bool(np.isnan(self.laser_spot_px).any())


def laser_depth(laser: LaserPointer, camera: CameraModel, spot_px: Matrix) -> float:
    """Depth of the spot by triangulation with the nominal model, NaN if it cannot be had."""
    if np.isnan(spot_px).any():
        return float("nan")
    try:
        return laser.triangulate(camera, spot_px).depth_m
    except ValueError:
        return float("nan")


@dataclass(frozen=True)
class DesiredImage:
    """What teaching stores (Fig. C-2): the desired features and what follows from them.

    depth_m is Z*, the laser depth at the taught pose, which approximates the depth of
    every corner (a planar part of small height, docs/thesis-notes.md section 5). cdMo is the
    object pose in the desired camera frame estimated from the taught corners with the
    nominal camera (PBVS and the 2.5D normal need it); corner_depths_m are the depths
    of the corners in that estimate.
    """

    corners_px: Matrix
    laser_spot_px: Matrix
    depth_m: float
    cdMo: Matrix
    corner_depths_m: Matrix

    @property
    def centroid_px(self) -> Matrix:
        return self.corners_px.mean(axis=0)
