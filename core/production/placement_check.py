"""Placement checked by vision: where the placed part's top face is, seen from the check pose.

Teaching stores a check view: a flange pose over the metal part and the top-face corners
the camera saw there with the part correctly placed. After a release the assembly goes
back to that pose and looks again; the part's displacement in its own top plane is the
run's placement error, measured by the cell's own camera on any cell.

From pixels to millimetres, by the part's known side rather than the camera's depth:
the top face is a plane, and the pinhole projection (eqs. 2-1 .. 2-3) of a plane is a
homography H between its points and the undistorted normalized image coordinates. The
four taught corners and the square of side ``part_side_m`` they are the corners of fix
H exactly (four point pairs, eight unknowns), so

    p = H x_n    (p in metres in the taught top face, x_n = camera.pixel_to_normalized(u, v))

maps the centre seen now (the crossing of the face's diagonals, the image of the face's
centre under any perspective) into the taught top plane, and the error is
|p - (s/2, s/2)|. The scale comes from the part in the same image, so neither the
check pose's depth nor the focal length enter it (the camera model only removes lens
distortion), and the perspective of a camera not quite square to the face is exact,
where a single mm-per-px factor would not be. It holds while the part lies flat at the
taught height (its bottom on the pocket floor): a part resting on the pocket's walls is
beyond any tolerance anyway. Which corner comes first does not matter: any cyclic order
of a square's corners differs from another by a turn or flip of the square, which
keeps distances.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import Matrix


@dataclass(frozen=True)
class CheckView:
    """The taught check view: the flange pose over the metal part (base frame, as the
    JRC reports it) and the part's top-face corners (4, 2) in px the camera saw there with
    the part correctly placed, in the extractor's order."""

    check_bMe: Matrix
    corners_px: Matrix


@dataclass(frozen=True)
class PlacementCheck:
    """What the check found: whether the four corners were seen and, if so, how far the
    top face's centre is from where it was taught (offset_mm in the taught top face's
    axes, error_mm its length)."""

    found: bool
    offset_mm: Matrix
    error_mm: float


NOT_FOUND = PlacementCheck(False, np.full(2, np.nan), float("nan"))


def diagonals_crossing(corners: Matrix) -> Matrix:
    """Where the diagonals of a convex quadrilateral (4, 2) cross: the image of a square's
    centre under any perspective (the corners' mean is not, off the axis). The corners are
    taken round the face first (by their angle about their mean), whatever order they come
    in: a tracker may hand them over out of order after the part turned, and the crossing
    of two sides instead of the diagonals lies far off the face."""
    corners = np.asarray(corners, dtype=float)
    around = corners - corners.mean(axis=0)
    a, b, c, d = corners[np.argsort(np.arctan2(around[:, 1], around[:, 0]))]
    # a + t (c - a) = b + s (d - b), solved for t.
    t, _ = np.linalg.solve(np.column_stack([c - a, b - d]), b - a)
    return a + t * (c - a)


def check_placement(check: CheckView, corners_px: Matrix, camera: CameraModel, part_side_m: float) -> PlacementCheck:
    """The placement error seen from the check pose (module docstring: p = H x_n).

    corners_px: the corners (4, 2) seen now, NaN where unseen; fewer than four is
    NOT_FOUND (the part is not where the check view looks).
    """
    corners_px = np.asarray(corners_px, dtype=float)
    if corners_px.shape != (4, 2) or not np.all(np.isfinite(corners_px)):
        return NOT_FOUND
    taught_n = camera.pixel_to_normalized(check.corners_px)
    seen_n = camera.pixel_to_normalized(corners_px)
    square_m = part_side_m * np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    H = cv2.getPerspectiveTransform(taught_n.astype(np.float32), square_m.astype(np.float32))
    try:
        centre_n = diagonals_crossing(seen_n)
    except np.linalg.LinAlgError:  # parallel diagonals: no face, whatever the detector said
        return NOT_FOUND
    p = H @ np.append(centre_n, 1.0)
    offset_mm = 1000.0 * (p[:2] / p[2] - part_side_m / 2)
    return PlacementCheck(True, offset_mm, float(np.hypot(*offset_mm)))
