"""Report figures drawn with OpenCV: line plots, image-plane trajectories, 3-D paths.

Small, dependency-free (numpy + cv2) plotting for figures like the thesis's Figs. 5-1 ..
5-8. Every function is pure: it takes data and returns a new uint8 BGR image on a white
background; nothing here knows about robots.

Conventions:

* Colors are BGR tuples, as everywhere in OpenCV. A series without a color takes
  ``PALETTE[i % len(PALETTE)]`` where i is its index in the sequence passed to the plot.
* NaN (or inf) in a series splits its line into pieces; nothing is drawn across the gap.
* Pixel coordinates are OpenCV's: (column, row), with integer values at pixel centres.
  The ``*_with_axes`` / ``*_with_view`` variants also return the data-to-pixel mapping
  the figure was drawn with, so callers and tests can locate data on the image.
* Text is drawn with ``cv2.FONT_HERSHEY_SIMPLEX``, which only has printable ASCII.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

Image = NDArray[np.uint8]
BGR = tuple[int, int, int]
Limits3 = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]

# Matplotlib's "tab10" colors (less its gray, which would read as an axis), in BGR.
PALETTE: tuple[BGR, ...] = (
    (180, 119, 31),  # blue
    (14, 127, 255),  # orange
    (44, 160, 44),  # green
    (40, 39, 214),  # red
    (189, 103, 148),  # purple
    (75, 86, 140),  # brown
    (194, 119, 227),  # pink
    (34, 189, 188),  # olive
    (207, 190, 23),  # cyan
)

WHITE: BGR = (255, 255, 255)
BLACK: BGR = (0, 0, 0)
_GRID: BGR = (228, 228, 228)
_BACK_EDGE: BGR = (150, 150, 150)
_OUTSIDE_IMAGE: BGR = (243, 243, 243)
_IMAGE_FRAME: BGR = (70, 70, 70)
_LEGEND_BORDER: BGR = (170, 170, 170)
_INITIAL_COLOR: BGR = BLACK
_DESIRED_COLOR: BGR = (40, 39, 214)

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_TICK_SCALE = 0.4
_LABEL_SCALE = 0.48
_TITLE_SCALE = 0.55
_LEGEND_SCALE = 0.42
_CAPTION_SCALE = 0.55

_PAD = 8  # figure edge to the outermost text
_GAP = 5  # between a tick mark and its label, a label and the next item
_TICK_LEN = 5
_LINE_THICKNESS = 2
_MARKER_RADIUS = 5
_MARGIN = 0.04  # autoscale margin, a fraction of the data range on each side
_SHIFT = 4  # fractional bits for cv2 drawing: positions to 1/16 px
_LEGEND_SAMPLE = 26  # length of the line sample in a legend row
_MIN_TICK_EDGE = 60  # px: a 3-D axis seen shorter than this gets no ticks or label
_MARKERS = ("o", "*", "x", "+", "s", ".")


def default_color(index: int) -> BGR:
    """The palette color for the series at ``index``, cycling."""
    return PALETTE[index % len(PALETTE)]


def _check_color(color: object) -> BGR | None:
    if color is None:
        return None
    values = tuple(int(c) for c in color)  # type: ignore[union-attr]
    if len(values) != 3 or any(not 0 <= c <= 255 for c in values):
        raise ValueError(f"color must be a BGR triple of 0..255, got {color!r}")
    return values  # type: ignore[return-value]


@dataclass(frozen=True, eq=False)
class Series:
    """A 2-D line: x and y of equal length T; NaN in either splits the line."""

    label: str
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    color: BGR | None = None

    def __post_init__(self) -> None:
        x, y = np.atleast_1d(np.asarray(self.x, dtype=float)), np.atleast_1d(np.asarray(self.y, dtype=float))
        if x.ndim != 1 or y.ndim != 1 or x.shape != y.shape:
            raise ValueError(f"series {self.label!r}: x and y must be 1-D of equal length, got {x.shape} and {y.shape}")
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", y)
        object.__setattr__(self, "color", _check_color(self.color))


@dataclass(frozen=True, eq=False)
class Series3:
    """A 3-D polyline: xyz of shape (T, 3); a row with NaN splits the line."""

    label: str
    xyz: NDArray[np.float64]
    color: BGR | None = None

    def __post_init__(self) -> None:
        xyz = np.atleast_2d(np.asarray(self.xyz, dtype=float))
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"path {self.label!r}: xyz must have shape (T, 3), got {np.shape(self.xyz)}")
        object.__setattr__(self, "xyz", xyz)
        object.__setattr__(self, "color", _check_color(self.color))


def _colors(items: Sequence[Series] | Sequence[Series3]) -> list[BGR]:
    return [item.color if item.color is not None else default_color(i) for i, item in enumerate(items)]


# --------------------------------------------------------------------------- ticks


def _finite_range(lo: float, hi: float) -> tuple[float, float]:
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
    lo, hi = _finite_range(lo, hi)
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


def _ticks_within(lo: float, hi: float, max_ticks: int) -> NDArray[np.float64]:
    """The finest nice ticks inside [lo, hi] that number at most max_ticks."""
    tolerance = 1e-9 * (hi - lo)
    for intervals in range(max_ticks + 1, 1, -1):
        ticks = nice_ticks(lo, hi, intervals)
        inside = ticks[(ticks >= lo - tolerance) & (ticks <= hi + tolerance)]
        if len(inside) <= max_ticks:
            return inside
    return inside


def _padded_limits(values: NDArray[np.float64], margin: float = _MARGIN) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = _finite_range(float(finite.min()), float(finite.max()))
    pad = margin * (hi - lo)
    return lo - pad, hi + pad


# --------------------------------------------------------------------------- mapping


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


def _view_basis(azimuth_deg: float, elevation_deg: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    right = np.array([math.cos(az), math.sin(az), 0.0])
    up = np.array([-math.sin(el) * math.sin(az), math.sin(el) * math.cos(az), math.cos(el)])
    return right, up


# --------------------------------------------------------------------------- drawing primitives


def _blank(width: int, height: int) -> Image:
    return np.full((height, width, 3), 255, dtype=np.uint8)


def _check_size(size: tuple[int, int]) -> tuple[int, int]:
    width, height = (int(v) for v in size)
    if width < 120 or height < 100:
        raise ValueError(f"figure size must be at least 120 x 100 px, got {size}")
    return width, height


def _text_size(text: str, scale: float, thickness: int = 1) -> tuple[int, int, int]:
    (width, height), baseline = cv2.getTextSize(text, _FONT, scale, thickness)
    return width, height, baseline


def _put_text(
    img: Image,
    text: str,
    x: float,
    y: float,
    scale: float,
    color: BGR = BLACK,
    ha: str = "left",
    va: str = "top",
    thickness: int = 1,
) -> None:
    """Text anchored at (x, y): ha in left/center/right, va in top/center/bottom (of the caps)."""
    width, height, _ = _text_size(text, scale, thickness)
    left = {"left": x, "center": x - width / 2, "right": x - width}[ha]
    baseline_y = {"top": y + height, "center": y + height / 2, "bottom": y}[va]
    cv2.putText(img, text, (round(left), round(baseline_y)), _FONT, scale, color, thickness, cv2.LINE_AA)


def _put_text_vertical(img: Image, text: str, cx: float, cy: float, scale: float, color: BGR = BLACK) -> None:
    """Text rotated 90 degrees counter-clockwise (reading upward), centred on (cx, cy)."""
    width, height, baseline = _text_size(text, scale)
    patch = _blank(width + 4, height + baseline + 4)
    cv2.putText(patch, text, (2, height + 2), _FONT, scale, color, 1, cv2.LINE_AA)
    patch = cv2.rotate(patch, cv2.ROTATE_90_COUNTERCLOCKWISE)
    _paste_darker(img, patch, round(cx - patch.shape[1] / 2), round(cy - (width + 4) / 2))


def _paste_darker(img: Image, patch: Image, x0: int, y0: int) -> None:
    """Darken img with patch at (x0, y0), clipped to img: dark text on white shows through."""
    h, w = patch.shape[:2]
    top, left = max(y0, 0), max(x0, 0)
    bottom, right = min(y0 + h, img.shape[0]), min(x0 + w, img.shape[1])
    if bottom <= top or right <= left:
        return
    region = img[top:bottom, left:right]
    np.minimum(region, patch[top - y0 : bottom - y0, left - x0 : right - x0], out=region)


def _put_text_beside(
    img: Image, text: str, point: NDArray[np.float64], direction: NDArray[np.float64], gap: float, scale: float
) -> tuple[float, float]:
    """Text on the side of ``point`` that ``direction`` (unit, pixels) points to; returns its size."""
    width, height, _ = _text_size(text, scale)
    reach = (abs(direction[0]) * width + abs(direction[1]) * height) / 2
    centre = point + direction * (gap + reach)
    _put_text(img, text, centre[0], centre[1], scale, ha="center", va="center")
    return width, height


def _fixed(points: NDArray[np.float64]) -> NDArray[np.int32]:
    return np.round(np.asarray(points) * (1 << _SHIFT)).astype(np.int32)


def _clip_polyline(points: NDArray[np.float64], lo: tuple[float, float], hi: tuple[float, float]) -> list[NDArray[np.float64]]:
    """The pieces of a polyline inside the rectangle [lo, hi] (Liang-Barsky on each segment)."""
    inside = np.all((points >= lo) & (points <= hi), axis=1)
    if inside.all():
        return [points]
    if len(points) == 1:
        return []
    a, d = points[:-1], np.diff(points, axis=0)
    t0, t1 = np.zeros(len(a)), np.ones(len(a))
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in (0, 1):
            for bound, sign in ((lo[axis], -1.0), (hi[axis], 1.0)):
                p = sign * d[:, axis]
                q = sign * (bound - a[:, axis])
                r = q / p
                t0 = np.where(p < 0, np.maximum(t0, r), t0)
                t1 = np.where(p > 0, np.minimum(t1, r), t1)
                t1 = np.where((p == 0) & (q < 0), -1.0, t1)
    visible = t0 <= t1
    starts, ends = a + t0[:, None] * d, a + t1[:, None] * d
    pieces: list[NDArray[np.float64]] = []
    current: list[NDArray[np.float64]] = []
    for i in np.flatnonzero(visible):
        if current and not (t0[i] == 0.0 and t1[i - 1] == 1.0 and visible[i - 1]):
            pieces.append(np.array(current))
            current = []
        if not current:
            current.append(starts[i])
        current.append(ends[i])
    if current:
        pieces.append(np.array(current))
    return pieces


def _finite_runs(points: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Maximal runs of consecutive rows with all values finite."""
    finite = np.all(np.isfinite(points), axis=1)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], finite.astype(np.int8), [0]])))
    return [points[start:stop] for start, stop in zip(edges[::2], edges[1::2])]


def _draw_polyline(img: Image, points_px: NDArray[np.float64], color: BGR, thickness: int = _LINE_THICKNESS) -> None:
    """A polyline in pixels, split at NaN, clipped to (a little beyond) the image."""
    height, width = img.shape[:2]
    margin = 4.0 * thickness
    lo, hi = (-margin, -margin), (width - 1 + margin, height - 1 + margin)
    for run in _finite_runs(np.asarray(points_px, dtype=float).reshape(-1, 2)):
        for piece in _clip_polyline(run, lo, hi):
            if len(piece) == 1:
                cv2.circle(img, tuple(_fixed(piece[0])), (thickness << _SHIFT) // 2 + 8, color, -1, cv2.LINE_AA, _SHIFT)
            else:
                cv2.polylines(img, [_fixed(piece)], False, color, thickness, cv2.LINE_AA, _SHIFT)


def _draw_marker(img: Image, center: NDArray[np.float64], kind: str, color: BGR, radius: int = _MARKER_RADIUS) -> None:
    """One marker: 'o' circle, '*' asterisk, 'x' cross, '+' plus, 's' square, '.' dot."""
    if kind not in _MARKERS:
        raise ValueError(f"unknown marker {kind!r}; use one of {_MARKERS}")
    height, width = img.shape[:2]
    cx, cy = float(center[0]), float(center[1])
    if not (math.isfinite(cx) and math.isfinite(cy)):
        return
    if not (-2 * radius <= cx <= width + 2 * radius and -2 * radius <= cy <= height + 2 * radius):
        return
    c = np.array([cx, cy])

    def segment(dx: float, dy: float) -> None:
        cv2.line(
            img, tuple(_fixed(c - (dx, dy))), tuple(_fixed(c + (dx, dy))), color, 2 if kind != "*" else 1, cv2.LINE_AA, _SHIFT
        )

    r = float(radius)
    if kind == "o":
        cv2.circle(img, tuple(_fixed(c)), radius << _SHIFT, color, 1, cv2.LINE_AA, _SHIFT)
    elif kind == ".":
        cv2.circle(img, tuple(_fixed(c)), (radius << _SHIFT) // 2, color, -1, cv2.LINE_AA, _SHIFT)
    elif kind == "s":
        corner = _fixed(np.array([[cx - r, cy - r], [cx + r, cy - r], [cx + r, cy + r], [cx - r, cy + r]]))
        cv2.polylines(img, [corner], True, color, 2, cv2.LINE_AA, _SHIFT)
    else:
        diagonal = r / math.sqrt(2.0)
        if kind in ("+", "*"):
            segment(r + 1, 0.0)
            segment(0.0, r + 1)
        if kind in ("x", "*"):
            segment(diagonal + 1, diagonal + 1)
            segment(diagonal + 1, -(diagonal + 1))


# --------------------------------------------------------------------------- legend


@dataclass(frozen=True)
class _Entry:
    label: str
    color: BGR
    kind: str  # "line" or a marker


def _legend_size(entries: Sequence[_Entry]) -> tuple[int, int, int]:
    """(width, height, row height) of a legend box for the entries."""
    text = [_text_size(e.label, _LEGEND_SCALE) for e in entries]
    row = max(max(h + b for _, h, b in text), 2 * _MARKER_RADIUS + 2) + 6
    width = 8 + _LEGEND_SAMPLE + 8 + max(w for w, _, _ in text) + 8
    return width, len(entries) * row + 8, row


def _draw_legend(img: Image, entries: Sequence[_Entry], left: int, top: int) -> tuple[int, int, int, int]:
    width, height, row = _legend_size(entries)
    cv2.rectangle(img, (left, top), (left + width, top + height), WHITE, -1)
    cv2.rectangle(img, (left, top), (left + width, top + height), _LEGEND_BORDER, 1, cv2.LINE_AA)
    for i, entry in enumerate(entries):
        cy = top + 4 + i * row + row / 2
        x0 = left + 8
        if entry.kind == "line":
            _draw_polyline(img, np.array([[x0, cy], [x0 + _LEGEND_SAMPLE, cy]]), entry.color)
        else:
            _draw_marker(img, np.array([x0 + _LEGEND_SAMPLE / 2, cy]), entry.kind, entry.color)
        _put_text(img, entry.label, x0 + _LEGEND_SAMPLE + 8, cy, _LEGEND_SCALE, va="center")
    return left, top, left + width, top + height


def _place_legend(
    img: Image, entries: Sequence[_Entry], area: tuple[int, int, int, int], occupied: NDArray[np.bool_]
) -> tuple[int, int, int, int] | None:
    """Draw the legend in the spot of ``area`` that covers the fewest ``occupied`` pixels."""
    entries = [e for e in entries if e.label]
    if not entries:
        return None
    width, height, _ = _legend_size(entries)
    left, top, right, bottom = area
    inset = 8
    xs = {"l": left + inset, "c": (left + right - width) // 2, "r": right - inset - width}
    ys = {"t": top + inset, "c": (top + bottom - height) // 2, "b": bottom - inset - height}
    # Preference order on ties: matplotlib's, upper right first.
    candidates = ["tr", "tl", "br", "bl", "tc", "bc", "cr", "cl"]
    best, best_cost = None, None
    for name in candidates:
        x, y = xs[name[1]], ys[name[0]]
        x, y = max(x, 0), max(y, 0)
        cost = int(occupied[y : y + height + 1, x : x + width + 1].sum())
        if best_cost is None or cost < best_cost:
            best, best_cost = (x, y), cost
    assert best is not None
    return _draw_legend(img, entries, *best)


# --------------------------------------------------------------------------- 2-D axes


def _text_height(scale: float) -> int:
    return _text_size("0", scale)[1]


def _axes_box(
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
    tick_h = _text_height(_TICK_SCALE)
    label_h = _text_height(_LABEL_SCALE) + 4
    title_h = _text_height(_TITLE_SCALE) + 4
    y_label_w = max((_text_size(t, _TICK_SCALE)[0] for t in y_labels), default=0)
    last_x_w = _text_size(x_labels[-1], _TICK_SCALE)[0] if x_labels else 0
    left = _PAD + (label_h + 2 * _GAP if ylabel else 0) + y_label_w + _GAP + _TICK_LEN
    top = _PAD + (title_h + 2 * _GAP if title else tick_h // 2 + 2)
    right = width - 1 - max(_PAD + 4, last_x_w // 2 + _PAD)
    bottom = height - 1 - (_PAD + _TICK_LEN + _GAP + tick_h + (2 * _GAP + label_h if xlabel else 0))
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


def _draw_grid(img: Image, axes: Axes) -> None:
    left, top, right, bottom = axes.box
    for x in axes.x_ticks:
        column = round(float(axes.to_pixel(x, axes.y_lim[0])[0]))
        cv2.line(img, (column, top), (column, bottom), _GRID, 1)
    for y in axes.y_ticks:
        row = round(float(axes.to_pixel(axes.x_lim[0], y)[1]))
        cv2.line(img, (left, row), (right, row), _GRID, 1)


def _draw_frame(img: Image, axes: Axes, title: str, xlabel: str, ylabel: str) -> None:
    """Axes box, tick marks, tick labels, axis labels and title around axes.box."""
    left, top, right, bottom = axes.box
    cv2.rectangle(img, (left, top), (right, bottom), BLACK, 1)
    tick_h = _text_height(_TICK_SCALE)
    for x, text in zip(axes.x_ticks, tick_labels(axes.x_ticks)):
        column = round(float(axes.to_pixel(x, axes.y_lim[0])[0]))
        cv2.line(img, (column, bottom), (column, bottom + _TICK_LEN), BLACK, 1)
        _put_text(img, text, column, bottom + _TICK_LEN + _GAP, _TICK_SCALE, ha="center")
    y_label_w = 0
    for y, text in zip(axes.y_ticks, tick_labels(axes.y_ticks)):
        row = round(float(axes.to_pixel(axes.x_lim[0], y)[1]))
        cv2.line(img, (left - _TICK_LEN, row), (left, row), BLACK, 1)
        _put_text(img, text, left - _TICK_LEN - _GAP, row, _TICK_SCALE, ha="right", va="center")
        y_label_w = max(y_label_w, _text_size(text, _TICK_SCALE)[0])
    if xlabel:
        _put_text(img, xlabel, (left + right) / 2, bottom + _TICK_LEN + _GAP + tick_h + 2 * _GAP, _LABEL_SCALE, ha="center")
    if ylabel:
        label_h = _text_height(_LABEL_SCALE) + 4
        cx = left - _TICK_LEN - _GAP - y_label_w - 2 * _GAP - label_h / 2
        _put_text_vertical(img, ylabel, cx, (top + bottom) / 2, _LABEL_SCALE)
    if title:
        _put_text(img, title, (left + right) / 2, _PAD, _TITLE_SCALE, ha="center")


def _draw_data_clipped(img: Image, axes: Axes, draw: Callable[[Image], None]) -> NDArray[np.bool_]:
    """Run ``draw(layer)`` on a copy, keep what falls inside axes.box; returns that mask."""
    left, top, right, bottom = axes.box
    layer = img.copy()
    draw(layer)
    occupied = np.zeros(img.shape[:2], dtype=bool)
    region = (slice(top, bottom + 1), slice(left, right + 1))
    occupied[region] = np.any(layer[region] != img[region], axis=-1)
    img[region] = layer[region]
    return occupied


def _limits(given: tuple[float, float] | None, data: NDArray[np.float64]) -> tuple[float, float]:
    if given is not None:
        return _finite_range(*given)
    return _padded_limits(data)


def line_plot_with_axes(
    series: Sequence[Series],
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    size: tuple[int, int] = (640, 400),
    *,
    xlim: tuple[float, float] | None = None,
    ylim: tuple[float, float] | None = None,
) -> tuple[Image, Axes]:
    """``line_plot`` that also returns the Axes mapping data to pixels."""
    width, height = _check_size(size)
    series = list(series)
    colors = _colors(series)
    if series:
        finite = [np.isfinite(s.x) & np.isfinite(s.y) for s in series]
        xs = np.concatenate([s.x[f] for s, f in zip(series, finite)])
        ys = np.concatenate([s.y[f] for s, f in zip(series, finite)])
    else:
        xs = ys = np.empty(0)
    x_lim, y_lim = _limits(xlim, xs), _limits(ylim, ys)
    x_ticks = _ticks_within(*x_lim, max_ticks=int(np.clip(width // 90, 2, 10)))
    y_ticks = _ticks_within(*y_lim, max_ticks=int(np.clip(height // 55, 2, 10)))
    box = _axes_box((width, height), title, xlabel, ylabel, tick_labels(x_ticks), tick_labels(y_ticks))
    axes = Axes(x_lim, y_lim, box, False, tuple(map(float, x_ticks)), tuple(map(float, y_ticks)))

    img = _blank(width, height)
    _draw_grid(img, axes)

    def draw(layer: Image) -> None:
        for s, color in zip(series, colors):
            _draw_polyline(layer, axes.to_pixel(s.x, s.y), color)

    occupied = _draw_data_clipped(img, axes, draw)
    _draw_frame(img, axes, title, xlabel, ylabel)
    legend = _place_legend(img, [_Entry(s.label, c, "line") for s, c in zip(series, colors)], box, occupied)
    return img, replace(axes, legend_box=legend)


def line_plot(*args: Any, **kwargs: Any) -> Image:
    """Lines y(x) in a box with ticks, a light grid, title, axis labels and a legend.

    Limits fit the finite data with a small margin unless ``xlim``/``ylim`` are given.
    The legend lists the series with a non-empty label, in the corner that hides the
    least data. ``size`` is (width, height) in pixels.
    """
    return line_plot_with_axes(*args, **kwargs)[0]


def _as_points(points: ArrayLike | None, name: str) -> NDArray[np.float64]:
    if points is None:
        return np.empty((0, 2))
    array = np.atleast_2d(np.asarray(points, dtype=float))
    if array.size == 0:
        return np.empty((0, 2))
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"{name} must have shape (K, 2), got {np.shape(points)}")
    return array


def image_trajectory_plot_with_axes(
    trajectories: Sequence[Series],
    image_size: tuple[int, int] = (640, 480),
    title: str = "",
    initial_marker_points: ArrayLike | None = None,
    desired_points: ArrayLike | None = None,
    extra_points: Sequence[tuple[str, ArrayLike, BGR] | tuple[str, ArrayLike, BGR, str]] = (),
    *,
    margin: float = 0.25,
    size: tuple[int, int] = (640, 540),
    xlabel: str = "u (pixel)",
    ylabel: str = "v (pixel)",
    initial_label: str = "initial",
    desired_label: str = "desired",
) -> tuple[Image, Axes]:
    """``image_trajectory_plot`` that also returns the Axes (``y_down=True``)."""
    width, height = _check_size(size)
    image_w, image_h = (float(v) for v in image_size)
    if image_w <= 0 or image_h <= 0:
        raise ValueError(f"image_size must be positive, got {image_size}")
    initial = _as_points(initial_marker_points, "initial_marker_points")
    desired = _as_points(desired_points, "desired_points")
    extras = []
    for item in extra_points:
        label, points, color = item[:3]
        kind = item[3] if len(item) > 3 else "s"
        extras.append((str(label), _as_points(points, f"extra points {label!r}"), _check_color(color), kind))
    trajectories = list(trajectories)
    colors = _colors(trajectories)

    x_lim = (-margin * image_w, (1 + margin) * image_w)
    y_lim = (-margin * image_h, (1 + margin) * image_h)
    x_ticks = _ticks_within(*x_lim, max_ticks=int(np.clip(width // 100, 2, 10)))
    y_ticks = _ticks_within(*y_lim, max_ticks=int(np.clip(height // 60, 2, 10)))
    aspect = (x_lim[1] - x_lim[0]) / (y_lim[1] - y_lim[0])
    box = _axes_box((width, height), title, xlabel, ylabel, tick_labels(x_ticks), tick_labels(y_ticks), aspect)
    axes = Axes(x_lim, y_lim, box, True, tuple(map(float, x_ticks)), tuple(map(float, y_ticks)))

    img = _blank(width, height)
    left, top, right, bottom = box
    frame = np.round(axes.to_pixel([0.0, image_w], [0.0, image_h])).astype(int)
    cv2.rectangle(img, (left, top), (right, bottom), _OUTSIDE_IMAGE, -1)
    cv2.rectangle(img, tuple(frame[0]), tuple(frame[1]), WHITE, -1)
    _draw_grid(img, axes)
    cv2.rectangle(img, tuple(frame[0]), tuple(frame[1]), _IMAGE_FRAME, 2)

    def draw(layer: Image) -> None:
        for s, color in zip(trajectories, colors):
            _draw_polyline(layer, axes.to_pixel(s.x, s.y), color)
        for label, points, color, kind in extras:
            for p in axes.to_pixel(points[:, 0], points[:, 1]):
                _draw_marker(layer, p, kind, color)
        for p in axes.to_pixel(initial[:, 0], initial[:, 1]):
            _draw_marker(layer, p, "o", _INITIAL_COLOR)
        for p in axes.to_pixel(desired[:, 0], desired[:, 1]):
            _draw_marker(layer, p, "*", _DESIRED_COLOR, radius=_MARKER_RADIUS + 1)

    occupied = _draw_data_clipped(img, axes, draw)
    _draw_frame(img, axes, title, xlabel, ylabel)
    entries = [_Entry(s.label, c, "line") for s, c in zip(trajectories, colors)]
    if len(initial):
        entries.append(_Entry(initial_label, _INITIAL_COLOR, "o"))
    if len(desired):
        entries.append(_Entry(desired_label, _DESIRED_COLOR, "*"))
    entries += [_Entry(label, color, kind) for label, points, color, kind in extras if len(points)]
    legend = _place_legend(img, entries, box, occupied)
    return img, replace(axes, legend_box=legend)


def image_trajectory_plot(*args: Any, **kwargs: Any) -> Image:
    """Feature trajectories on the image plane, drawn as a camera image: u right, v down.

    trajectories: Series with x = u and y = v in pixels. The view covers the image
    [0, W] x [0, H] (its border drawn) plus ``margin`` of its size on each side, shaded,
    so points that leave the image stay visible; beyond that they are clipped. Initial
    points are drawn as 'o', desired points as '*'; ``extra_points`` are
    ``(label, (K, 2) points, color)`` with an optional 4th marker ('o', '*', 'x', '+',
    's' or '.', default 's'). Equal scale on u and v.
    """
    return image_trajectory_plot_with_axes(*args, **kwargs)[0]


def _box_limits(paths: Sequence[Series3]) -> Limits3:
    """Per-axis limits around the finite data at equal scale: thin axes get a minimum width."""
    points = np.concatenate([p.xyz for p in paths]) if paths else np.empty((0, 3))
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) == 0:
        return ((0.0, 1.0), (0.0, 1.0), (0.0, 1.0))
    lo, hi = points.min(axis=0), points.max(axis=0)
    extent = float((hi - lo).max())
    if extent <= 1e-12 * float(np.abs(points).max()):
        extent = 0.2 * float(np.abs(points).max()) or 1.0
    limits = []
    for a, b in zip(lo, hi):
        centre, half = (a + b) / 2, max((b - a) / 2, 0.1 * extent)
        pad = _MARGIN * extent
        limits.append((float(centre - half - pad), float(centre + half + pad)))
    return limits[0], limits[1], limits[2]


def _corners(limits: Sequence[tuple[float, float]]) -> NDArray[np.float64]:
    return np.array([[x, y, z] for x in limits[0] for y in limits[1] for z in limits[2]])


def _fit_view(
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


def _tick_edges(view: View3D) -> list[_TickEdge]:
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


def _axis_ticks(view: View3D, edges: Sequence[_TickEdge]) -> list[NDArray[np.float64]]:
    ticks = []
    for edge in edges:
        _, _, length = _edge_geometry(view, edge)
        if length < _MIN_TICK_EDGE:
            ticks.append(np.empty(0))
            continue
        lo, hi = view.limits[edge.axis]
        ticks.append(_ticks_within(lo, hi, max_ticks=int(np.clip(length // 36, 2, 7))))
    return ticks


def _draw_box_3d(
    img: Image, view: View3D, edges: Sequence[_TickEdge], ticks: Sequence[NDArray[np.float64]], axis_labels: Sequence[str]
) -> None:
    limits = view.limits
    toward = view.toward_viewer
    back = [limits[i][0] if toward[i] >= 0 else limits[i][1] for i in range(3)]

    def segment(p: Sequence[float], q: Sequence[float], color: BGR) -> None:
        _draw_polyline(img, view.to_pixel(np.array([p, q], dtype=float)), color, 1)

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
            p = view.to_pixel(point)
            cv2.line(img, tuple(_fixed(p)), tuple(_fixed(p + outward * _TICK_LEN)), BLACK, 1, cv2.LINE_AA, _SHIFT)
            w, h = _put_text_beside(img, text, p, outward, _TICK_LEN + _GAP, _TICK_SCALE)
            reach = max(reach, abs(outward[0]) * w + abs(outward[1]) * h)
        middle = view.to_pixel((np.array(edge.start) + np.array(edge.end)) / 2)
        gap = _TICK_LEN + _GAP + reach + 2 * _GAP
        if edge.axis == 2:
            label_h = _text_height(_LABEL_SCALE) + 4
            position = middle + outward * (gap + label_h / 2)
            _put_text_vertical(img, label, position[0], position[1], _LABEL_SCALE)
        else:
            _put_text_beside(img, label, middle, outward, gap, _LABEL_SCALE)


def path_3d_plot_with_view(
    paths: Sequence[Series3],
    title: str = "",
    azimuth_deg: float = -37.5,
    elevation_deg: float = 30.0,
    size: tuple[int, int] = (640, 480),
    axis_labels: tuple[str, str, str] = ("X (m)", "Y (m)", "Z (m)"),
) -> tuple[Image, View3D]:
    """``path_3d_plot`` that also returns the View3D projection it used."""
    width, height = _check_size(size)
    if not -90.0 < elevation_deg < 90.0:
        raise ValueError(f"elevation_deg must be in (-90, 90), got {elevation_deg}")
    paths = list(paths)
    colors = _colors(paths)
    limits = _box_limits(paths)
    right, up = _view_basis(azimuth_deg, elevation_deg)
    title_h = (_text_height(_TITLE_SCALE) + 4 + 2 * _GAP) if title else 0
    label_room = _TICK_LEN + _GAP + 2 * _GAP + _text_height(_LABEL_SCALE) + 4 + _PAD

    # Two passes: tick counts need the scale, the margins need the tick label widths.
    view = _fit_view(limits, right, up, (70, _PAD + title_h + 10, width - 70, height - 70))
    edges = _tick_edges(view)
    ticks = _axis_ticks(view, edges)
    label_w = max((_text_size(t, _TICK_SCALE)[0] for axis in ticks for t in tick_labels(axis)), default=20)
    tick_h = _text_height(_TICK_SCALE)
    side = label_room + label_w
    area = (side, _PAD + title_h + tick_h, width - 1 - side * 0.8, height - 1 - (label_room + tick_h + 8))
    view = _fit_view(limits, right, up, area)
    edges = _tick_edges(view)

    img = _blank(width, height)
    _draw_box_3d(img, view, edges, ticks, axis_labels)
    for path, color in zip(paths, colors):
        _draw_polyline(img, view.to_pixel(path.xyz), color)
    for path, color in zip(paths, colors):
        finite = path.xyz[np.all(np.isfinite(path.xyz), axis=1)]
        if len(finite):
            _draw_marker(img, view.to_pixel(finite[0]), "o", color)
            _draw_marker(img, view.to_pixel(finite[-1]), "*", color, radius=_MARKER_RADIUS + 1)
    if title:
        _put_text(img, title, width / 2, _PAD, _TITLE_SCALE, ha="center")
    entries = [_Entry(p.label, c, "line") for p, c in zip(paths, colors)]
    if any(p.label for p in paths):
        entries += [_Entry("start", BLACK, "o"), _Entry("end", BLACK, "*")]
    occupied = np.any(img != 255, axis=-1)
    _place_legend(img, entries, (0, title_h, width - 1, height - 1), occupied)
    return img, view


def path_3d_plot(*args: Any, **kwargs: Any) -> Image:
    """3-D polylines in an orthographic view with MATLAB's ``view(azimuth, elevation)``.

    The data's bounding box is drawn with a light grid on its three back faces and
    ticks on three edges (x and y along the bottom front, z on the left); one scale for
    all axes. Each path has an 'o' at its start and a '*' at its end. Z is up on the
    image for any elevation in (-90, 90).
    """
    return path_3d_plot_with_view(*args, **kwargs)[0]


def _as_bgr(panel: ArrayLike) -> Image:
    array = np.asarray(panel)
    if array.dtype != np.uint8:
        raise ValueError(f"panels must be uint8 images, got {array.dtype}")
    if array.ndim == 2:
        return cv2.cvtColor(array, cv2.COLOR_GRAY2BGR)
    if array.ndim == 3 and array.shape[2] == 3:
        return array
    raise ValueError(f"panels must be (H, W) or (H, W, 3) images, got shape {array.shape}")


def caption_strip(text: str, width: int) -> Image:
    """A white strip of the given width with ``text`` centred, shrunk to fit if needed."""
    scale = _CAPTION_SCALE
    while scale > 0.3 and _text_size(text, scale)[0] > width - 2 * _PAD:
        scale -= 0.05
    _, height, baseline = _text_size(text, scale)
    strip = _blank(width, height + baseline + 2 * _PAD)
    _put_text(strip, text, width / 2, _PAD, scale, ha="center")
    return strip


def grid(panels: Sequence[Image], columns: int, caption: str | None = None) -> Image:
    """Panels in rows of ``columns``, each centred in a cell the size of the largest.

    Without a caption the result is exactly (rows * cell height, columns * cell width);
    a caption adds one centred line below. Cells left over in the last row stay white.
    """
    images = [_as_bgr(p) for p in panels]
    if not images:
        raise ValueError("grid needs at least one panel")
    if columns < 1:
        raise ValueError(f"columns must be >= 1, got {columns}")
    columns = min(columns, len(images))
    rows = math.ceil(len(images) / columns)
    cell_h = max(p.shape[0] for p in images)
    cell_w = max(p.shape[1] for p in images)
    out = _blank(columns * cell_w, rows * cell_h)
    for i, panel in enumerate(images):
        row, column = divmod(i, columns)
        y0 = row * cell_h + (cell_h - panel.shape[0]) // 2
        x0 = column * cell_w + (cell_w - panel.shape[1]) // 2
        out[y0 : y0 + panel.shape[0], x0 : x0 + panel.shape[1]] = panel
    if caption:
        out = np.vstack([out, caption_strip(caption, out.shape[1])])
    return out


def write_png(path: str | Path, image: Image) -> Path:
    """Write image as PNG at path, creating parent directories; OSError names the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        ok = cv2.imwrite(str(path), np.ascontiguousarray(image))
    except cv2.error as error:
        raise OSError(f"could not write PNG {path}: {error}") from error
    if not ok:
        raise OSError(f"could not write PNG {path}")
    return path
