"""What the detectors share: input checks and straight-edge location by the partial-area effect.

Pixel convention (OpenCV): the pixel at row r, column c has its centre at (u, v) = (c, r).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from vservo.core.geometry.spatial import Matrix

#: Smallest image side any detector accepts.
MIN_IMAGE_SIDE = 16


def image_problem(image: object) -> str:
    """Why ``image`` cannot be measured, or "" when it is an 8-bit single-channel image."""
    if not isinstance(image, np.ndarray):
        return f"image must be an 8-bit single channel numpy array, got {type(image).__name__}"
    if image.dtype != np.uint8 or image.ndim != 2:
        return f"image must be 8-bit single channel, got {image.dtype} {image.shape}"
    if min(image.shape) < MIN_IMAGE_SIDE:
        return f"image too small: {image.shape}, need at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE}"
    return ""


#: Margin (px) of the full-resolution window around a region found on every other pixel.
_WINDOW_MARGIN_PX = 4


def bright_contours(img: np.ndarray, threshold: float, approximation: int, whole_frame: bool = False) -> list[np.ndarray]:
    """Outer contours (full-frame coordinates) of the pixels >= ``threshold``, at least
    of the largest region and of whatever else lies near it.

    The largest region is found on every other pixel first and traced at full
    resolution in a window around it: thresholding and tracing the whole frame costs
    several times more, most of it in touching a fresh frame-sized array. When the
    largest traced contour reaches the window's edge (the region is thinner than a
    sampled pixel somewhere) the whole frame is traced. ``approximation`` is OpenCV's
    contour approximation method; ``whole_frame`` skips the window. Empty when no pixel
    passes.
    """
    height, width = img.shape
    coarse = (np.ascontiguousarray(img[::2, ::2]) >= threshold).view(np.uint8) if not whole_frame else None
    found = cv2.findContours(coarse, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)[0] if coarse is not None else ()
    if found:
        x, y, w, h = cv2.boundingRect(max(found, key=cv2.contourArea))
        x0, y0 = max(2 * x - _WINDOW_MARGIN_PX, 0), max(2 * y - _WINDOW_MARGIN_PX, 0)
        x1, y1 = min(2 * (x + w) + _WINDOW_MARGIN_PX, width), min(2 * (y + h) + _WINDOW_MARGIN_PX, height)
        window = (img[y0:y1, x0:x1] >= threshold).view(np.uint8)
        contours, _ = cv2.findContours(window, cv2.RETR_EXTERNAL, approximation, offset=(x0, y0))
        if contours:
            x, y, w, h = cv2.boundingRect(max(contours, key=cv2.contourArea))
            if (x > x0 or x0 == 0) and (y > y0 or y0 == 0) and (x + w < x1 or x1 == width) and (y + h < y1 or y1 == height):
                return list(contours)
    contours, _ = cv2.findContours((img >= threshold).view(np.uint8), cv2.RETR_EXTERNAL, approximation)
    return list(contours)


def frozen_array(values: object, shape: tuple[int, ...]) -> Matrix:
    """A read-only float64 copy of ``values`` with the given shape."""
    array = np.array(values, dtype=np.float64).reshape(shape)
    array.flags.writeable = False
    return array


#: One straight edge to sample: (unit normal from dark to bright, offset, start, stop).
Segment = tuple[Matrix, float, Matrix, Matrix]


@dataclass(frozen=True)
class Strips:
    """Strips of pixels across straight edges (see ``sample_strips``), one row per strip.

    segment: which segment the strip belongs to (sorted); along: the strip's column (its
    row for a steep edge); steep: the edge runs more along v than along u; base: the
    pixel across the edge nearest the segment's line; values: grey levels from base - r
    to base + r (r = half the row length); bright_high: the bright side is at the larger
    index across.
    """

    segment: np.ndarray
    along: np.ndarray
    steep: np.ndarray
    base: np.ndarray
    values: Matrix
    bright_high: np.ndarray


def sample_strips(
    image: np.ndarray,
    segments: list[Segment],
    reach: int,
    keep_out: Sequence[tuple[Matrix, float]] = (),
    end_margin: float = 0.0,
) -> Strips | None:
    """One strip of 2 reach + 1 pixels per column (per row for a steep edge) across each
    segment (normal, offset, start, stop), centred on the pixel nearest its line, from
    ``end_margin`` px (along the strips' axis) after start to as much before stop; strips
    leaving the image or reaching within a disc of ``keep_out`` [(centre, radius), ...]
    are skipped. None when there is no strip."""
    height, width = image.shape
    # Per segment (in Python: there are a handful): which way its strips run, which
    # pixels along the edge they cover, and its line in the strips' frame.
    table, counts, shifts = [], [], []
    total = 0
    for normal, offset, start, stop in segments:
        n0, n1 = float(normal[0]), float(normal[1])
        steep = abs(n0) > abs(n1)  # the edge runs more along v than along u
        axis = 1 if steep else 0
        lo, hi = sorted((float(start[axis]), float(stop[axis])))
        first = max(math.ceil(lo + end_margin), 0)
        last = min(math.floor(hi - end_margin), (height if steep else width) - 1)
        count = max(last - first + 1, 0)
        # (steep, normal across, normal along, offset, extent across, and the index
        # steps in the flattened image of a pixel along and of a pixel across)
        table.append(
            (
                steep,
                n0 if steep else n1,
                n1 if steep else n0,
                float(offset),
                width if steep else height,
                width if steep else 1,
                1 if steep else width,
            )
        )
        counts.append(count)
        shifts.append(first - total)
        total += count
    if total == 0:
        return None
    seg = np.repeat(np.arange(len(segments)), counts)
    along = np.arange(total) + np.repeat(shifts, counts)
    steep, n_across, n_along, offsets, extent, along_stride, across_stride = np.array(table).take(seg, axis=0).T
    base = np.rint((offsets - n_along * along) / n_across)
    keep = (base >= reach) & (base + reach < extent)
    steep = steep > 0.0
    for point, radius in keep_out:
        # The disc's centre in each strip's frame: along the edge and across it.
        za = np.where(steep, float(point[1]), float(point[0]))
        zc = np.where(steep, float(point[0]), float(point[1]))
        nearest = np.minimum(np.maximum(zc, base - (reach + 0.5)), base + (reach + 0.5))
        keep &= (along - za) ** 2 + (nearest - zc) ** 2 > radius * radius
    kept = np.flatnonzero(keep)
    if not len(kept):
        return None
    seg, along, steep, base, n_across = seg.take(kept), along.take(kept), steep.take(kept), base.take(kept), n_across.take(kept)
    across_stride = across_stride.take(kept)
    # The strips' pixels by their index in the flattened image (np.take: much cheaper
    # than 2-D indexing).
    first_pixel = along * along_stride.take(kept) + base * across_stride
    pixels = (first_pixel[:, None] + across_stride[:, None] * np.arange(-reach, reach + 1)).astype(np.int64)
    values = np.ascontiguousarray(image).ravel().take(pixels).astype(np.float64)
    return Strips(seg, along, steep, base.astype(np.int64), values, n_across > 0.0)


def edge_points_many(
    image: np.ndarray,
    segments: list[Segment],
    half_width: float = 1.5,
    level_px: int = 1,
    keep_out: Sequence[tuple[Matrix, float]] = (),
    end_margin: float = 0.0,
    min_contrast: float = 12.0,
) -> list[Matrix]:
    """Sub-pixel points of straight edges, each near its line normal . x = offset.

    ``normal`` (unit) points from the dark side to the bright side. Each edge is sampled
    between the points ``start`` and ``stop`` (on or near its line), one strip of
    2 ceil(half_width) + 1 pixels per column (per row for a steep edge) across it: the
    strip's grey levels, scaled to 0 on the dark level and 1 on the bright one, sum to
    the length of its bright part, which puts the edge where a box-filtered (or any
    symmetrically blurred) straight step has it, whatever its phase against the pixel
    grid: the partial-area effect. The dark and bright levels are read on ``level_px``
    pixels just beyond the strip's two ends and smoothed along the edge (a running
    median of 5 strips), which also follows uneven lighting. A narrow strip stays on a
    side face a few pixels wide next to the edge, which a wide one would cross.

    Strips within ``end_margin`` px of a segment's ends (along the strips' axis) or
    reaching within a disc of ``keep_out`` [(centre, radius), ...] are skipped. Returns
    one (N_i, 2) array of points (u, v) per segment.
    """
    count = len(segments)
    empty = [np.empty((0, 2)) for _ in range(count)]
    k = math.ceil(half_width)
    strips = sample_strips(image, segments, k + level_px, keep_out, end_margin)
    if strips is None:
        return empty
    values = strips.values
    low_end = values[:, :level_px].sum(axis=1) / level_px
    high_end = values[:, -level_px:].sum(axis=1) / level_px
    bright_high = strips.bright_high
    bright_raw = np.where(bright_high, high_end, low_end)
    dark_raw = np.where(bright_high, low_end, high_end)
    ok = np.flatnonzero(bright_raw - dark_raw > min_contrast)
    if not len(ok):
        return empty
    seg, along, steep, base, bright_high = (
        strips.segment.take(ok),
        strips.along.take(ok),
        strips.steep.take(ok),
        strips.base.take(ok),
        bright_high.take(ok),
    )
    strip = values.take(ok, axis=0)[:, level_px:-level_px]
    bright, dark = running_median(np.array((bright_raw.take(ok), dark_raw.take(ok))).T, seg).T
    contrast = bright - dark
    bright_length = ((strip - dark[:, None]) / np.where(contrast > 0.0, contrast, 1.0)[:, None]).sum(axis=1)
    position = np.where(bright_high, base + k + 0.5 - bright_length, base - k - 0.5 + bright_length)
    # The edge must lie inside its strip, away from the ends.
    good = (contrast > min_contrast) & (np.abs(position - base) < k - 0.25)
    good = np.flatnonzero(good)
    points = np.array((np.where(steep, position, along), np.where(steep, along, position))).T.take(good, axis=0)
    seg = seg.take(good)
    bounds = np.searchsorted(seg, np.arange(count + 1))
    return [points[bounds[i] : bounds[i + 1]] for i in range(count)]


def running_median(levels: Matrix, segment: np.ndarray) -> Matrix:
    """Running median of 5 successive strips of the same segment (sorted by segment),
    of each column of ``levels`` (N,) or (N, k); near a segment's ends the window's
    members beyond it repeat its end strip.

    A median keeps the step where the far side of an edge changes (a side face ending
    at a junction) and follows uneven lighting, while it quietens the noise.
    """
    if not len(levels):
        return levels.copy()
    bounds = np.searchsorted(segment, np.arange(int(segment[-1]) + 2))
    starts, stops = bounds.take(segment), bounds.take(segment + 1) - 1
    window = np.minimum(np.maximum(np.arange(len(levels)) + _WINDOW_OFFSETS, starts), stops)  # (5, N)
    return median_of_five(*np.take(levels, window, axis=0))


#: The running window's members relative to its middle strip.
_WINDOW_OFFSETS = np.arange(-2, 3)[:, None]


def median_of_five(a: Matrix, b: Matrix, c: Matrix, d: Matrix, e: Matrix) -> Matrix:
    """Elementwise median of five arrays by comparisons (a sorting network: for a few
    hundred rows of five, sorting costs several times more). Of a, b, c, d the smallest
    and the largest cannot be the median: it is the median of e and the two others.
    """
    low = np.maximum(np.minimum(a, b), np.minimum(c, d))
    high = np.minimum(np.maximum(a, b), np.maximum(c, d))
    return np.maximum(np.minimum(e, low), np.minimum(np.maximum(e, low), high))


def segment_medians(values: Matrix, segment: np.ndarray, count: int) -> Matrix:
    """The median (lower middle) of ``values`` in each of ``count`` segments (``segment``
    sorted); NaN for an empty one. A partial sort per segment: for a handful of
    segments cheaper than np.median's or one lexsort's overheads."""
    bounds = np.searchsorted(segment, np.arange(count + 1)).tolist()
    medians = np.full(count, np.nan)
    for i, (start, stop) in enumerate(zip(bounds[:-1], bounds[1:])):
        if stop > start:
            middle = (stop - start - 1) // 2
            medians[i] = np.partition(values[start:stop], middle)[middle]
    return medians


def fit_lines(
    points: list[Matrix], normal_hints: list[Matrix], min_points: int = 3, rounds: int = 4
) -> list[tuple[Matrix, float, Matrix, float] | None]:
    """Robust straight-line fits, one per set of edge points: (unit normal, offset,
    inlier mask, RMS of the inliers' distances), or None with too few points.

    Least squares across each line's main direction (the points' errors are along one
    image axis, see ``edge_points_many``), then points beyond three sigmas (and beyond
    0.1 px) are dropped and the fit repeated. Normals are oriented like the
    hints. All sets are fitted together, which costs little more than one; ``rounds``
    bounds the fits per set.
    """
    count = len(points)
    results: list[tuple[Matrix, float, Matrix, float] | None] = [None] * count
    sizes = np.array([len(p) for p in points])
    if sizes.sum() == 0:
        return results
    seg = np.repeat(np.arange(count), sizes)
    stacked = np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in points])
    hints = np.array([np.asarray(h, dtype=np.float64) for h in normal_hints])
    steep_s = np.abs(hints[:, 0]) > np.abs(hints[:, 1])
    steep = steep_s[seg]
    a = np.where(steep, stacked[:, 1], stacked[:, 0])
    b = np.where(steep, stacked[:, 0], stacked[:, 1])
    a_mean = np.bincount(seg, a, count) / np.maximum(sizes, 1)
    a = a - a_mean[seg]
    # The sets' sums of 1, a, b, aa, ab over their inliers: one product per round with
    # the points' one-hot set membership.
    moments = np.empty((len(a), 5))
    moments[:, 0], moments[:, 1], moments[:, 2] = 1.0, a, b
    np.multiply(a, a, out=moments[:, 3])
    np.multiply(a, b, out=moments[:, 4])
    member = (seg[:, None] == np.arange(count)).astype(np.float64)
    keep = np.ones(len(a), bool)
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    for round_index in range(rounds):
        n, sa, sb, saa, sab = (moments * keep[:, None]).T.dot(member)
        det = n * saa - sa * sa
        ok = (n >= min_points) & (det > 1e-12)
        slope = np.where(ok, (n * sab - sa * sb) / np.where(ok, det, 1.0), 0.0)
        intercept = (sb - slope * sa) / np.maximum(n, 1.0)
        residual = b - intercept[seg] - slope[seg] * a
        if round_index == rounds - 1:
            break
        magnitude = np.abs(residual)
        # Each set's median |residual| over its inliers (one sort for all sets).
        order = np.lexsort((np.where(keep, magnitude, np.inf), seg))
        middle = np.minimum(bounds[:-1] + (np.maximum(n, 1.0).astype(np.int64) - 1) // 2, len(a) - 1)
        sigma = 1.4826 * magnitude[order][middle]
        new_keep = magnitude <= np.maximum(3.0 * sigma, 0.1)[seg]
        enough = np.bincount(seg, new_keep.astype(np.float64), count) >= min_points
        new_keep |= ~enough[seg] & keep  # a set that would fall short keeps its last inliers
        if not (new_keep ^ keep).any():
            break
        keep = new_keep
    # b = slope (a_img - a_mean) + intercept  <=>  b - slope a_img = intercept - slope a_mean
    scale = np.hypot(1.0, slope)
    normals = np.empty((count, 2))
    normals[:, 0] = np.where(steep_s, 1.0, -slope)
    normals[:, 1] = np.where(steep_s, -slope, 1.0)
    # unit length, and pointing like the hints
    sign = np.where((normals * hints).sum(axis=1) < 0.0, -1.0, 1.0) / scale
    normals *= sign[:, None]
    offsets = (intercept - slope * a_mean) * sign
    rms = np.sqrt(np.bincount(seg, keep * residual**2, count) / np.maximum(n, 1.0)) / scale
    for i in np.flatnonzero(ok):
        results[i] = (normals[i], float(offsets[i]), keep[bounds[i] : bounds[i + 1]].copy(), float(rms[i]))
    return results


def polygon_corners(lines: list[tuple[Matrix, float]]) -> Matrix:
    """Corners (K, 2) of a polygon given by its K sides as lines n . x = d in order:
    corner i is where side i - 1 meets side i (Cramer's rule); NaN where they are
    parallel. (Scalar arithmetic: for a handful of lines it costs a fraction of the
    array operations' overheads.)"""
    corners = np.empty((len(lines), 2))
    (a0, a1), d_a = lines[-1][0].tolist(), float(lines[-1][1])
    for i, (normal, offset) in enumerate(lines):
        (b0, b1), d_b = normal.tolist(), float(offset)
        det = a0 * b1 - a1 * b0
        if abs(det) < 1e-9:
            corners[i] = np.nan
        else:
            corners[i] = ((d_a * b1 - a1 * d_b) / det, (a0 * d_b - d_a * b0) / det)
        a0, a1, d_a = b0, b1, d_b
    return corners
