"""The laser spot: a fixed-level threshold, then a sub-pixel centre (thesis section 4.3).

The thesis finds the spot as the pixels brighter than a fixed level. Here that level
only finds and counts the blobs (exactly one, not too large, is a spot); the centre
comes from the grey levels around the blob. The spot adds light to whatever it falls
on, and the sensor clips:

    I(x) = min(255, B(x) + A exp(-|x - c|^2 / (2 s^2)))

where B is the scene without the spot. Around the blob, a hole (where the spot adds
light) and a ring outside it (where it adds none) are read:

- the ring is a plane (the table, the inside of the top face): the clipped spot stays
  symmetric about c, so c is the centroid of I - B in a small tapered disc re-centred
  on it until it settles;
- the ring shows edges (the spot on a side, a corner, near the mark): B is rebuilt in
  the hole from the straight edges crossing the ring (a line arrangement, each cell at
  the level the ring shows next to the hole), which keeps a corner sharp where a smooth
  fill would round it. Only hole pixels wholly inside one cell are used, and c comes
  from a robust fit of the model above, clipped pixels as one-sided constraints, so
  the clipped core - larger on a bright surface than on a dark one - does not pull c
  towards the bright side.

Known limit: a curved edge under the spot (the orientation mark's rim) is not modelled;
there the centre can be off by up to about a pixel.

Pixel convention (OpenCV): the pixel at row r, column c has its centre at (u, v) = (c, r).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.vision.edges import Segment, edge_points_many, fit_lines, frozen_array, image_problem
from vservo.core.perception.vision.least_squares import levenberg_marquardt

#: Grey level from which a pixel counts as clipped by the sensor.
CLIPPED_LEVEL = 254
#: Grey levels where the spot fit's Cauchy loss turns from square to logarithmic.
_CAUCHY_SCALE = 8.0
#: How far an edge is followed beyond the gradient samples that found it (px).
_EXTEND_PX = 3.0
#: Grey levels off the ring's plane that tell an edge near the spot (noise is a few levels).
_STRUCTURE_LEVEL = 12.0
#: Margin (px) beyond a pixel's half extent for an edge to leave the pixel pure.
_MIXED_MARGIN_PX = 0.25
#: How far (px) a fitted edge may move from its rough line under the spot.
_STEADY_PX = 1.0
#: Width (px) of the ring around the hole that shows the spot's surroundings.
_RING_PX = 8.0
#: Width (px) of the thin ring that tells uniform surroundings from edges near the spot.
_NEAR_RING_PX = 3.0
#: RMS turn (degrees) of the gradient along a rough edge beyond which it is a curve.
_STRAIGHT_SPREAD_DEG = 8.0


@dataclass(frozen=True)
class SpotDetection:
    """The laser spot seen in one image.

    spot_px: (2,) sub-pixel centre (u, v), NaN when not found.
    area_px: pixels at or above the threshold in the spot's blob (in the rejected blob
      when it is too large; 0 when there is none).
    confidence: in [0, 1], 0 when not found.
    reason: "" on success, otherwise why no spot is given.
    """

    found: bool
    spot_px: Matrix
    area_px: float
    confidence: float
    reason: str


def _no_spot(reason: str, area_px: float = 0.0) -> SpotDetection:
    return SpotDetection(False, frozen_array([np.nan, np.nan], (2,)), float(area_px), 0.0, reason)


def detect_laser_spot(image: np.ndarray, threshold: float = 250, min_area_px: int = 1, max_area_px: int = 150) -> SpotDetection:
    """Find the one laser spot in ``image`` (uint8, single channel); never raises.

    Pixels >= ``threshold`` form blobs (8-connected; blobs less than 3 px apart are one
    blob, a spot near the threshold breaks up in noise); blobs smaller than
    ``min_area_px`` are ignored. Exactly one blob of at most ``max_area_px`` pixels is a
    spot; none, several or a larger one (a saturated frame, a reflection) is not.
    """
    try:
        return _detect(image, threshold, min_area_px, max_area_px)
    except Exception as error:  # noqa: BLE001 - a detector reports, it never raises
        return _no_spot(f"spot detection failed: {type(error).__name__}: {error}")


def _detect(image: np.ndarray, threshold: float, min_area_px: int, max_area_px: int) -> SpotDetection:
    problem = image_problem(image)
    if problem:
        return _no_spot(problem)
    img = np.ascontiguousarray(image)
    # The bright pixels' bounding rectangle from row and column maxima: no frame-sized
    # mask (touching a fresh frame-sized array costs more than the test itself).
    row_max = img.max(axis=1)
    brightest = int(row_max.max())
    if brightest < threshold:
        return _no_spot(f"no spot: no pixel at or above {threshold:g} (brightest {brightest})")
    rows = np.flatnonzero(row_max >= threshold)
    y0, y1 = int(rows[0]), int(rows[-1]) + 1
    columns = np.flatnonzero(img[y0:y1].max(axis=0) >= threshold)
    x0, x1 = int(columns[0]), int(columns[-1]) + 1
    roi = (img[y0:y1, x0:x1] >= threshold).view(np.uint8)
    # Group blobs closer than 3 px: label the dilated mask, count the undilated pixels.
    grown = cv2.dilate(roi, np.ones((5, 5), np.uint8))
    count, labels = cv2.connectedComponents(grown, connectivity=8)
    on = roi > 0
    areas = np.bincount(labels[on], minlength=count)[1:]
    blobs = np.flatnonzero(areas >= max(min_area_px, 1)) + 1
    if blobs.size == 0:
        return _no_spot(f"no spot: no blob of at least {min_area_px} px at or above {threshold:g}")
    if blobs.size > 1:
        sizes = ", ".join(str(int(areas[b - 1])) for b in blobs[:6])
        more = ", ..." if blobs.size > 6 else ""
        return _no_spot(f"{blobs.size} bright blobs at or above {threshold:g} (areas {sizes}{more} px): not one spot")
    area = int(areas[blobs[0] - 1])
    if area > max_area_px:
        return _no_spot(f"bright blob too large: {area} px above max_area_px={max_area_px} (saturated frame or reflection)", area)
    rows, cols = np.nonzero(on & (labels == blobs[0]))
    blob_u, blob_v = cols + float(x0), rows + float(y0)
    centre, confidence = _subpixel_centre(img, blob_u, blob_v)
    return SpotDetection(True, frozen_array(centre, (2,)), float(area), confidence, "")


# ---------------------------------------------------------------------------------------
# Sub-pixel centre
# ---------------------------------------------------------------------------------------


def _subpixel_centre(img: np.ndarray, blob_u: np.ndarray, blob_v: np.ndarray) -> tuple[Matrix, float]:
    """Centre of the spot whose bright pixels are (blob_u, blob_v), and a confidence.

    1 on a uniform background; on edges 0.8 scaled down by the fit's RMS residual; 0.3
    when the fit failed and the centroid of the clipped core is all there is.
    """
    u0, v0 = float(blob_u.mean()), float(blob_v.mean())
    r_blob = float(np.sqrt(((blob_u - u0) ** 2 + (blob_v - v0) ** 2).max())) + 0.5
    r_hole = max(4.0, r_blob + 3.0)  # the spot adds less than ~2 grey levels beyond
    r_ring = r_hole + _RING_PX
    height, width = img.shape
    c0, c1 = max(int(u0 - r_ring) - 2, 0), min(int(u0 + r_ring) + 3, width)
    r0, r1 = max(int(v0 - r_ring) - 2, 0), min(int(v0 + r_ring) + 3, height)
    win = img[r0:r1, c0:c1].astype(np.float64)
    # The window's pixel centres (u along the rows, v down the columns), as full grids
    # for the masks' selections.
    u_axis, v_axis = np.arange(c0, c1, dtype=np.float64), np.arange(r0, r1, dtype=np.float64)
    uu, vv = np.empty(win.shape), np.empty(win.shape)
    uu[:], vv[:] = u_axis, v_axis[:, None]
    radius = np.sqrt(((u_axis - u0) ** 2)[None, :] + ((v_axis - v0) ** 2)[:, None])
    hole = radius < r_hole
    # Edges further out than just around the hole do not reach the spot: only a thin
    # ring decides whether the surroundings are uniform.
    near_ring = (radius >= r_hole) & (radius <= r_hole + _NEAR_RING_PX)

    background, structured = _plane_background(win, uu, vv, near_ring)
    if not structured:
        # Uniform surroundings: the clipped spot stays symmetric, its centroid is its centre.
        return _recentred_centroid(win - background, u_axis, v_axis, np.array([u0, v0]), r_blob), 1.0
    edged = _edge_background(img, win, uu, vv, np.array([u0, v0]), radius, r_hole, r_ring)
    use = hole
    if edged is not None:
        background, pure = edged
        use = hole & pure
    blob_centre = np.array([u0, v0])
    centroid = _centroid(win - background, uu, vv, use, blob_centre)
    if np.hypot(*(centroid - blob_centre)) > 1.0:  # the rebuilt background is off somewhere
        centroid = blob_centre
    fitted = _fit_spot(win[use], background[use], uu[use], vv[use], centroid, blob_centre)
    if fitted is None:
        return centroid, 0.3
    centre, rms = fitted
    return centre, 0.8 * float(np.clip(1.0 - (rms - 3.0) / 30.0, 0.3, 1.0))


def _centroid(excess: Matrix, uu: Matrix, vv: Matrix, hole: np.ndarray, fallback: Matrix) -> Matrix:
    """Centroid of the spot's light (I - B) over the hole; signed weights keep noise unbiased."""
    weights = excess[hole]
    total = weights.sum()
    if total <= 0.0:
        return fallback
    return np.array([(weights * uu[hole]).sum() / total, (weights * vv[hole]).sum() / total])


def _recentred_centroid(excess: Matrix, u_axis: Matrix, v_axis: Matrix, start: Matrix, r_blob: float) -> Matrix:
    """Centroid of the spot's light in a tapered disc re-centred on it until it settles.

    ``excess`` is the light over the window whose pixel centres are ``u_axis`` along a
    row and ``v_axis`` down a column. A disc centred on the estimate is symmetric about
    the true centre once it has settled, so the cut tail does not bias it; a small disc
    keeps the noise low; signed weights keep the noise unbiased.
    """
    radius = max(3.5, r_blob + 1.5)
    start_u, start_v = start.tolist()
    centre_u, centre_v = start_u, start_v
    for _ in range(6):
        distance = np.sqrt(((u_axis - centre_u) ** 2)[None, :] + ((v_axis - centre_v) ** 2)[:, None])
        weights = (radius + 0.5 - distance).clip(0.0, 1.0)
        weights *= excess
        total = float(weights.sum())
        if total <= 0.0:
            return start
        new_u, new_v = float(weights.sum(axis=0) @ u_axis) / total, float(weights.sum(axis=1) @ v_axis) / total
        if math.hypot(new_u - start_u, new_v - start_v) > radius:
            return start
        moved = max(abs(new_u - centre_u), abs(new_v - centre_v))
        centre_u, centre_v = new_u, new_v
        if moved < 1e-3:
            break
    return np.array([centre_u, centre_v])


def _plane_background(win: Matrix, uu: Matrix, vv: Matrix, ring: np.ndarray) -> tuple[Matrix, bool]:
    """A plane fitted to the ring, and whether the ring shows more than a plane (an edge)."""
    values, u, v = win[ring], uu[ring], vv[ring]
    u_mean, v_mean = float(u.sum()) / u.size, float(v.sum()) / v.size
    design = np.empty((values.size, 3))
    design[:, 0] = 1.0
    np.subtract(u, u_mean, out=design[:, 1])
    np.subtract(v, v_mean, out=design[:, 2])
    coef = np.linalg.solve(design.T @ design, design.T @ values)
    residual = values - design @ coef
    structured = np.count_nonzero(np.abs(residual) > _STRUCTURE_LEVEL) > 0.05 * values.size
    level, slope_u, slope_v = coef.tolist()
    # (the grids' first row and column are the window's u and v axes)
    plane = (level + slope_u * (uu[0] - u_mean))[None, :] + (slope_v * (vv[:, 0] - v_mean))[:, None]
    return plane, bool(structured)


@dataclass
class _HoleEdge:
    """A straight edge across the hole: its line (normal . p = offset, refitted on the
    strips), the strip it is sampled along (start .. stop), where along the line it shows
    (t_lo .. t_hi) and the line the gradients gave first."""

    normal: Matrix
    offset: float
    start: Matrix
    stop: Matrix
    t_lo: float
    t_hi: float
    rough_normal: Matrix
    rough_offset: float

    @property
    def strip(self) -> Segment:
        return (self.normal, self.offset, self.start, self.stop)


def _edge_background(
    img: np.ndarray, win: Matrix, uu: Matrix, vv: Matrix, centre: Matrix, radius: Matrix, r_hole: float, r_ring: float
) -> tuple[Matrix, np.ndarray] | None:
    """The spot-free scene inside the hole, from the straight edges that cross the ring,
    and which hole pixels it is sure of.

    Edges are found from the grey-level gradient in the ring and located by the
    partial-area effect, as lines; the lines cut the window into cells, each at the
    median level of the ring pixels it holds. A hole pixel wholly inside one cell has
    that cell's level; a pixel an edge crosses is mixed and left out. A cell the ring
    does not show (cut off by the extension of an edge that ends under the spot) takes
    the level across that extension. A corner under the spot stays sharp.
    """
    win32 = win.astype(np.float32)
    gu = cv2.Scharr(win32, cv2.CV_32F, 1, 0).astype(np.float64) / 32.0
    gv = cv2.Scharr(win32, cv2.CV_32F, 0, 1).astype(np.float64) / 32.0
    inner = np.zeros(win.shape, bool)
    inner[1:-1, 1:-1] = True
    usable = inner & (radius >= r_hole + 1.5) & (radius <= r_ring)
    # No straight edge at all (only the mark's curved rim nearby) leaves one cell.
    rough = _find_lines(uu[usable], vv[usable], gu[usable], gv[usable], centre, r_hole + 1.0)
    segments: list[_HoleEdge] = []
    far: list[tuple[Matrix, float]] = []
    for normal, offset, t_lo, t_hi in rough:
        if abs(float(normal @ centre) - offset) > r_hole + 1.0:
            # An edge that does not cross the hole (the mark's rim) needs no model there,
            # but what lies beyond it is not the hole's background either.
            far.append((normal, offset))
            continue
        direction = np.array([-normal[1], normal[0]])
        t_centre = float(centre @ direction)
        # A half-line (an edge ending at a junction under the spot) is real from the
        # junction outwards only; a line crossing the ring, both ways.
        if t_lo > t_centre:
            t_lo = t_centre - 1.0
        elif t_hi < t_centre:
            t_hi = t_centre + 1.0
        foot = offset * normal
        start = foot + (t_lo - _EXTEND_PX) * direction
        stop = foot + (t_hi + _EXTEND_PX) * direction
        segments.append(_HoleEdge(normal, offset, start, stop, t_lo, t_hi, normal, offset))
    # Narrow strips (they stay clear of the mark and of a narrow side face), twice: the
    # second pass centred on the first fit.
    for half_width in (1.5, 1.0):
        found = edge_points_many(img, [seg.strip for seg in segments], half_width, 1, [(centre, r_hole + 0.5)])
        for seg, fit in zip(segments, fit_lines(found, [seg.normal for seg in segments], min_points=3), strict=True):
            if fit is not None:
                seg.normal, seg.offset = fit[0], fit[1]
    lines, extents = [], []
    for seg in segments:
        normal, offset = seg.normal, seg.offset
        moved = abs(float(normal @ centre) - offset - (float(seg.rough_normal @ centre) - seg.rough_offset))
        if moved > _STEADY_PX or float(normal @ seg.rough_normal) < math.cos(math.radians(10.0)):
            # The strips strayed (a narrow wedge of side face at the junction): keep the
            # line the gradients gave.
            normal, offset = seg.rough_normal, seg.rough_offset
        if abs(float(normal @ centre) - offset) <= r_hole + 1.0:
            lines.append((normal, offset))
            extents.append((seg.t_lo, seg.t_hi))
        else:
            far.append((normal, offset))
    # No edge under the spot (an edge across the ring only): one cell, on the spot's side.
    normals = np.array([n for n, _ in lines]).reshape(-1, 2)
    offsets = np.array([d for _, d in lines])
    bits = 1 << np.arange(len(lines))

    def cell_codes(u: Matrix, v: Matrix) -> np.ndarray:
        return ((np.stack([u, v], axis=-1) @ normals.T - offsets > 0.0) * bits).sum(axis=-1)

    ring = (radius >= r_hole) & (radius <= r_ring)
    ru, rv, rvalues = uu[ring], vv[ring], win[ring]
    clear = (np.abs(np.stack([ru, rv], axis=-1) @ normals.T - offsets) > 1.0).all(axis=1)
    for normal, offset in far:
        side = normal[0] * ru + normal[1] * rv - offset
        clear &= (side * (float(normal @ centre) - offset) > 0.0) & (np.abs(side) > 1.0)
    if clear.sum() < 8:
        return None
    codes = cell_codes(ru[clear], rv[clear])
    closeness = np.argsort(radius[ring][clear], kind="stable")
    codes_by_radius, values_by_radius = codes[closeness], rvalues[clear][closeness]
    levels = np.full(1 << len(lines), np.nan)
    for code in np.unique(codes):
        # The pixels of the cell nearest the hole: a surface further out (the mark) can
        # take much of a cell's share of the ring without changing its level.
        values = values_by_radius[codes_by_radius == code]
        levels[code] = np.median(values[: max(5, math.ceil(0.3 * values.size))])

    hole = radius < r_hole + 1.0
    hu, hv = uu[hole], vv[hole]
    hole_codes = cell_codes(hu, hv)
    hole_levels = levels[hole_codes]
    unseen = np.isnan(hole_levels)
    if unseen.any():
        # Cross the line least real where the pixel is: the one whose edge samples lie
        # farthest from the pixel's foot on it (the extension of a half-line).
        t = np.stack([hu[unseen], hv[unseen]], axis=-1) @ np.column_stack([-normals[:, 1], normals[:, 0]]).T
        lo, hi = np.array(extents).T
        outside = np.maximum(np.maximum(lo - t, t - hi), 0.0)
        order = np.argsort(-outside, axis=1)
        fill = np.full(int(unseen.sum()), np.nan)
        for rank in range(len(lines)):
            flipped = hole_codes[unseen] ^ bits[order[:, rank]]
            fill = np.where(np.isnan(fill), levels[flipped], fill)
        hole_levels[unseen] = fill
    background = win.copy()
    background[hole] = hole_levels
    reach = 0.5 * np.abs(normals).sum(axis=1) + _MIXED_MARGIN_PX
    pure = np.ones(win.shape, bool)
    pure[hole] = (np.abs(np.stack([hu, hv], axis=-1) @ normals.T - offsets) > reach).all(axis=1) & np.isfinite(hole_levels)
    return background, pure


def _find_lines(
    u: Matrix, v: Matrix, gu: Matrix, gv: Matrix, centre: Matrix, reach: float, max_lines: int = 6
) -> list[tuple[Matrix, float, float, float]]:
    """Rough straight edges among gradient samples: (unit normal, offset, t_lo, t_hi).

    The line is normal . x = offset; t_lo .. t_hi is the extent of its samples along the
    direction (-normal[1], normal[0]).

    Greedy: seed at the strongest remaining gradient, gather the samples near its line
    whose gradient points along its normal (dark to bright), fit by weighted total
    least squares, gather again around the fit, refit, and remove what was used. Seeds
    whose edge would pass within ``reach`` of ``centre`` (the edges under the spot) go
    first, so that a curved rim nearby (the mark), which breaks into several short
    lines, cannot use up the lines.
    """
    magnitude = np.hypot(gu, gv)
    points = np.column_stack([u, v])
    free = magnitude > 12.0
    with np.errstate(invalid="ignore", divide="ignore"):
        tangent_miss = np.abs(((u - centre[0]) * gu + (v - centre[1]) * gv) / magnitude)
    priority = np.where(tangent_miss <= reach, magnitude + 1e4, magnitude)
    lines: list[tuple[Matrix, float, float, float]] = []
    while free.sum() >= 4 and len(lines) < max_lines:
        seed = int(np.argmax(np.where(free, priority, -1.0)))
        normal = np.array([gu[seed], gv[seed]]) / magnitude[seed]
        offset = float(points[seed] @ normal)
        used = np.zeros(u.size, bool)
        for gather in (1.0, 1.5, 1.5):
            along = gu * normal[0] + gv * normal[1]
            near = np.abs(points @ normal - offset) <= gather
            used = near & (along > 0.94 * magnitude)  # within 20 degrees of the normal
            if used.sum() < 3:
                break
            normal, offset = _weighted_line(points, np.where(used, along, 0.0), normal)
        across = np.abs(gu * normal[0] + gv * normal[1])
        removed = (np.abs(points @ normal - offset) <= 1.5) & (across > 0.87 * magnitude)  # within 30 degrees
        removed[seed] = True
        if used.sum() >= 4 and _straight(gu[used], gv[used], normal):
            t = points[used] @ np.array([-normal[1], normal[0]])
            lines.append((normal, offset, float(t.min()), float(t.max())))
        free &= ~removed
    return lines


def _straight(gu: Matrix, gv: Matrix, normal: Matrix) -> bool:
    """Whether gradients keep one direction, as along a straight edge (a rim turns)."""
    across = gu * normal[1] - gv * normal[0]
    along = gu * normal[0] + gv * normal[1]
    # the along-weighted mean of (across / along)^2
    spread = math.degrees(math.sqrt(float((across * across / along).sum()) / float(along.sum())))
    return spread < _STRAIGHT_SPREAD_DEG


def _weighted_line(points: Matrix, weight: Matrix, normal_hint: Matrix) -> tuple[Matrix, float]:
    """Weighted total-least-squares line, its normal oriented like ``normal_hint``."""
    total = weight.sum()
    mean = (weight @ points) / total
    du, dv = points[:, 0] - mean[0], points[:, 1] - mean[1]
    suu, svv, suv = weight @ (du * du), weight @ (dv * dv), weight @ (du * dv)
    angle = 0.5 * math.atan2(2.0 * suv, suu - svv)  # direction of largest spread
    normal = np.array([-math.sin(angle), math.cos(angle)])
    if normal @ normal_hint < 0.0:
        normal = -normal
    return normal, float(mean @ normal)


def _fit_spot(
    values: Matrix, background: Matrix, u: Matrix, v: Matrix, start: Matrix, anchor: Matrix
) -> tuple[Matrix, float] | None:
    """Robust fit of B + A exp(-r^2 / 2 s^2) to the pixels of the hole: centre and RMS.

    Clipped pixels only say that the model reaches the clipping level there (a one-sided
    residual). A Cauchy loss lets the few pixels where the rebuilt background is wrong
    count less; those still off by more than four loss scales after the fit are then
    dropped and the fit repeated. Returns None if the fit is not sound.
    """
    clipped = values >= CLIPPED_LEVEL
    peak = float(np.max(values - background))
    params = np.array([start[0], start[1], math.log(max(peak, 30.0)), math.log(1.3)])
    # The centre stays near the clipped core (``anchor``), which is within a pixel of it.
    lower = np.array([anchor[0] - 1.5, anchor[1] - 1.5, math.log(5.0), math.log(0.3)])
    upper = np.array([anchor[0] + 1.5, anchor[1] + 1.5, math.log(1e5), math.log(6.0)])
    keep = np.ones(values.size, bool)
    res = np.zeros(values.size)
    for _ in range(2):
        kept = (values[keep], background[keep], u[keep], v[keep], clipped[keep])

        def model(p: Matrix) -> tuple[Matrix, Matrix]:
            return _residuals(p, *kept)  # called within this pass only: kept is this pass's

        params, res = levenberg_marquardt(
            model,
            params,
            lower,
            upper,
            iterations=20,
            settled=lambda old, new: float(np.abs(new[:2] - old[:2]).max()) < 2e-3,
            loss_scale=_CAUCHY_SCALE,
        )
        model_res = _residuals(params, values, background, u, v, clipped)[0]
        outliers = np.abs(model_res) > 4.0 * _CAUCHY_SCALE
        if not outliers.any() or (~outliers).sum() < 8:
            break
        keep = ~outliers
    sigma = math.exp(params[3])
    if not (np.all(np.isfinite(params)) and 0.4 < sigma < 5.0):
        return None
    inliers = np.abs(res) < 3.0 * _CAUCHY_SCALE
    rms = float(np.sqrt(np.mean(res[inliers] ** 2))) if inliers.any() else float("inf")
    return params[:2].copy(), rms


def _residuals(p: Matrix, values: Matrix, background: Matrix, u: Matrix, v: Matrix, clipped: np.ndarray) -> tuple[Matrix, Matrix]:
    """Residuals of the clipped spot model and their Jacobian in (cu, cv, log A, log s)."""
    cu, cv, log_a, log_s = p.tolist()
    amp, s2 = math.exp(log_a), math.exp(2.0 * log_s)
    du, dv = u - cu, v - cv
    r2 = du * du + dv * dv
    g = amp * np.exp(r2 * (-0.5 / s2))
    model = background + g
    res = np.where(clipped, np.minimum(model - CLIPPED_LEVEL, 0.0), model - values)
    g_s2 = g / s2
    jac = np.empty((len(g), 4))
    np.multiply(g_s2, du, out=jac[:, 0])
    np.multiply(g_s2, dv, out=jac[:, 1])
    jac[:, 2] = g
    np.multiply(g_s2, r2, out=jac[:, 3])
    jac[clipped & (model >= CLIPPED_LEVEL)] = 0.0
    return res, jac
