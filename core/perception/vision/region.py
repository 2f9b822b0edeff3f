"""The object's region: area and centroid from image moments (thesis section 4.4, stage 1.B).

Stage 1.B of the thesis servos on "the area occupied by pixels satisfying the required
threshold": the object's pixels by a fixed-level threshold, their area m00 and centroid
(m10 / m00, m01 / m00) from the moments of eqs. 4-33 .. 4-35. It works when the object
is only partly in view, which is when it is needed: ``touches_border`` says so.

The laser spot is bright enough to pass any threshold, so it is not object evidence on
its own: a bright blob made only of the spot (its clipped core and its halo) is dropped.
Holes inside the object (the dark orientation mark on the top face) belong to it, as they
do to the projected face the simulator measures (vservo.core.sim.plant.visible_region).

Pixel convention (OpenCV): the pixel at row r, column c has its centre at (u, v) = (c, r),
which is also what cv2.moments sums.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vservo.core.perception.features import ObjectRegion
from vservo.core.perception.vision.edges import bright_contours, frozen_array, image_problem

#: Pixels at or above this level are the laser spot (or clipped), not evidence of the object.
SATURATED_LEVEL = 250
#: How far the spot's halo reaches beyond its clipped core (px).
SPOT_HALO_PX = 3
#: Clipped blobs up to this many pixels are a laser spot; larger ones are scene (a glare).
MAX_SPOT_AREA_PX = 150


@dataclass(frozen=True)
class RegionDetection:
    """The object's region in one image.

    region: area m00 (px^2) and centroid (u, v); area 0 and NaN centroid when not found.
    touches_border: the region reaches the image border (the object is cut: stage 1.B).
    confidence: in [0, 1]; 0 when not found, lower when the region is cut by the border.
    reason: "" on success, otherwise why no region is given.
    """

    region: ObjectRegion
    touches_border: bool
    confidence: float
    reason: str

    @property
    def found(self) -> bool:
        return self.region.seen


def _no_region(reason: str) -> RegionDetection:
    return RegionDetection(ObjectRegion(0.0, frozen_array([np.nan, np.nan], (2,))), False, 0.0, reason)


def detect_object_region(image: np.ndarray, threshold: float = 100, min_area_px2: float = 30) -> RegionDetection:
    """The object's pixels (>= ``threshold``), its largest part, and their moments; never raises.

    Connected parts (8-connected, holes filled) with fewer than ``min_area_px2`` pixels
    outside the laser spot's reach count as nothing; of the others the largest is the
    object.
    """
    try:
        return _detect(image, threshold, min_area_px2)
    except Exception as error:  # noqa: BLE001 - a detector reports, it never raises
        return _no_region(f"region detection failed: {type(error).__name__}: {error}")


def _detect(image: np.ndarray, threshold: float, min_area_px2: float) -> RegionDetection:
    problem = image_problem(image)
    if problem:
        return _no_region(problem)
    img = np.ascontiguousarray(image)
    height, width = img.shape
    contours = bright_contours(img, threshold, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return _no_region(f"no object: no pixel at or above {threshold:g}")
    chosen = _with_evidence(img, contours, min_area_px2)
    if chosen is None:
        # Around the largest bright region there was only the spot: the whole frame.
        chosen = _with_evidence(img, bright_contours(img, threshold, cv2.CHAIN_APPROX_SIMPLE, whole_frame=True), min_area_px2)
    if chosen is None:
        return _no_region(
            f"no object: no region of at least {min_area_px2:g} px^2 at or above {threshold:g} besides the laser spot"
        )

    mask, x, y, w, h = chosen
    moments = cv2.moments(mask, binaryImage=True)
    m00 = moments["m00"]
    if m00 >= 0.95 * height * width:
        return _no_region(f"region fills the whole image ({m00:.0f} px^2): overexposed or saturated frame")
    centroid = np.array([moments["m10"] / m00 + x, moments["m01"] / m00 + y])
    touches = x <= 0 or y <= 0 or x + w >= width or y + h >= height
    confidence = (0.7 if touches else 1.0) * float(min(1.0, m00 / (10.0 * max(min_area_px2, 1.0))))
    return RegionDetection(ObjectRegion(float(m00), frozen_array(centroid, (2,))), bool(touches), confidence, "")


def _with_evidence(
    img: np.ndarray, contours: list[np.ndarray], min_area_px2: float
) -> tuple[np.ndarray, int, int, int, int] | None:
    """The largest region (filled mask and its box x, y, w, h) with at least
    ``min_area_px2`` pixels outside the laser spot's reach, or None."""
    outline = np.array([cv2.contourArea(c) for c in contours])
    for index in np.argsort(-outline, kind="stable"):
        contour = contours[int(index)]
        x, y, w, h = cv2.boundingRect(contour)
        if w * h < min_area_px2:
            break  # this and all smaller ones cannot hold min_area_px2 pixels
        mask = np.zeros((h, w), np.uint8)
        cv2.drawContours(mask, [contour], -1, 1, thickness=cv2.FILLED, offset=(-x, -y))
        evidence = mask & (1 - _spot_zone(img[y : y + h, x : x + w]))
        if cv2.countNonZero(evidence) >= min_area_px2:
            return mask, x, y, w, h
    return None


def _spot_zone(roi: np.ndarray) -> np.ndarray:
    """1 within the reach of small clipped blobs (the laser spot and its halo), else 0.

    Only the rectangle holding the clipped pixels (grown by the halo) is labelled: the
    spot is a few pixels in a large region.
    """
    zone = np.zeros(roi.shape, np.uint8)
    if cv2.minMaxLoc(roi)[1] < SATURATED_LEVEL:
        return zone
    saturated = (roi >= SATURATED_LEVEL).view(np.uint8)
    x, y, w, h = cv2.boundingRect(saturated)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(saturated[y : y + h, x : x + w], connectivity=8)
    small = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] <= MAX_SPOT_AREA_PX) + 1
    if small.size == 0:
        return zone
    keep = np.zeros(count, np.uint8)
    keep[small] = 1
    height, width = roi.shape
    x0, y0 = max(x - SPOT_HALO_PX, 0), max(y - SPOT_HALO_PX, 0)
    x1, y1 = min(x + w + SPOT_HALO_PX, width), min(y + h + SPOT_HALO_PX, height)
    zone[y : y + h, x : x + w] = keep[labels]
    size = 2 * SPOT_HALO_PX + 1
    zone[y0:y1, x0:x1] = cv2.dilate(zone[y0:y1, x0:x1], cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size)))
    return zone
