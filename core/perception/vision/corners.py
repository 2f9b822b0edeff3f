"""The four corners of the cube's top face, sub-pixel and in the taught order.

The thesis detects the object's corners in the image; here the top face is the
brightest sizeable region of the scene, so it is found by a threshold between its grey
level and the next darker one (a side face or the table, read off the histogram), as the
largest convex quadrilateral; touching the image border, it is refused. Its corners are
then refined from the straight sides:

- lines through the threshold outline's points start each side, leaving out the laser
  spot's disc (it passes any threshold, and next to the face it bulges the outline);
- each side's edge is located strip by strip across it by the partial-area effect
  (``vservo.core.perception.vision.edges.edge_points_many``: exact for box-filtered edges, nearly so under
  a mild symmetric blur), in narrow strips that stay on a side face a few pixels wide,
  away from the corners, the laser spot and the orientation mark; a line is fitted to
  each side robustly; along a side within a degree or so of a pixel row or column the
  outline's line can be a pixel off at one end, and strips that see the edge on part
  of the side only are read again twice as wide; a fit that turns its line or whose
  points bunch on part of the side is not trusted (re-centred and tried again);
- a side face narrower than that, down to a sliver under a pixel seen almost edge-on,
  biases the partial-area line outwards by its width times its relative level: where
  the pixels along a side do not fit a single step, the side is fitted as a three-level
  edge, face - side face - table, whose side face is a box's (``vservo.core.perception.vision.bands``);
- a side face so thin that the histogram does not show it can be taken for top face by
  the threshold; the outline then runs along its outer edge, which the grey level just
  inside betrays, and the region is taken again with a threshold near the face's level;
- adjacent lines cross at the corners. A spot sitting on a corner therefore leaves the
  corner where the sides say it is.

Order: corner 0 is the corner nearest the orientation mark (the dark disc on the top
face, found inside the quadrilateral, its centre by darkness-weighted centroid); the
others follow around the face with the requested winding. Without the mark, the last
frame's ordered corners fix the order (the cyclic shift nearest to them).

Known limits: the sides are straight lines, so lens distortion (curved edges) biases the
corners unless the image is undistorted first; a side face along a side nearly aligned
with the pixel grid can leave two explanations of its pixels (a thin bright sliver or a
wider dimmer one) that only its taper to a corner tells apart, and a fit may settle on
the wrong one (a few tenths of a pixel); under optical blur the band's edges melt into
one ramp and the three-level fit is an approximation (a Gaussian for pixel, slant and
blur together).

Pixel convention (OpenCV): the pixel at row r, column c has its centre at (u, v) = (c, r).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.vision.bands import banded_lines
from vservo.core.perception.vision.edges import (
    Strips,
    bright_contours,
    edge_points_many,
    fit_lines,
    frozen_array,
    image_problem,
    polygon_corners,
    sample_strips,
    segment_medians,
)
from vservo.core.perception.vision.spot import SpotDetection

#: Smallest top face, in pixels of area, worth measuring.
MIN_FACE_AREA_PX = 100.0
#: Pixels at or above this level are the laser spot (or clipped), not the scene.
SATURATED_LEVEL = 250
#: The orientation mark's radius as a fraction of the face side (vservo.core.cell.scene.Cube: side / 8).
MARK_RADIUS_FRACTION = 0.125

#: Smoothing of the grey-level histogram (a Gaussian of sigma 2 levels).
_LEVEL_KERNEL = np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2)
_LEVEL_KERNEL /= _LEVEL_KERNEL.sum()
#: Farthest (px) a refined corner may lie from the threshold outline's polygon: beyond,
#: a side fit has gone astray and no corners are better than wrong ones.
_MAX_MOVE_PX = 4.0
#: A side's fit may turn its line by this little (cos of ~5 degrees), or it is not trusted.
_STEADY_COS = 0.996
#: Nor is a fit whose points span less than this share of the side.
_LEAST_SPAN = 0.4
#: Pixels each side of a side's line read when looking for a narrow side face beyond it.
_BAND_REACH = 5
#: Just inside a side of the top face the image is within this share of the contrast
#: (face against the next darker surface) of the face's level.
_FACE_MARGIN = 0.2
#: What ``_refine`` returns when an outline side runs along a side face.
_DIM_SIDE = "dim side"


@dataclass(frozen=True)
class CornerDetection:
    """The top face's corners in one image.

    corners_px: (4, 2) corners (u, v) in the taught order, NaN rows when not found.
    mark_px: (2,) centre of the orientation mark, NaN if it was not seen.
    confidence: in [0, 1] from the line fits' residuals, their support and the contrast;
      0 when not found.
    reason: "" on success, otherwise why no corners are given.
    """

    found: bool
    corners_px: Matrix
    mark_px: Matrix
    confidence: float
    reason: str


def _no_corners(reason: str, mark_px: Matrix | None = None) -> CornerDetection:
    mark = np.full(2, np.nan) if mark_px is None else mark_px
    return CornerDetection(False, frozen_array(np.full((4, 2), np.nan), (4, 2)), frozen_array(mark, (2,)), 0.0, reason)


def detect_corners(
    image: np.ndarray,
    spot: SpotDetection | None = None,
    previous_px: np.ndarray | None = None,
    winding: int = 1,
) -> CornerDetection:
    """The four corners of the bright top face in ``image`` (uint8, single channel); never raises.

    spot: the laser spot of the same image, if found its surroundings are left out of
      the side fits.
    previous_px: the last frame's ordered corners (4, 2), used to order the corners
      when the orientation mark is not seen.
    winding: +1 orders the corners so that sum(u_i v_{i+1} - u_{i+1} v_i) > 0 (clockwise
      on screen, v pointing down), -1 the other way round.
    """
    try:
        return _detect(image, spot, previous_px, winding)
    except Exception as error:  # noqa: BLE001 - a detector reports, it never raises
        return _no_corners(f"corner detection failed: {type(error).__name__}: {error}")


def _detect(image: np.ndarray, spot: SpotDetection | None, previous_px: np.ndarray | None, winding: int) -> CornerDetection:
    problem = image_problem(image)
    if problem:
        return _no_corners(problem)
    if winding not in (1, -1):
        return _no_corners(f"winding must be +1 or -1, got {winding!r}")
    img = np.ascontiguousarray(image)
    levels = _face_levels(img)
    if levels is None:
        return _no_corners("no bright top face: no grey level stands out above the background")
    face_level, below_level, threshold = levels

    # The spot passes any threshold: where it lies next to the face it bulges the
    # outline, which the side lines must not follow.
    spot_out: list[tuple[Matrix, float]] = []
    if spot is not None and spot.found and np.all(np.isfinite(spot.spot_px)):
        spot_radius = max(5.0, math.sqrt(max(spot.area_px, 0.0) / math.pi) + 4.5)
        spot_out.append((np.asarray(spot.spot_px, dtype=np.float64), spot_radius))
    quad, outline, problem = _rough_quadrilateral(img, threshold, spot_out)
    if quad is None or outline is None:
        return _no_corners(problem)

    mark_px, mark_radius = _find_mark(img, quad, face_level, below_level)
    keep_out = list(spot_out)
    if np.all(np.isfinite(mark_px)):
        keep_out.append((mark_px, mark_radius + 1.5))

    # A side face that the threshold took for top face (too thin for the histogram to
    # show it) puts the outline on its outer edge: then the region is taken again with
    # a threshold just under the face's level.
    face_floor = face_level - _FACE_MARGIN * (face_level - below_level)
    refined = _refine(img, quad, outline, keep_out, spot_out, face_floor)
    if refined == _DIM_SIDE:
        quad, outline, _ = _rough_quadrilateral(img, face_floor, spot_out)
        refined = None if quad is None or outline is None else _refine(img, quad, outline, keep_out, spot_out, -np.inf)
    if refined is None or isinstance(refined, str):  # (the one str _refine returns is _DIM_SIDE)
        return _no_corners("top face sides could not be fitted (too little clean edge)", mark_px)
    corners, side_quality = refined

    ordered, order_problem, by_mark = _order(corners, mark_px, previous_px, winding)
    if ordered is None:
        return _no_corners(order_problem, mark_px)
    contrast = face_level - below_level
    confidence = float(np.clip(contrast / 60.0, 0.0, 1.0) * side_quality * (1.0 if by_mark else 0.8))
    return CornerDetection(True, frozen_array(ordered, (4, 2)), frozen_array(mark_px, (2,)), confidence, "")


# ---------------------------------------------------------------------------------------
# The bright face
# ---------------------------------------------------------------------------------------


def _face_levels(img: np.ndarray) -> tuple[float, float, float] | None:
    """(top-face level, next darker level, threshold between them), from the histogram.

    The top face is the brightest grey level held by enough pixels (the spot's clipped
    pixels aside); the next darker level is the next such peak below it (a side face
    or the table). Peaks are read on a smoothed histogram of every other pixel.
    """
    hist = cv2.calcHist([np.ascontiguousarray(img[::2, ::2])], [0], None, [256], [0, 256]).ravel()
    hist[SATURATED_LEVEL:] = 0.0
    smooth = np.convolve(hist, _LEVEL_KERNEL, mode="same")
    mass = np.convolve(hist, np.ones(13), mode="same")  # pixels within +-6 levels
    min_mass = MIN_FACE_AREA_PX / 4.0  # a surface of the smallest face at least; a quarter of the pixels are sampled
    inner = smooth[1:-1]
    is_peak = (inner >= smooth[:-2]) & (inner > smooth[2:]) & (mass[1:-1] >= min_mass)
    peaks = np.flatnonzero(is_peak)[::-1] + 1  # brightest first
    if peaks.size < 2:
        return None
    face = int(peaks[0])
    for peak in peaks[1:]:
        # The next darker surface is the first peak parted from the face by a valley; a
        # peak without one is the same surface under uneven light.
        valley = float(smooth[peak : face + 1].min())
        if face - peak >= 20 and valley < 0.5 * min(smooth[peak], smooth[face]):
            return float(face), float(peak), 0.5 * (face + peak)
    return None


def _rough_quadrilateral(
    img: np.ndarray, threshold: float, spot_out: list[tuple[Matrix, float]]
) -> tuple[Matrix | None, Matrix | None, str]:
    """The largest bright region's quadrilateral (4, 2) in contour order and its outline
    (boundary pixels, (M, 2)), or None, None and why. The region's convexity is judged
    without the outline's points in the discs of ``spot_out``: the laser spot next to
    the face passes the threshold and stretches the region's hull towards it."""
    height, width = img.shape
    # (the threshold passes pixels above it, as cv2.THRESH_BINARY does)
    contours = bright_contours(img, math.floor(threshold) + 1, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None, None, "no bright top face above the threshold"
    contour = max(contours, key=cv2.contourArea)
    area = cv2.contourArea(contour)
    if area < MIN_FACE_AREA_PX:
        return None, None, f"no bright top face: largest bright region is {area:.0f} px^2"
    x, y, w, h = cv2.boundingRect(contour)
    if x <= 0 or y <= 0 or x + w >= width or y + h >= height:
        return None, None, "object cut by the image border"
    hull = cv2.convexHull(contour)
    hull_area = cv2.contourArea(hull)
    # Convex but for the spot: its bulge, next to the face, stretches the hull.
    points = contour.reshape(-1, 2)
    for centre, radius in spot_out:
        offset = points - centre
        outside = (offset * offset).sum(axis=1) > radius * radius
        if outside.sum() >= 0.5 * len(points):
            points = points[outside]
    face_hull_area = cv2.contourArea(cv2.convexHull(points)) if len(points) < len(contour) else hull_area
    if area < 0.85 * face_hull_area:
        return None, None, f"bright region is not convex (fills {area / face_hull_area:.0%} of its hull)"
    perimeter = cv2.arcLength(hull, True)
    for fraction in (0.02, 0.03, 0.045, 0.06, 0.08, 0.1, 0.015, 0.01):
        approx = cv2.approxPolyDP(hull, fraction * perimeter, True)
        if len(approx) == 4:
            quad = approx.reshape(4, 2).astype(np.float64)
            if cv2.contourArea(quad.astype(np.float32)) >= 0.85 * hull_area:
                return quad, contour.reshape(-1, 2).astype(np.float64), ""
    return None, None, "bright region is not a quadrilateral"


# ---------------------------------------------------------------------------------------
# The orientation mark
# ---------------------------------------------------------------------------------------


def _find_mark(img: np.ndarray, quad: Matrix, face_level: float, below_level: float) -> tuple[Matrix, float]:
    """Centre and radius of the dark disc on the face, (NaN, NaN) and 0 when not seen.

    The largest dark blob inside the face (clear of the sides' blur), if its area is
    within a factor of about three of the mark's, is the mark; its centre is the
    centroid of the darkness (face level - I) around it, inside the face.
    """
    not_seen = np.full(2, np.nan), 0.0
    height, width = img.shape
    x0, y0 = max(int(quad[:, 0].min()) - 1, 0), max(int(quad[:, 1].min()) - 1, 0)
    x1, y1 = min(int(quad[:, 0].max()) + 2, width), min(int(quad[:, 1].max()) + 2, height)
    roi = img[y0:y1, x0:x1]
    centre = quad.mean(axis=0)
    inner = centre + 0.88 * (quad - centre) - np.array([x0, y0])  # clear of the sides' blur
    face_mask = np.zeros(roi.shape, np.uint8)
    cv2.fillConvexPoly(face_mask, np.round(inner * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
    dark_level = min(below_level, face_level - 40.0)
    _, dark = cv2.threshold(roi, 0.5 * (face_level + dark_level), 1, cv2.THRESH_BINARY_INV)
    dark = cv2.bitwise_and(dark, face_mask)
    contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return not_seen
    areas = [cv2.contourArea(c) for c in contours]
    best = int(np.argmax(areas))
    face_area = float(cv2.contourArea(quad.astype(np.float32)))
    expected = math.pi * MARK_RADIUS_FRACTION**2 * face_area
    area = areas[best] + 0.5 * cv2.arcLength(contours[best], True) + 1.0  # outline area to pixel count
    if not 0.3 * expected <= area <= 3.0 * expected:
        return not_seen
    bx, by, bw, bh = cv2.boundingRect(contours[best])
    grow = 2
    sx0, sy0 = max(bx - grow, 0), max(by - grow, 0)
    sx1, sy1 = min(bx + bw + grow, roi.shape[1]), min(by + bh + grow, roi.shape[0])
    darkness = np.clip(face_level - roi[sy0:sy1, sx0:sx1].astype(np.float32), 0.0, None) * face_mask[sy0:sy1, sx0:sx1]
    moments = cv2.moments(darkness)
    if moments["m00"] <= 0.0:
        return not_seen
    mark = np.array([moments["m10"] / moments["m00"] + sx0 + x0, moments["m01"] / moments["m00"] + sy0 + y0])
    return mark, math.sqrt(area / math.pi)


# ---------------------------------------------------------------------------------------
# Sub-pixel sides and corners
# ---------------------------------------------------------------------------------------


def _refine(
    img: np.ndarray,
    quad: Matrix,
    outline: Matrix,
    keep_out: list[tuple[Matrix, float]],
    spot_out: list[tuple[Matrix, float]],
    face_floor: float,
) -> tuple[Matrix, float] | str | None:
    """Corners (4, 2) from the four fitted sides, and a fit quality in [0, 1], or None.

    Start: lines through the threshold outline's points along each side (a few tenths
    of a pixel off). Then partial-area strips around them, narrow enough to stay on a
    side face a few pixels wide, a second time if a line moved much, and the
    three-level fit where a narrower side face runs along a side. None when a side
    cannot be fitted or a corner strays from the outline; ``_DIM_SIDE`` when just inside
    an outline side the image is darker than ``face_floor`` (the outline runs along a
    side face, not along the top face).
    """
    lines = _outline_lines(quad, outline, spot_out)
    if lines is None:
        return None
    allowance = _move_allowance(quad, spot_out)
    corners = polygon_corners(lines)
    if _strayed(corners, quad, allowance):
        return None
    quality = 0.0
    # Wide strips across the sides, read once: for a dim outline side here, for side
    # faces along the sides at the end (their pixels do not move with the lines' last
    # hundredths).
    wide = sample_strips(
        img,
        [(normal, offset, corners[i], corners[(i + 1) % 4]) for i, (normal, offset) in enumerate(lines)],
        _BAND_REACH,
        keep_out,
        _BAND_REACH + 2.0,
    )
    if wide is not None and _dim_inside(wide, len(lines)) < face_floor:
        return _DIM_SIDE
    # Narrow strips: +-1 px holds a box-filtered edge with a slant of up to 1 px per px,
    # and they stay on a side face a few pixels wide. Under blur the ramp spills beyond
    # them, symmetrically about a centred edge; wider strips would swallow side faces.
    # A second pass re-centres the strips when the first moved a line much. Strips
    # clear of the corners (the strips cross the line at the corner, so the distance
    # along the strips' axis is the distance to the corner), the spot and the mark.
    for attempt in range(2):
        segments = [(normal, offset, corners[i], corners[(i + 1) % 4]) for i, (normal, offset) in enumerate(lines)]
        sides = edge_points_many(img, segments, 1.0, 1, keep_out, 4.0)
        fits = fit_lines(sides, [seg[0] for seg in segments], min_points=6, rounds=3 if attempt else 2)
        spread = [
            fit is not None and _well_spread(points[fit[2]], *segment[2:])
            for segment, points, fit in zip(segments, sides, fits, strict=True)
        ]
        lost = [i for i, well in enumerate(spread) if not well]
        if lost:
            # The outline can be a pixel off an edge along a row or a column, beyond
            # these strips' reach: along a side within a degree or so of the pixel grid
            # the outline is a staircase of one step or none, its line up to a pixel
            # off at one end, and these strips find the edge on part of the side only
            # (their points bunch) or nowhere. +-2 px strips for those sides, taken
            # where they cover the side.
            wider = edge_points_many(img, [segments[i] for i in lost], 1.5, 1, keep_out, 4.5)
            refits = fit_lines(wider, [segments[i][0] for i in lost], min_points=6, rounds=2)
            for i, points, fit in zip(lost, wider, refits, strict=True):
                if fit is not None and _well_spread(points[fit[2]], *segments[i][2:]):
                    sides[i], fits[i], spread[i] = points, fit, True
                elif fits[i] is None:
                    sides[i], fits[i] = points, fit
        new_lines, qualities = [], []
        recentred = False
        for (normal, offset, _, _), points, fit, well in zip(segments, sides, fits, spread, strict=True):
            if fit is None or float(fit[0] @ normal) < _STEADY_COS:
                # Too few clean strips, or the line turned (a narrow side face right
                # along the side): keep the line; the band fit may correct it.
                new_lines.append((normal, offset))
                qualities.append(0.0)
                continue
            line_normal, line_offset, inliers, rms = fit
            if not well:
                # The points bunch up: strips off the edge (then re-centred on the
                # points, keeping the direction, to try again) or a narrow side face
                # that only a few strips see past (kept for the band fit).
                new_lines.append((normal, float(normal @ points[inliers].mean(axis=0)) if attempt == 0 else offset))
                qualities.append(0.0)
                recentred = attempt == 0
                continue
            new_lines.append((line_normal, line_offset))
            inlier_count = np.count_nonzero(inliers)
            support = min(inlier_count / 10.0, 1.0) * (0.5 + 0.5 * inlier_count / len(inliers))
            qualities.append(support / (1.0 + (rms / 0.2) ** 2))
        if sum(quality > 0.0 for quality in qualities) < 2 and not recentred:
            return None  # (re-centred sides get their second pass first)
        quality = float(min(qualities))
        moved = max(abs(float(new[0] @ corners[i]) - new[1]) for i, new in enumerate(new_lines))
        lines = new_lines
        corners = polygon_corners(lines)
        if _strayed(corners, quad, allowance):
            return None
        if attempt == 0 and moved < 0.75 and not recentred:
            break  # the strips were centred well enough
    # A side face narrower than the strips would pull a side outwards.
    if wide is not None:
        for i, banded in enumerate(banded_lines(wide, lines)):
            if banded is not None:
                lines[i] = banded.line
    corners = polygon_corners(lines)
    if _strayed(corners, quad, allowance):
        return None
    return corners, quality


def _least_squares_lines(points: Matrix, members: np.ndarray, hints: Matrix) -> list[tuple[Matrix, float]] | None:
    """One least-squares line per column of ``members`` (M, K) through its points, as
    (unit normal oriented like ``hints`` (K, 2), offset moved half a pixel against the
    normal: the outline's pixel centres lie that far inside the threshold's crossing);
    None if a line has fewer than four points. The residuals are taken across each
    line's main direction, as in ``fit_lines``; all lines from one matrix product.
    """
    weights = members.astype(np.float64)
    u, v = points[:, 0], points[:, 1]
    moments = np.empty((len(points), 6))
    moments[:, 0], moments[:, 1], moments[:, 2] = 1.0, u, v
    np.multiply(points, points, out=moments[:, 3:5])
    np.multiply(u, v, out=moments[:, 5])
    sums = weights.T @ moments  # (K, 6): count, u, v, uu, vv, uv
    count = sums[:, 0]
    if count.min() < 4:
        return None
    steep = np.abs(hints[:, 0]) > np.abs(hints[:, 1])  # then u = slope v + intercept
    s_a, s_b = np.where(steep, sums[:, 2], sums[:, 1]), np.where(steep, sums[:, 1], sums[:, 2])
    s_aa = np.where(steep, sums[:, 4], sums[:, 3])
    det = count * s_aa - s_a * s_a
    if det.min() <= 1e-12:
        return None
    slope = (count * sums[:, 5] - s_a * s_b) / det
    intercept = (s_b - slope * s_a) / count
    normals = np.empty((len(slope), 2))
    normals[:, 0] = np.where(steep, 1.0, -slope)
    normals[:, 1] = np.where(steep, -slope, 1.0)
    scale = np.sqrt(1.0 + slope * slope)
    flip = np.where((normals * hints).sum(axis=1) < 0.0, -1.0, 1.0) / scale
    normals *= flip[:, None]
    offsets = (intercept * flip - 0.5).tolist()
    return [(normals[i], offsets[i]) for i in range(len(hints))]


def _distance_to_outline(point: Matrix, polygon: Matrix) -> float:
    """Distance from ``point`` to the closed polygon's sides."""
    direction = np.concatenate((polygon[1:], polygon[:1])) - polygon
    share = np.clip(((point - polygon) * direction).sum(axis=1) / (direction * direction).sum(axis=1), 0.0, 1.0)
    offset = polygon + share[:, None] * direction - point
    return math.sqrt(float((offset * offset).sum(axis=1).min()))


def _well_spread(points: Matrix, start: Matrix, stop: Matrix) -> bool:
    """Whether edge points cover enough of the side from ``start`` to ``stop`` to fix its line."""
    if not len(points):
        return False
    direction = stop - start
    length2 = float(direction @ direction)
    along = (points - start) @ direction
    return length2 > 0.0 and float(along.max() - along.min()) >= _LEAST_SPAN * length2


def _move_allowance(quad: Matrix, spot_out: list[tuple[Matrix, float]]) -> Matrix:
    """How far (px) each corner may move from the outline's quadrilateral: as far as a
    side fit can move it, and for a corner under the spot's disc (missing from the
    outline) as far again as the disc's radius."""
    allowance = np.full(len(quad), _MAX_MOVE_PX)
    for centre, radius in spot_out:
        offset = quad - centre
        allowance[(offset * offset).sum(axis=1) < (radius + _MAX_MOVE_PX) ** 2] += radius
    return allowance


def _strayed(corners: Matrix, quad: Matrix, allowance: Matrix) -> bool:
    """Whether a corner is not finite or lies farther from the quadrilateral than allowed."""
    return not (np.abs(corners - quad).max(axis=1) <= allowance).all()  # (NaN compares False)


def _dim_inside(strips: Strips, count: int) -> float:
    """The lowest, over the sides, of the median grey level 2 px inside the face."""
    inside = np.where(strips.bright_high, strips.values[:, _BAND_REACH + 2], strips.values[:, -_BAND_REACH - 3])
    levels = segment_medians(inside, strips.segment, count)
    return float(np.nanmin(levels)) if np.any(np.isfinite(levels)) else np.inf


def _outline_lines(quad: Matrix, outline: Matrix, spot_out: list[tuple[Matrix, float]]) -> list[tuple[Matrix, float]] | None:
    """A line per side (inward unit normal, offset) through the outline's points along it.

    The outline runs through the centres of the region's boundary pixels, on average
    half a pixel inside the threshold's crossing: the lines are moved out by that much.
    Outline points within the discs of ``spot_out`` are left out: the laser spot next
    to the face passes the threshold and bulges the outline, and can pull a corner of
    the quadrilateral off the face: with the spot next to the outline, the points are
    taken again near the first lines.
    """
    corners = quad
    lines: list[tuple[Matrix, float]] = []
    spot_near = any(_distance_to_outline(centre, quad) < radius + 2.0 for centre, radius in spot_out)
    for _ in range(2):
        edges = corners[[1, 2, 3, 0]] - corners
        lengths = np.sqrt((edges * edges).sum(axis=1))
        directions = edges / lengths[:, None]
        normals = directions[:, ::-1] * np.array([-1.0, 1.0])
        normals *= np.where(((corners.sum(axis=0) / len(corners) - corners) * normals).sum(axis=1) < 0.0, -1.0, 1.0)[:, None]
        along = outline @ directions.T - (corners * directions).sum(axis=1)  # (M, 4)
        across = outline @ normals.T - (corners * normals).sum(axis=1)
        margin = 2.0 + 0.1 * lengths
        near = (np.abs(across) < 2.0) & (along > margin) & (along < lengths - margin)
        for centre, radius in spot_out:
            offset = outline - centre
            near &= ((offset * offset).sum(axis=1) > radius * radius)[:, None]
        fitted = _least_squares_lines(outline, near, normals)
        if fitted is None:
            return None
        lines = fitted
        corners = polygon_corners(lines)
        if not (np.all(np.isfinite(corners)) and spot_near):
            break
    return lines


# ---------------------------------------------------------------------------------------
# Order
# ---------------------------------------------------------------------------------------


def _signed_area2(points: Matrix) -> float:
    following = points[[1, 2, 3, 0]]
    return float((points[:, 0] * following[:, 1] - following[:, 0] * points[:, 1]).sum())


def _order(corners: Matrix, mark_px: Matrix, previous_px: np.ndarray | None, winding: int) -> tuple[Matrix | None, str, bool]:
    """Corners in the taught order, or None and why; True when the mark fixed the order."""
    if _signed_area2(corners) * winding < 0.0:
        corners = corners[::-1].copy()
    if np.isfinite(mark_px).all():
        offset = corners - mark_px
        distance = np.sqrt((offset * offset).sum(axis=1))
        nearest = int(distance.argmin())
        if distance[nearest] < 0.75 * np.partition(distance, 1)[1]:
            return corners[(np.arange(4) + nearest) % 4], "", True
    previous = _valid_previous(previous_px)
    if previous is None:
        return None, "cannot tell corner 0: orientation mark not seen and no previous corners", False
    seen = np.isfinite(previous).all(axis=1)
    shifted = corners[(np.arange(4)[None, :] + np.arange(4)[:, None]) % 4]  # (shift, corner, 2)
    offset = shifted[:, seen] - previous[seen]
    shift = int((offset * offset).sum(axis=(1, 2)).argmin())
    return shifted[shift].copy(), "", False


def _valid_previous(previous_px: object) -> Matrix | None:
    """The previous corners as (4, 2) floats with at least two seen, or None."""
    if previous_px is None:
        return None
    try:
        previous = np.asarray(previous_px, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if previous.shape != (4, 2) or np.all(np.isfinite(previous), axis=1).sum() < 2:
        return None
    return previous
