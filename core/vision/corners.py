"""The four corners of the cube's top face, sub-pixel and in the taught order.

The thesis detects the object's corners in the image; here the top face is the
brightest sizeable region of the scene, so it is found by a threshold between its grey
level and the next darker one (a side face or the table, read off the histogram), as the
largest convex quadrilateral; touching the image border, it is refused. Its corners are
then refined from the straight sides:

- each side's edge is located strip by strip across it by the partial-area effect
  (``core.vision.edge_points_many``: exact for box-filtered edges, nearly so under a
  mild symmetric blur), in narrow strips that stay on a side face a few pixels wide,
  away from the corners, the laser spot and the orientation mark;
- a side face narrower than that (a cube seen nearly from above) is fitted as a
  three-level profile, face - side face - table, along the side, with the image's blur
  read off the sides;
- a side face so thin that the histogram does not show it can be taken for top face by
  the threshold; the outline then runs along its outer edge, which the grey level just
  inside betrays, and the region is taken again with a threshold near the face's level;
- a line is fitted to each side robustly and adjacent lines cross at the corners. A
  spot sitting on a corner therefore leaves the corner where the sides say it is.

Order: corner 0 is the corner nearest the orientation mark (the dark disc on the top
face, found inside the quadrilateral, its centre by darkness-weighted centroid); the
others follow around the face with the requested winding. Without the mark, the last
frame's ordered corners fix the order (the cyclic shift nearest to them).

Known limits: the sides are straight lines, so lens distortion (curved edges) biases the
corners unless the image is undistorted first; a side face under ~1 px wide cannot be
told from the edge's own blur and moves its side out by up to its width times its
relative grey level; under optical blur (sigma 0.5 - 0.8 px) side faces up to a few
pixels wide melt into the edge and bias their side by a few tenths of a pixel.

Pixel convention (OpenCV): the pixel at row r, column c has its centre at (u, v) = (c, r).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.spatial import Matrix
from core.vision.edges import Strips, edge_points_many, fit_lines, frozen_array, image_problem, intersect, sample_strips
from core.vision.spot import SpotDetection

#: Smallest top face, in pixels of area, worth measuring.
MIN_FACE_AREA_PX = 100.0
#: Pixels at or above this level are the laser spot (or clipped), not the scene.
SATURATED_LEVEL = 250
#: The orientation mark's radius as a fraction of the face side (core.scene.Cube: side / 8).
MARK_RADIUS_FRACTION = 0.125

#: Farthest (px) a refined corner may lie from the threshold outline's polygon: beyond,
#: a side fit has gone astray and no corners are better than wrong ones.
_MAX_MOVE_PX = 4.0
#: A side's fit may turn its line by this little (cos of ~5 degrees), or it is not trusted.
_STEADY_COS = 0.996
#: Pixels each side of a side's line read when looking for a narrow side face beyond it.
_BAND_REACH = 5
#: Least slant (px per px) of the model's edges, so that the fit has a gradient everywhere.
_MIN_SLANT = 0.1
#: Farthest (px) the three-level fit may move a side from where the narrow strips put it.
_MAX_BAND_SHIFT_PX = 2.0
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

    quad, outline, problem = _rough_quadrilateral(img, threshold)
    if quad is None or outline is None:
        return _no_corners(problem)

    mark_px, mark_radius = _find_mark(img, quad, face_level, below_level)
    keep_out: list[tuple[Matrix, float]] = []
    if spot is not None and spot.found and np.all(np.isfinite(spot.spot_px)):
        spot_radius = max(5.0, math.sqrt(max(spot.area_px, 0.0) / math.pi) + 4.5)
        keep_out.append((np.asarray(spot.spot_px, dtype=np.float64), spot_radius))
    if np.all(np.isfinite(mark_px)):
        keep_out.append((mark_px, mark_radius + 1.5))

    # A side face that the threshold took for top face (too thin for the histogram to
    # show it) puts the outline on its outer edge: then the region is taken again with
    # a threshold just under the face's level.
    face_floor = face_level - _FACE_MARGIN * (face_level - below_level)
    refined = _refine(img, quad, outline, keep_out, face_floor)
    if refined == _DIM_SIDE:
        quad, outline, _ = _rough_quadrilateral(img, face_floor)
        refined = None if quad is None or outline is None else _refine(img, quad, outline, keep_out, -np.inf)
    if refined is None or refined == _DIM_SIDE:
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
    sample = img[::2, ::2]
    hist = cv2.calcHist([sample], [0], None, [256], [0, 256]).ravel()
    hist[SATURATED_LEVEL:] = 0.0
    kernel = np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2)
    smooth = np.convolve(hist, kernel / kernel.sum(), mode="same")
    mass = np.convolve(hist, np.ones(13), mode="same")  # pixels within +-6 levels
    min_mass = MIN_FACE_AREA_PX / 4.0  # a surface of the smallest face at least; a quarter of the pixels are sampled
    is_peak = (smooth >= np.roll(smooth, 1)) & (smooth > np.roll(smooth, -1)) & (mass >= min_mass)
    is_peak[:1] = False
    is_peak[-1:] = False
    peaks = np.flatnonzero(is_peak)[::-1]  # brightest first
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


def _rough_quadrilateral(img: np.ndarray, threshold: float) -> tuple[Matrix | None, Matrix | None, str]:
    """The largest bright region's quadrilateral (4, 2) in contour order and its outline
    (boundary pixels, (M, 2)), or None, None and why."""
    _, binary = cv2.threshold(img, threshold, 255, cv2.THRESH_BINARY)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None, None, "no bright top face above the threshold"
    areas = [cv2.contourArea(c) for c in contours]
    best = int(np.argmax(areas))
    contour = contours[best]
    if areas[best] < MIN_FACE_AREA_PX:
        return None, None, f"no bright top face: largest bright region is {areas[best]:.0f} px^2"
    height, width = img.shape
    x, y, w, h = cv2.boundingRect(contour)
    if x <= 0 or y <= 0 or x + w >= width or y + h >= height:
        return None, None, "object cut by the image border"
    hull = cv2.convexHull(contour)
    hull_area = cv2.contourArea(hull)
    if areas[best] < 0.85 * hull_area:
        return None, None, f"bright region is not convex (fills {areas[best] / hull_area:.0%} of its hull)"
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
    dark &= face_mask
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
    img: np.ndarray, quad: Matrix, outline: Matrix, keep_out: list[tuple[Matrix, float]], face_floor: float
) -> tuple[Matrix, float] | str | None:
    """Corners (4, 2) from the four fitted sides, and a fit quality in [0, 1], or None.

    Start: lines through the threshold outline's points along each side (a few tenths
    of a pixel off). Then partial-area strips around them, as narrow as the image's
    blur allows (narrow enough to stay on a side face a few pixels wide), a second time
    if a line moved much, and the three-level fit where a narrower side face runs along
    a side. None when a side cannot be fitted or a corner strays from the outline;
    ``_DIM_SIDE`` when just inside an outline side the image is darker than
    ``face_floor`` (the outline runs along a side face, not along the top face).
    """
    lines = _outline_lines(quad, outline)
    if lines is None:
        return None
    corners = np.array([intersect(lines[i - 1], lines[i]) for i in range(4)])
    if not np.all(np.isfinite(corners)) or np.abs(corners - quad).max() > _MAX_MOVE_PX:
        return None
    quality = 0.0
    # Wide strips across the sides, read once: for the blur here, for narrow side faces
    # at the end (their pixels do not move with the lines' last hundredths).
    wide = sample_strips(
        img,
        [(normal, offset, corners[i], corners[(i + 1) % 4]) for i, (normal, offset) in enumerate(lines)],
        _BAND_REACH,
        keep_out,
        _BAND_REACH + 2.0,
    )
    if wide is not None and _dim_inside(wide, len(lines)) < face_floor:
        return _DIM_SIDE
    blur = _edge_blur(wide, lines) if wide is not None else 0.0
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
        lost = [i for i, fit in enumerate(fits) if fit is None]
        if lost:
            # The outline can be a pixel off an edge along a row or a column, beyond
            # these strips' reach: +-2 px strips for those sides.
            wider = edge_points_many(img, [segments[i] for i in lost], 1.5, 1, keep_out, 4.5)
            for i, fit in zip(lost, fit_lines(wider, [segments[i][0] for i in lost], min_points=6, rounds=2), strict=True):
                fits[i] = fit
        new_lines, qualities = [], []
        for (normal, offset, _, _), fit in zip(segments, fits, strict=True):
            if fit is None or float(fit[0] @ normal) < _STEADY_COS:
                # Too few clean strips, or the line turned (a narrow side face right
                # along the side): keep the line; the three-level fit may correct it.
                new_lines.append((normal, offset))
                qualities.append(0.0)
                continue
            line_normal, line_offset, inliers, rms = fit
            new_lines.append((line_normal, line_offset))
            support = min(inliers.sum() / 10.0, 1.0) * (0.5 + 0.5 * inliers.mean())
            qualities.append(support / (1.0 + (rms / 0.2) ** 2))
        if sum(quality > 0.0 for quality in qualities) < 2:
            return None
        quality = float(min(qualities))
        moved = max(abs(float(new[0] @ corners[i]) - new[1]) for i, new in enumerate(new_lines))
        lines = new_lines
        corners = np.array([intersect(lines[i - 1], lines[i]) for i in range(4)])
        if not np.all(np.isfinite(corners)) or np.abs(corners - quad).max() > _MAX_MOVE_PX:
            return None
        if attempt == 0 and moved < 0.5:
            break  # the strips were centred well enough
    # A side face narrower than the strips would pull a side outwards.
    if wide is not None:
        for i, banded in enumerate(_banded_lines(wide, lines, blur)):
            if banded is not None:
                lines[i] = banded
    corners = np.array([intersect(lines[i - 1], lines[i]) for i in range(4)])
    if not np.all(np.isfinite(corners)) or np.abs(corners - quad).max() > _MAX_MOVE_PX:
        return None
    return corners, quality


def _dim_inside(strips: Strips, count: int) -> float:
    """The lowest, over the sides, of the median grey level 2 px inside the face."""
    values = np.where(strips.bright_high[:, None], strips.values, strips.values[:, ::-1])
    inside = values[:, _BAND_REACH + 2]
    bounds = np.searchsorted(strips.segment, np.arange(count + 1))
    levels = [float(np.median(inside[bounds[i] : bounds[i + 1]])) for i in range(count) if bounds[i + 1] > bounds[i]]
    return min(levels) if levels else np.inf


def _edge_blur(strips: Strips, lines: list[tuple[Matrix, float]]) -> float:
    """The optical blur of the image (sigma of a Gaussian, px), from the top face's sides.

    Across a straight edge the grey levels' differences spread with variance 1/6 (the
    pixel's box, twice: the edge's coverage and the differencing) plus slant^2 / 12
    plus sigma^2. The moments are summed over each side's strips before they are
    divided (the noise then averages out), within 3.5 px of the line. The second
    cleanest side decides (a side face along a side widens its profile); estimates
    under 0.45 px are within the noise and read as no blur.
    """
    values = strips.values[:, 1:-1]  # 4 px each side
    sign = np.where(strips.bright_high, 1.0, -1.0)
    normals = np.array([normal for normal, _ in lines])
    offsets = np.array([offset for _, offset in lines])
    steep_s = np.abs(normals[:, 0]) > np.abs(normals[:, 1])
    n_across = np.where(steep_s, normals[:, 0], normals[:, 1])[strips.segment]
    n_along = np.where(steep_s, normals[:, 1], normals[:, 0])[strips.segment]
    line_at = (offsets[strips.segment] - n_along * strips.along) / n_across  # across coordinate of the line
    # Differences between neighbours, at the midpoints, in the bright-positive frame.
    steps = sign[:, None] * np.diff(values, axis=1)
    position = sign[:, None] * (strips.base[:, None] + np.arange(-4, 4)[None, :] + 0.5 - line_at[:, None])
    contrast = sign * (values[:, -1] - values[:, 0])
    usable = contrast > 20.0
    bounds = np.searchsorted(strips.segment, np.arange(len(lines) + 1))
    slant = n_along / n_across
    per_side = []
    for i in range(len(lines)):
        rows = slice(bounds[i], bounds[i + 1])
        ok = usable[rows]
        if ok.sum() < 6:
            continue
        d = steps[rows][ok] / contrast[rows][ok, None]
        x = position[rows][ok]
        m0, m1, m2 = d.sum(), (d * x).sum(), (d * x * x).sum()
        if m0 <= 0.0:
            continue
        per_side.append(m2 / m0 - (m1 / m0) ** 2 - 1.0 / 6.0 - float(slant[rows][0]) ** 2 / 12.0)
    if not per_side:
        return 0.0
    variance = sorted(per_side)[min(1, len(per_side) - 1)]
    sigma = math.sqrt(variance) if variance > 0.0 else 0.0
    return sigma if sigma > 0.45 else 0.0


def _outline_lines(quad: Matrix, outline: Matrix) -> list[tuple[Matrix, float]] | None:
    """A line per side (inward unit normal, offset) through the outline's points along it.

    The outline runs through the centres of the region's boundary pixels, on average
    half a pixel inside the threshold's crossing: the lines are moved out by that much.
    """
    ends = np.roll(quad, -1, axis=0)
    lengths = np.linalg.norm(ends - quad, axis=1)
    directions = (ends - quad) / lengths[:, None]
    normals = np.column_stack([-directions[:, 1], directions[:, 0]])
    normals *= np.where(((quad.mean(axis=0) - quad) * normals).sum(axis=1) < 0.0, -1.0, 1.0)[:, None]
    relative = outline[:, None, :] - quad[None, :, :]  # (M, 4, 2)
    along = (relative * directions[None]).sum(axis=2)
    across = (relative * normals[None]).sum(axis=2)
    margin = 2.0 + 0.1 * lengths
    near = (np.abs(across) < 2.0) & (along > margin) & (along < lengths - margin)
    point_sets = [outline[near[:, i]] for i in range(4)]
    lines = []
    for fit, hint in zip(fit_lines(point_sets, list(normals), min_points=4, rounds=1), normals, strict=True):
        if fit is None:
            return None
        lines.append((fit[0], fit[1] - 0.5))
    return lines


def _banded_lines(strips: Strips, lines: list[tuple[Matrix, float]], blur: float = 0.0) -> list[tuple[Matrix, float] | None]:
    """Each side's line when a side face narrower than ~4 px runs along it, else None.

    Such a band (grey level between the face's and the table's) sits inside the narrow
    strips and biases the partial-area position outwards by its width times its
    relative level. Here the strips are wider (the table beyond the band in view) and
    the three-level profile - face, band, table - is fitted as box-filtered steps along
    the whole side: the face edge (offset and slope), the band's width (linear along
    the side) and its level, with the image's ``blur``. Only done where the band shows:
    pixels clearly above the table level beyond the face edge as seen from the bright
    side. A band under ~1 px (more under blur) cannot be told from the edge itself and
    still biases the side by up to its width times its relative level.
    """
    count = len(lines)
    result: list[tuple[Matrix, float] | None] = [None] * count
    seg = strips.segment
    bounds = np.searchsorted(seg, np.arange(count + 1))
    # Every side at once: bright end last, levels scaled 0 (table) .. 1 (face).
    values = np.where(strips.bright_high[:, None], strips.values, strips.values[:, ::-1])
    sign = np.where(strips.bright_high, 1.0, -1.0)
    present = np.flatnonzero(bounds[1:] > bounds[:-1])
    sums = np.add.reduceat(values[:, [0, -1]], bounds[present], axis=0)
    levels = np.full((count, 2), np.nan)
    levels[present] = sums / (bounds[present + 1] - bounds[present])[:, None]
    dark, bright = levels[seg, 0], levels[seg, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        scaled = (values[:, 1:-1] - dark[:, None]) / (bright - dark)[:, None]  # pixels -4 .. 4 across
    across = (sign * strips.base)[:, None] + np.arange(-_BAND_REACH + 1, _BAND_REACH)[None, :]  # bright-positive
    normals = np.array([normal for normal, _ in lines])
    steep_s = np.abs(normals[:, 0]) > np.abs(normals[:, 1])
    n_across = np.where(steep_s, normals[:, 0], normals[:, 1])
    n_along = np.where(steep_s, normals[:, 1], normals[:, 0])
    slope = -sign * n_along[seg] / n_across[seg]
    # The face edge seen from the bright side: just before the first pixel (from the
    # dark end) that is nearly as bright as the face. A band shows as pixels well above
    # the table level further out than that.
    rows = np.arange(len(scaled))
    first_bright = np.argmax(scaled > 0.9, axis=1)
    has_bright = (scaled[rows, first_bright] > 0.9) & (values[:, -1] - values[:, 0] > 20.0)
    edge = across[rows, first_bright] - 0.5 - 1.3 * blur
    in_band = (scaled > 0.15) & (across < (edge - 1.0 - 0.5 * np.abs(slope) - 2.5 * blur)[:, None])
    band_pixels = in_band.sum(axis=1)
    for index in range(count):
        part = slice(bounds[index], bounds[index + 1])
        good = has_bright[part]
        if good.sum() < 8 or not bright[bounds[index]] - dark[bounds[index]] > 20.0:
            continue
        if np.median(band_pixels[part][good]) < 1.0:
            continue  # no band: the narrow strips were right
        result[index] = _banded_fit(
            lines[index],
            scaled[part][good],
            across[part][good],
            strips.along[part][good].astype(np.float64),
            edge[part][good],
            in_band[part][good],
            float(sign[bounds[index]]),
            bool(steep_s[index]),
            blur,
        )
    return result


def _banded_fit(
    line: tuple[Matrix, float],
    scaled: Matrix,
    across: Matrix,
    along: Matrix,
    edge: Matrix,
    in_band: np.ndarray,
    sign: float,
    steep: bool,
    blur: float,
) -> tuple[Matrix, float] | None:
    """Levenberg-Marquardt fit of the face-band-table profile on one side's strips (see
    ``_banded_lines``)."""
    normal, offset = line
    n_across, n_along = (normal[0], normal[1]) if steep else (normal[1], normal[0])
    t = along - along.mean()
    slope = -sign * n_along / n_across
    c0_start = float(np.median(edge - slope * t))
    band_pixels = in_band.sum(axis=1)
    level_start = float(np.clip(np.median(scaled[in_band]), 0.1, 0.9))
    params = np.array([c0_start, slope, float(np.median(band_pixels)), 0.0, level_start])
    tt = t[:, None]
    flat = scaled.ravel()
    reach_t = float(np.abs(t).max()) + 1.0
    lower = np.array([c0_start - 2.0, slope - 2.0 / reach_t, 0.0, -2.0 / reach_t, 0.02])
    upper = np.array([c0_start + 2.0, slope + 2.0 / reach_t, 5.0, 2.0 / reach_t, 0.98])

    def model(p: Matrix) -> tuple[Matrix, Matrix]:
        c0, m, w0, w1, level = p
        e1 = (c0 + m * t)[:, None]
        # A little slant keeps the model smooth: with an edge on a
        # pixel boundary, a sharp step would give no gradient at all.
        cover, slope_d = _coverage(across[None], np.stack([e1, e1 - (w0 + w1 * t)[:, None]]), max(abs(m), _MIN_SLANT), blur)
        residual = flat - ((1.0 - level) * cover[0] + level * cover[1]).ravel()
        d_c0 = (1.0 - level) * slope_d[0] + level * slope_d[1]
        d_w0 = -level * slope_d[1]
        jac = np.stack([d_c0, d_c0 * tt, d_w0, d_w0 * tt, cover[1] - cover[0]], axis=-1).reshape(-1, 5)
        return residual, jac

    # The profile's cost has poor minima in (width, level): descend from the better of
    # the first guess and the best of a grid of edges and widths.
    grid_c0, grid_w = np.meshgrid(c0_start + np.array([-0.4, 0.2]), np.array([0.75, 1.5, 2.5, 3.5]))
    grid = np.column_stack([grid_c0.ravel(), grid_w.ravel()])
    e1 = grid[:, 0, None] + slope * t[None, :]  # (G, N)
    slant = max(abs(slope), _MIN_SLANT)
    cover1 = _coverage(across[None], e1[:, :, None], slant, blur)[0]
    cover2 = _coverage(across[None], (e1 - grid[:, 1, None])[:, :, None], slant, blur)[0]
    grid_cost = ((scaled[None] - (1.0 - params[4]) * cover1 - params[4] * cover2) ** 2).sum(axis=(1, 2))
    best = int(np.argmin(grid_cost))
    start_residual = model(params)[0]
    if grid_cost[best] < float(start_residual @ start_residual):
        params[0], params[2] = grid[best]
    params, _ = _descend(model, params, lower, upper, reach_t)
    c0, m, w0, w1, level = params
    widths = w0 + w1 * t
    if not (np.all(np.isfinite(params)) and 0.05 < level < 0.95 and widths.min() > -0.2 and widths.max() < 5.0):
        return None
    narrow_at = sign * (offset - n_along * along) / n_across  # the narrow strips' edge, bright-positive
    if np.abs(c0 + m * t - narrow_at).max() > _MAX_BAND_SHIFT_PX:
        return None  # more than a narrow side face can explain: the fit found something else
    # Back to the image: the edge's across coordinate is sign * (c0 + m (along - mean)),
    # so across - sign m along = sign (c0 - m mean).
    mean_along = float(along.mean())
    new_normal = np.array([1.0, -sign * m]) if steep else np.array([-sign * m, 1.0])
    new_offset = sign * (c0 - m * mean_along)
    scale = float(np.hypot(*new_normal))
    new_normal, new_offset = new_normal / scale, new_offset / scale
    if new_normal @ normal < 0.0:
        new_normal, new_offset = -new_normal, -new_offset
    return new_normal, float(new_offset)


def _descend(model, params: Matrix, lower: Matrix, upper: Matrix, reach_t: float) -> tuple[Matrix, float]:
    """Levenberg-Marquardt on ``model`` (params -> residual, Jacobian) within the bounds."""
    residual, jac = model(params)
    cost = float(residual @ residual)
    damping = 1e-3
    for _ in range(4):
        normal_eq = jac.T @ jac
        step = np.linalg.solve(normal_eq + damping * np.diag(np.diag(normal_eq) + 1e-9), jac.T @ residual)
        trial = np.clip(params + step, lower, upper)
        residual_t, jac_t = model(trial)
        cost_t = float(residual_t @ residual_t)
        if cost_t < cost:
            moved = abs(trial[0] - params[0]) + abs(trial[1] - params[1]) * reach_t
            params, residual, jac, cost = trial, residual_t, jac_t, cost_t
            damping = max(damping / 4.0, 1e-7)
            if moved < 2e-3:  # the edge has settled (the band may not)
                break
        else:
            damping *= 8.0
    return params, cost


def _coverage(across: Matrix, edge: Matrix, slant: float, blur: float = 0.0) -> tuple[Matrix, Matrix]:
    """Share of each pixel beyond an edge crossing it with ``slant`` px per px along the
    strip, seen through a Gaussian ``blur``, and its derivative with respect to the
    edge's position. Without blur exact; with it the pixel, slant and blur kernels
    together are taken as one Gaussian (of their summed variances)."""
    c = across + 0.5 - edge
    if blur >= 0.25:
        spread = math.sqrt((1.0 + slant * slant) / 12.0 + blur * blur)
        z = (c - 0.5) / spread
        return 0.5 * (1.0 + _erf(z / math.sqrt(2.0))), -np.exp(-0.5 * z * z) / (spread * math.sqrt(2.0 * math.pi))
    hi, lo = c + 0.5 * slant, c - 0.5 * slant

    def antiderivative(z: Matrix) -> Matrix:
        return np.where(z < 0.0, 0.0, np.where(z < 1.0, 0.5 * z * z, z - 0.5))

    cover = (antiderivative(hi) - antiderivative(lo)) / slant
    return cover, -(np.clip(hi, 0.0, 1.0) - np.clip(lo, 0.0, 1.0)) / slant


def _erf(x: Matrix) -> Matrix:
    """The error function (Abramowitz and Stegun 7.1.26, error below 1.5e-7)."""
    a = np.abs(x)
    t = 1.0 / (1.0 + 0.3275911 * a)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    return np.sign(x) * (1.0 - poly * np.exp(-a * a))


# ---------------------------------------------------------------------------------------
# Order
# ---------------------------------------------------------------------------------------


def _signed_area2(points: Matrix) -> float:
    u, v = points[:, 0], points[:, 1]
    return float((u * np.roll(v, -1) - np.roll(u, -1) * v).sum())


def _order(corners: Matrix, mark_px: Matrix, previous_px: np.ndarray | None, winding: int) -> tuple[Matrix | None, str, bool]:
    """Corners in the taught order, or None and why; True when the mark fixed the order."""
    if _signed_area2(corners) * winding < 0.0:
        corners = corners[::-1].copy()
    if np.all(np.isfinite(mark_px)):
        distance = np.linalg.norm(corners - mark_px, axis=1)
        nearest = int(np.argmin(distance))
        others = np.delete(distance, nearest)
        if distance[nearest] < 0.75 * others.min():
            return np.roll(corners, -nearest, axis=0), "", True
    previous = _valid_previous(previous_px)
    if previous is None:
        return None, "cannot tell corner 0: orientation mark not seen and no previous corners", False
    seen = np.all(np.isfinite(previous), axis=1)
    costs = [
        float((np.linalg.norm(np.roll(corners, -shift, axis=0)[seen] - previous[seen], axis=1) ** 2).sum()) for shift in range(4)
    ]
    shift = int(np.argmin(costs))
    return np.roll(corners, -shift, axis=0), "", False


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
