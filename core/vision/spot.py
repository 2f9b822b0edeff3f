"""The laser spot: a fixed-level threshold, then a sub-pixel centre (thesis section 4.3).

The thesis finds the spot as the pixels brighter than a fixed level. Here that level
only detects and counts the blobs; the centre comes from the grey levels around the
blob. The spot adds light to whatever it falls on, and the sensor clips at 255:

    I(x) = min(255, B(x) + A exp(-|x - c|^2 / (2 s^2)))

where B is the scene without the spot. On a uniform background (the table, the inside
of the top face) B is a plane fitted to a ring around the blob. On an edge or a
corner of the top face it is not: B is then rebuilt inside the ring from the straight
edges crossing the ring (a line arrangement, each cell at the level the ring shows
for it), which keeps a corner sharp where a smooth fill would round it. The centre c
then comes from a least-squares fit of the model above to the unclipped pixels, with
the clipped ones as one-sided constraints, so the clipped core, smaller on a dark
background than on a bright one, does not pull c towards the bright side.

Pixel convention (OpenCV): the pixel at row r, column c has its centre at (u, v) = (c, r).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.spatial import Matrix

#: Smallest image side any detector accepts.
MIN_IMAGE_SIDE = 16
#: Grey level from which a pixel counts as clipped by the sensor.
CLIPPED_LEVEL = 254


def image_problem(image: object) -> str:
    """Why ``image`` cannot be measured, or "" when it is an 8-bit single-channel image."""
    if not isinstance(image, np.ndarray):
        return f"image must be an 8-bit single channel numpy array, got {type(image).__name__}"
    if image.dtype != np.uint8 or image.ndim != 2:
        return f"image must be 8-bit single channel, got {image.dtype} {image.shape}"
    if min(image.shape) < MIN_IMAGE_SIDE:
        return f"image too small: {image.shape}, need at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE}"
    return ""


def frozen_array(values: object, shape: tuple[int, ...]) -> Matrix:
    """A read-only float64 copy of ``values`` with the given shape."""
    array = np.array(values, dtype=np.float64).reshape(shape)
    array.flags.writeable = False
    return array


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


def detect_laser_spot(
    image: np.ndarray, threshold: float = 250, min_area_px: int = 1, max_area_px: int = 150
) -> SpotDetection:
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
    brightest = cv2.minMaxLoc(img)[1]
    if brightest < threshold:
        return _no_spot(f"no spot: no pixel at or above {threshold:g} (brightest {brightest:.0f})")
    binary = (img >= threshold).view(np.uint8)
    x0, y0, w, h = cv2.boundingRect(binary)
    roi = binary[y0 : y0 + h, x0 : x0 + w]
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
        return _no_spot(
            f"bright blob too large: {area} px above max_area_px={max_area_px} (saturated frame or reflection)", area
        )
    rows, cols = np.nonzero(on & (labels == blobs[0]))
    blob_u, blob_v = cols + float(x0), rows + float(y0)
    centre, confidence, note = _subpixel_centre(img, blob_u, blob_v)
    return SpotDetection(True, frozen_array(centre, (2,)), float(area), confidence, note)


# ---------------------------------------------------------------------------------------
# Sub-pixel centre
# ---------------------------------------------------------------------------------------


def _subpixel_centre(img: np.ndarray, blob_u: np.ndarray, blob_v: np.ndarray) -> tuple[Matrix, float, str]:
    """Centre of the spot whose clipped pixels are (blob_u, blob_v), its confidence, and ""."""
    u0, v0 = float(blob_u.mean()), float(blob_v.mean())
    r_blob = float(np.sqrt(((blob_u - u0) ** 2 + (blob_v - v0) ** 2).max())) + 0.5
    r_hole = max(4.0, r_blob + 3.0)  # the spot adds less than ~2 grey levels beyond
    r_ring = r_hole + 6.0
    height, width = img.shape
    c0, c1 = max(int(u0 - r_ring) - 2, 0), min(int(u0 + r_ring) + 3, width)
    r0, r1 = max(int(v0 - r_ring) - 2, 0), min(int(v0 + r_ring) + 3, height)
    win = img[r0:r1, c0:c1].astype(np.float64)
    uu, vv = np.meshgrid(np.arange(c0, c1, dtype=np.float64), np.arange(r0, r1, dtype=np.float64))
    radius = np.hypot(uu - u0, vv - v0)
    ring = (radius >= r_hole) & (radius <= r_ring)
    hole = radius < r_hole
    confidence = 1.0

    background, structured = _plane_background(win, uu, vv, ring)
    if structured:
        edged = _edge_background(win, uu, vv, radius, r_hole, r_ring)
        if edged is not None:
            background = edged
        confidence *= 0.8
    excess = np.where(hole, win - background, 0.0)
    weights = np.clip(excess, 0.0, None)
    total = weights.sum()
    if total <= 0.0:
        return np.array([u0, v0]), 0.3, ""
    centroid = np.array([(weights * uu).sum() / total, (weights * vv).sum() / total])

    fitted = _fit_spot(win[hole], background[hole], uu[hole], vv[hole], centroid)
    if fitted is None:
        return centroid, 0.5 * confidence, ""
    centre, rms = fitted
    confidence *= float(np.clip(1.0 - (rms - 3.0) / 30.0, 0.3, 1.0))
    return centre, confidence, ""


def _plane_background(win: Matrix, uu: Matrix, vv: Matrix, ring: np.ndarray) -> tuple[Matrix, bool]:
    """A plane fitted to the ring, and whether the ring shows more than a plane (an edge)."""
    values = win[ring]
    design = np.column_stack([np.ones(values.size), uu[ring] - uu[ring].mean(), vv[ring] - vv[ring].mean()])
    coef, *_ = np.linalg.lstsq(design, values, rcond=None)
    residual = values - design @ coef
    structured = bool(np.percentile(np.abs(residual), 95) > 12.0)
    plane = coef[0] + coef[1] * (uu - uu[ring].mean()) + coef[2] * (vv - vv[ring].mean())
    return plane, structured


def _edge_background(
    win: Matrix, uu: Matrix, vv: Matrix, radius: Matrix, r_hole: float, r_ring: float
) -> Matrix | None:
    """The spot-free scene inside the ring, from the straight edges that cross the ring.

    Edges are found from the grey-level gradient in the ring, as lines; the lines cut
    the window into cells, each at the median level of the ring pixels it holds; inside
    the hole the cells are drawn with 4 x 4 supersampling, as a camera pixel averages.
    """
    win32 = win.astype(np.float32)
    gu = cv2.Scharr(win32, cv2.CV_32F, 1, 0).astype(np.float64) / 32.0
    gv = cv2.Scharr(win32, cv2.CV_32F, 0, 1).astype(np.float64) / 32.0
    inner = np.zeros(win.shape, bool)
    inner[1:-1, 1:-1] = True
    usable = inner & (radius >= r_hole + 1.5) & (radius <= r_ring)
    lines = _find_lines(uu[usable], vv[usable], gu[usable], gv[usable])
    if not lines:
        return None
    normals = np.array([n for n, _ in lines])
    offsets = np.array([d for _, d in lines])

    def cell_codes(u: Matrix, v: Matrix) -> Matrix:
        side = (np.stack([u, v], axis=-1) @ normals.T - offsets) > 0.0
        return (side * (1 << np.arange(len(lines)))).sum(axis=-1)

    ring = (radius >= r_hole) & (radius <= r_ring)
    ru, rv, rvalues = uu[ring], vv[ring], win[ring]
    distance = np.abs(np.stack([ru, rv], axis=-1) @ normals.T - offsets).min(axis=1)
    clear = distance > 1.0
    if clear.sum() < 8:
        return None
    codes = cell_codes(ru[clear], rv[clear])
    fallback = float(np.median(rvalues[clear]))
    levels = np.full(1 << len(lines), fallback)
    for code in np.unique(codes):
        levels[code] = np.median(rvalues[clear][codes == code])

    background = win.copy()
    hole = radius < r_hole + 1.0
    offsets_ss = (np.arange(4) + 0.5) / 4.0 - 0.5
    du, dv = np.meshgrid(offsets_ss, offsets_ss)
    su = uu[hole][:, None] + du.ravel()[None, :]
    sv = vv[hole][:, None] + dv.ravel()[None, :]
    background[hole] = levels[cell_codes(su, sv)].mean(axis=1)
    return background


def _find_lines(
    u: Matrix, v: Matrix, gu: Matrix, gv: Matrix, max_lines: int = 4
) -> list[tuple[Matrix, float]]:
    """Straight edges among gradient samples: (unit normal, offset) with normal . x = offset.

    Greedy: seed at the strongest remaining gradient, gather the samples near its line
    with a gradient along its normal, fit by weighted total least squares (weights the
    gradient along the normal: its first moment across a box-blurred step is the step's
    position), gather again around the fit, refit, and remove what was used.
    """
    magnitude = np.hypot(gu, gv)
    points = np.column_stack([u, v])
    free = magnitude > 12.0
    lines: list[tuple[Matrix, float]] = []
    while free.sum() >= 4 and len(lines) < max_lines:
        seed = int(np.argmax(np.where(free, magnitude, -1.0)))
        normal = np.array([gu[seed], gv[seed]]) / magnitude[seed]
        offset = float(points[seed] @ normal)
        used = np.zeros(u.size, bool)
        for gather in (1.5, 2.0, 2.0):
            along = gu * normal[0] + gv * normal[1]
            near = np.abs(points @ normal - offset) <= gather
            aligned = along > 0.5 * magnitude  # within 60 degrees of the normal
            used = near & aligned & (along > 0.0)
            weight = np.where(used, along, 0.0)
            if weight.sum() <= 0.0 or used.sum() < 3:
                break
            normal, offset = _weighted_line(points, weight, normal)
        removed = (np.abs(points @ normal - offset) <= 2.5) & (np.abs(gu * normal[0] + gv * normal[1]) > 0.3 * magnitude)
        removed[seed] = True
        if used.sum() >= 4:
            lines.append((normal, offset))
        free &= ~removed
    return lines


def _weighted_line(points: Matrix, weight: Matrix, normal_hint: Matrix) -> tuple[Matrix, float]:
    """Weighted total-least-squares line, its normal oriented like ``normal_hint``."""
    total = weight.sum()
    mean = (weight[:, None] * points).sum(axis=0) / total
    centred = points - mean
    scatter = (weight[:, None, None] * centred[:, :, None] * centred[:, None, :]).sum(axis=0)
    _, vectors = np.linalg.eigh(scatter)
    normal = vectors[:, 0]
    if normal @ normal_hint < 0.0:
        normal = -normal
    return normal, float(mean @ normal)


def _fit_spot(
    values: Matrix, background: Matrix, u: Matrix, v: Matrix, start: Matrix, iterations: int = 30
) -> tuple[Matrix, float] | None:
    """Levenberg-Marquardt fit of B + A exp(-r^2 / 2 s^2) to the pixels of the hole.

    Clipped pixels only say that the model reaches the clipping level there (a one-sided
    residual). Returns the centre and the RMS residual, or None if the fit is not sound.
    """
    clipped = values >= CLIPPED_LEVEL
    excess = values - background
    peak = float(np.max(excess))
    params = np.array([start[0], start[1], math.log(max(peak, 30.0)), math.log(1.3)])

    def residuals(p: Matrix) -> tuple[Matrix, Matrix]:
        cu, cv, log_a, log_s = p
        amp, s2 = math.exp(log_a), math.exp(2.0 * log_s)
        du, dv = u - cu, v - cv
        g = np.exp(-(du * du + dv * dv) / (2.0 * s2))
        model = background + amp * g
        res = model - values
        active = ~clipped | (model < CLIPPED_LEVEL)
        res = np.where(clipped, np.minimum(model - CLIPPED_LEVEL, 0.0), res)
        jac = np.column_stack(
            [amp * g * du / s2, amp * g * dv / s2, amp * g, amp * g * (du * du + dv * dv) / s2]
        )
        jac[~active] = 0.0
        return res, jac

    damping = 1e-3
    res, jac = residuals(params)
    cost = float(res @ res)
    for _ in range(iterations):
        normal = jac.T @ jac
        gradient = jac.T @ res
        step = np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-9), -gradient)
        trial = params + step
        res_t, jac_t = residuals(trial)
        cost_t = float(res_t @ res_t)
        if cost_t < cost:
            params, res, jac, cost = trial, res_t, jac_t, cost_t
            damping = max(damping / 3.0, 1e-7)
            if np.abs(step[:2]).max() < 1e-4:
                break
        else:
            damping *= 4.0
            if damping > 1e6:
                break
    centre = params[:2]
    sigma = math.exp(params[3])
    if not (np.all(np.isfinite(params)) and np.hypot(*(centre - start)) < 2.0 and 0.4 < sigma < 5.0):
        return None
    return centre.copy(), math.sqrt(cost / max(values.size, 1))
