"""What frames a figure's data: nice ticks and their labels, the 2-D axes box (grid,
ticks, labels, title) and the 3-D view (orthographic projection, the data's box with a
grid on its back faces and ticks on three edges). ``Axes`` and ``View3D`` are the
data-to-pixel mappings a figure was drawn with.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vservo.core.study.canvas import (
    BGR,
    BLACK,
    GAP,
    LABEL_SCALE,
    PAD,
    SHIFT,
    TICK_LEN,
    TICK_SCALE,
    TITLE_SCALE,
    Image,
    draw_polyline,
    fixed,
    put_text,
    put_text_beside,
    put_text_vertical,
    text_height,
    text_size,
)

Limits3 = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]

_GRID: BGR = (228, 228, 228)
_BACK_EDGE: BGR = (150, 150, 150)
MARGIN = 0.04  # autoscale margin, a fraction of the data range on each side
_MIN_TICK_EDGE = 60  # px: a 3-D axis seen shorter than this gets no ticks or label


def finite_range(lo: float, hi: float) -> tuple[float, float]:
    """(lo, hi) ordered, NaN/inf replaced by the other end, a zero width widened."""
    values = [float(v) for v in (lo, hi) if math.isfinite(float(v))]
    if not values:
        return 0.0, 1.0
    lo, hi = min(values), max(values)
    if hi - lo <= 1e-12 * max(abs(lo), abs(hi)):
        half = 0.1 * abs(lo) if lo != 0.0 else 1.0
        lo, hi = lo - half, hi + half
    return lo, hi


def nice_ticks(lo: float, hi: float, max_ticks: int = 6) -> NDArray[np.float64]:
    """Evenly spaced ticks with a 1, 2 or 5 x 10^k step that cover [lo, hi].

    The first tick is <= lo and the last >= hi, with at most ``max_ticks`` intervals
    (so at most max_ticks + 1 ticks), using the finest step that allows it. NaN or inf
    at one end is replaced by the other end, a zero-width range is widened around its
    value, and a range with no finite end becomes [0, 1].
    """
    if max_ticks < 2:
        raise ValueError(f"max_ticks must be >= 2, got {max_ticks}")
    lo, hi = finite_range(lo, hi)
    span = hi - lo
    if not math.isfinite(span):
        return np.array([lo, hi])
    exponent = math.floor(math.log10(span / max_ticks))
    while True:  # ends: once step >= span, the ticks need at most 2 intervals
        for mantissa in (1.0, 2.0, 5.0):
            step = mantissa * 10.0**exponent
            first = math.floor(lo / step + 1e-9)
            last = math.ceil(hi / step - 1e-9)
            if last - first <= max_ticks:
                return np.array([float(f"{k * step:.12g}") for k in range(first, last + 1)])
        exponent += 1


def format_tick(value: float, step: float) -> str:
    """A compact label for a tick on a grid of the given step: '0.05', '-0.1', '300'."""
    if value == 0.0:
        return "0"
    exponent = math.floor(math.log10(abs(step)) + 1e-9) if step > 0 else 0
    decimals = max(0, -exponent)
    if abs(value) >= 1e6 or decimals > 5:
        text = f"{value:.3g}".replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")
        return text
    text = f"{value:.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def tick_labels(ticks: ArrayLike) -> list[str]:
    """Labels for evenly spaced ticks, formatted with the precision their step needs."""
    ticks = np.asarray(ticks, dtype=float).reshape(-1)
    if ticks.size == 0:
        return []
    steps = np.abs(np.diff(ticks))
    step = float(steps.min()) if steps.size and steps.min() > 0 else (abs(float(ticks[0])) or 1.0)
    return [format_tick(float(t), step) for t in ticks]


def ticks_within(lo: float, hi: float, max_ticks: int) -> NDArray[np.float64]:
    """The finest nice ticks inside [lo, hi] that number at most max_ticks."""
    tolerance = 1e-9 * (hi - lo)
    for intervals in range(max_ticks + 1, 1, -1):
        ticks = nice_ticks(lo, hi, intervals)
        inside = ticks[(ticks >= lo - tolerance) & (ticks <= hi + tolerance)]
        if len(inside) <= max_ticks:
            return inside
    return inside


def padded_limits(values: NDArray[np.float64], margin: float = MARGIN) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = finite_range(float(finite.min()), float(finite.max()))
    pad = margin * (hi - lo)
    return lo - pad, hi + pad


@dataclass(frozen=True)
class Axes:
    """Where a 2-D plot put its data: x_lim maps to box columns, y_lim to box rows.

    box is (left, top, right, bottom) in pixels, the columns/rows of the axes lines.
    With ``y_down`` y_lim[0] is at the top (an image plane); otherwise at the bottom.
    legend_box is (left, top, right, bottom) of the legend, or None without a legend.
    """

    x_lim: tuple[float, float]
    y_lim: tuple[float, float]
    box: tuple[int, int, int, int]
    y_down: bool = False
    x_ticks: tuple[float, ...] = ()
    y_ticks: tuple[float, ...] = ()
    legend_box: tuple[int, int, int, int] | None = None

    def to_pixel(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """Pixel (column, row) of data (x, y); shape broadcast(x, y) + (2,)."""
        left, top, right, bottom = self.box
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        column = left + (x - self.x_lim[0]) / (self.x_lim[1] - self.x_lim[0]) * (right - left)
        fraction = (y - self.y_lim[0]) / (self.y_lim[1] - self.y_lim[0])
        row = top + fraction * (bottom - top) if self.y_down else bottom - fraction * (bottom - top)
        return np.stack([column, row], axis=-1)


@dataclass(frozen=True, eq=False)
class View3D:
    """The orthographic projection a 3-D plot was drawn with.

    ``to_pixel(p) = center_px + scale * [right . (p - center), -(up . (p - center))]``,
    with ``right``/``up`` the unit screen directions in data coordinates (MATLAB's
    ``view(azimuth, elevation)``): one scale for all three axes.
    """

    right: NDArray[np.float64]
    up: NDArray[np.float64]
    center: NDArray[np.float64]
    center_px: tuple[float, float]
    scale: float
    limits: Limits3

    @property
    def toward_viewer(self) -> NDArray[np.float64]:
        return np.cross(self.right, self.up)

    def to_pixel(self, xyz: ArrayLike) -> NDArray[np.float64]:
        """Pixel (column, row) of points (..., 3)."""
        offset = np.asarray(xyz, dtype=float) - self.center
        column = self.center_px[0] + self.scale * (offset @ self.right)
        row = self.center_px[1] - self.scale * (offset @ self.up)
        return np.stack([column, row], axis=-1)


def view_basis(azimuth_deg: float, elevation_deg: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    right = np.array([math.cos(az), math.sin(az), 0.0])
    up = np.array([-math.sin(el) * math.sin(az), math.sin(el) * math.cos(az), math.cos(el)])
    return right, up


def axes_box(
    size: tuple[int, int],
    title: str,
    xlabel: str,
    ylabel: str,
    x_labels: Sequence[str],
    y_labels: Sequence[str],
    aspect: float | None = None,
) -> tuple[int, int, int, int]:
    """Pixel box of the axes leaving room for title, labels and tick labels.

    With ``aspect`` (data width / data height at equal scale) the box is shrunk to it and
    centred in the room available.
    """
    width, height = size
    tick_h = text_height(TICK_SCALE)
    label_h = text_height(LABEL_SCALE) + 4
    title_h = text_height(TITLE_SCALE) + 4
    y_label_w = max((text_size(t, TICK_SCALE)[0] for t in y_labels), default=0)
    last_x_w = text_size(x_labels[-1], TICK_SCALE)[0] if x_labels else 0
    left = PAD + (label_h + 2 * GAP if ylabel else 0) + y_label_w + GAP + TICK_LEN
    top = PAD + (title_h + 2 * GAP if title else tick_h // 2 + 2)
    right = width - 1 - max(PAD + 4, last_x_w // 2 + PAD)
    bottom = height - 1 - (PAD + TICK_LEN + GAP + tick_h + (2 * GAP + label_h if xlabel else 0))
    if aspect is not None and right > left and bottom > top:
        room_w, room_h = right - left, bottom - top
        if room_w / room_h > aspect:
            extra = room_w - round(room_h * aspect)
            left, right = left + extra // 2, right - (extra - extra // 2)
        else:
            extra = room_h - round(room_w / aspect)
            top, bottom = top + extra // 2, bottom - (extra - extra // 2)
    if right - left < 20 or bottom - top < 20:
        raise ValueError(f"figure size {size} leaves no room for the axes")
    return left, top, right, bottom


def draw_grid(img: Image, axes: Axes) -> None:
    left, top, right, bottom = axes.box
    for x in axes.x_ticks:
        column = round(float(axes.to_pixel(x, axes.y_lim[0])[0]))
        cv2.line(img, (column, top), (column, bottom), _GRID, 1)
    for y in axes.y_ticks:
        row = round(float(axes.to_pixel(axes.x_lim[0], y)[1]))
        cv2.line(img, (left, row), (right, row), _GRID, 1)


def draw_frame(img: Image, axes: Axes, title: str, xlabel: str, ylabel: str) -> None:
    """Axes box, tick marks, tick labels, axis labels and title around axes.box."""
    left, top, right, bottom = axes.box
    cv2.rectangle(img, (left, top), (right, bottom), BLACK, 1)
    tick_h = text_height(TICK_SCALE)
    for x, text in zip(axes.x_ticks, tick_labels(axes.x_ticks)):
        column = round(float(axes.to_pixel(x, axes.y_lim[0])[0]))
        cv2.line(img, (column, bottom), (column, bottom + TICK_LEN), BLACK, 1)
        put_text(img, text, column, bottom + TICK_LEN + GAP, TICK_SCALE, ha="center")
    y_label_w = 0
    for y, text in zip(axes.y_ticks, tick_labels(axes.y_ticks)):
        row = round(float(axes.to_pixel(axes.x_lim[0], y)[1]))
        cv2.line(img, (left - TICK_LEN, row), (left, row), BLACK, 1)
        put_text(img, text, left - TICK_LEN - GAP, row, TICK_SCALE, ha="right", va="center")
        y_label_w = max(y_label_w, text_size(text, TICK_SCALE)[0])
    if xlabel:
        put_text(img, xlabel, (left + right) / 2, bottom + TICK_LEN + GAP + tick_h + 2 * GAP, LABEL_SCALE, ha="center")
    if ylabel:
        label_h = text_height(LABEL_SCALE) + 4
        cx = left - TICK_LEN - GAP - y_label_w - 2 * GAP - label_h / 2
        put_text_vertical(img, ylabel, cx, (top + bottom) / 2, LABEL_SCALE)
    if title:
        put_text(img, title, (left + right) / 2, PAD, TITLE_SCALE, ha="center")


def draw_data_clipped(img: Image, axes: Axes, draw: Callable[[Image], None]) -> NDArray[np.bool_]:
    """Run ``draw(layer)`` on a copy, keep what falls inside axes.box; returns that mask."""
    left, top, right, bottom = axes.box
    layer = img.copy()
    draw(layer)
    occupied = np.zeros(img.shape[:2], dtype=bool)
    region = (slice(top, bottom + 1), slice(left, right + 1))
    occupied[region] = np.any(layer[region] != img[region], axis=-1)
    img[region] = layer[region]
    return occupied


def _corners(limits: Sequence[tuple[float, float]]) -> NDArray[np.float64]:
    return np.array([[x, y, z] for x in limits[0] for y in limits[1] for z in limits[2]])


def fit_view(
    limits: Limits3, right: NDArray[np.float64], up: NDArray[np.float64], area: tuple[float, float, float, float]
) -> View3D:
    """Scale and centre the projected box into area (left, top, right, bottom)."""
    center = np.array([(a + b) / 2 for a, b in limits])
    screen = (_corners(limits) - center) @ np.stack([right, up]).T
    span = np.maximum(screen.max(axis=0) - screen.min(axis=0), 1e-12)
    left, top, right_px, bottom = area
    scale = min((right_px - left) / span[0], (bottom - top) / span[1])
    mid = (screen.max(axis=0) + screen.min(axis=0)) / 2
    center_px = ((left + right_px) / 2 - scale * mid[0], (top + bottom) / 2 + scale * mid[1])
    return View3D(right, up, center, center_px, float(scale), limits)


@dataclass(frozen=True)
class _TickEdge:
    axis: int
    start: tuple[float, float, float]  # the edge at the low end of the axis
    end: tuple[float, float, float]


def tick_edges(view: View3D) -> list[_TickEdge]:
    """The edges that carry ticks: x and y along the bottom front, z at the left."""
    (x0, x1), (y0, y1), (z0, _) = view.limits
    # The lower of two parallel bottom edges is the one lower on the image (larger row).
    y_edge = max((y0, y1), key=lambda y: view.to_pixel([(x0 + x1) / 2, y, z0])[1])
    x_edge = max((x0, x1), key=lambda x: view.to_pixel([x, (y0 + y1) / 2, z0])[1])
    corner = min(((x, y) for x in (x0, x1) for y in (y0, y1)), key=lambda c: view.to_pixel([c[0], c[1], z0])[0])
    z_lo, z_hi = view.limits[2]
    return [
        _TickEdge(0, (x0, y_edge, z0), (x1, y_edge, z0)),
        _TickEdge(1, (x_edge, y0, z0), (x_edge, y1, z0)),
        _TickEdge(2, (corner[0], corner[1], z_lo), (corner[0], corner[1], z_hi)),
    ]


def _edge_geometry(view: View3D, edge: _TickEdge) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Projected start, unit outward normal (away from the box centre) and pixel length."""
    a, b = view.to_pixel(np.array(edge.start)), view.to_pixel(np.array(edge.end))
    along = b - a
    length = float(np.hypot(*along))
    centre_px = view.to_pixel(view.center)
    away = (a + b) / 2 - centre_px
    if length > 1e-9:
        unit = along / length
        away = away - unit * float(away @ unit)
    norm = float(np.hypot(*away))
    outward = away / norm if norm > 1e-9 else np.array([0.0, 1.0])
    if edge.axis == 2:  # the z axis carries its labels horizontally to the left
        outward = np.array([-1.0 if outward[0] <= 0 else 1.0, 0.0])
    return a, outward, length


def axis_ticks(view: View3D, edges: Sequence[_TickEdge]) -> list[NDArray[np.float64]]:
    ticks = []
    for edge in edges:
        _, _, length = _edge_geometry(view, edge)
        if length < _MIN_TICK_EDGE:
            ticks.append(np.empty(0))
            continue
        lo, hi = view.limits[edge.axis]
        ticks.append(ticks_within(lo, hi, max_ticks=int(np.clip(length // 36, 2, 7))))
    return ticks


def draw_box_3d(
    img: Image, view: View3D, edges: Sequence[_TickEdge], ticks: Sequence[NDArray[np.float64]], axis_labels: Sequence[str]
) -> None:
    limits = view.limits
    toward = view.toward_viewer
    back = [limits[i][0] if toward[i] >= 0 else limits[i][1] for i in range(3)]

    def segment(p: Sequence[float], q: Sequence[float], color: BGR) -> None:
        draw_polyline(img, view.to_pixel(np.array([p, q], dtype=float)), color, 1)

    # Grid on the three back faces, then their edges.
    for face in range(3):
        others = [i for i in range(3) if i != face]
        for k, j in (others, others[::-1]):
            for t in ticks[k]:
                p, q = [0.0] * 3, [0.0] * 3
                p[face] = q[face] = back[face]
                p[k] = q[k] = float(t)
                p[j], q[j] = limits[j]
                segment(p, q, _GRID)
    for face in range(3):
        others = [i for i in range(3) if i != face]
        for k, j in (others, others[::-1]):
            for value in limits[k]:
                p, q = [0.0] * 3, [0.0] * 3
                p[face] = q[face] = back[face]
                p[k] = q[k] = value
                p[j], q[j] = limits[j]
                segment(p, q, _BACK_EDGE)
    # Tick edges: ticks, tick labels, axis label.
    for edge, axis_ticks, label in zip(edges, ticks, axis_labels):
        start, outward, length = _edge_geometry(view, edge)
        segment(edge.start, edge.end, BLACK)
        if length < _MIN_TICK_EDGE:
            continue
        reach = 0.0
        for t, text in zip(axis_ticks, tick_labels(axis_ticks)):
            point = np.array(edge.start, dtype=float)
            point[edge.axis] = t
            tick_px = view.to_pixel(point)
            cv2.line(img, tuple(fixed(tick_px)), tuple(fixed(tick_px + outward * TICK_LEN)), BLACK, 1, cv2.LINE_AA, SHIFT)
            w, h = put_text_beside(img, text, tick_px, outward, TICK_LEN + GAP, TICK_SCALE)
            reach = max(reach, abs(outward[0]) * w + abs(outward[1]) * h)
        middle = view.to_pixel((np.array(edge.start) + np.array(edge.end)) / 2)
        gap = TICK_LEN + GAP + reach + 2 * GAP
        if edge.axis == 2:
            label_h = text_height(LABEL_SCALE) + 4
            position = middle + outward * (gap + label_h / 2)
            put_text_vertical(img, label, position[0], position[1], LABEL_SCALE)
        else:
            put_text_beside(img, label, middle, outward, gap, LABEL_SCALE)
