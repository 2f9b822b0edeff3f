"""Drawing primitives for the report's figures, on OpenCV: the figures' style (palette,
fonts, sizes), text, polylines, markers, legends, and panels put side by side.

Conventions:

* Colors are BGR tuples, as everywhere in OpenCV. A series without a color takes
  ``PALETTE[i % len(PALETTE)]`` where i is its index in the sequence passed to the plot.
* NaN (or inf) in a series splits its line into pieces; nothing is drawn across the gap.
* Pixel coordinates are OpenCV's: (column, row), with integer values at pixel centres.
* Text is drawn with ``cv2.FONT_HERSHEY_SIMPLEX``, which only has printable ASCII.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

Image = NDArray[np.uint8]
BGR = tuple[int, int, int]

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
_LEGEND_BORDER: BGR = (170, 170, 170)

_FONT = cv2.FONT_HERSHEY_SIMPLEX
TICK_SCALE = 0.4
LABEL_SCALE = 0.48
TITLE_SCALE = 0.55
_LEGEND_SCALE = 0.42
_CAPTION_SCALE = 0.55

PAD = 8  # figure edge to the outermost text
GAP = 5  # between a tick mark and its label, a label and the next item
TICK_LEN = 5
_LINE_THICKNESS = 2
MARKER_RADIUS = 5
SHIFT = 4  # fractional bits for cv2 drawing: positions to 1/16 px
_LEGEND_SAMPLE = 26  # length of the line sample in a legend row
_MARKERS = ("o", "*", "x", "+", "s", ".")


def default_color(index: int) -> BGR:
    """The palette color for the series at ``index``, cycling."""
    return PALETTE[index % len(PALETTE)]


def check_color(color: object) -> BGR:
    """``color`` as a BGR triple of 0..255; ValueError otherwise."""
    values = tuple(int(c) for c in color) if isinstance(color, Iterable) else ()
    if len(values) != 3 or any(not 0 <= c <= 255 for c in values):
        raise ValueError(f"color must be a BGR triple of 0..255, got {color!r}")
    return values[0], values[1], values[2]


def blank(width: int, height: int) -> Image:
    return np.full((height, width, 3), 255, dtype=np.uint8)


def check_size(size: tuple[int, int]) -> tuple[int, int]:
    width, height = (int(v) for v in size)
    if width < 120 or height < 100:
        raise ValueError(f"figure size must be at least 120 x 100 px, got {size}")
    return width, height


def text_size(text: str, scale: float, thickness: int = 1) -> tuple[int, int, int]:
    (width, height), baseline = cv2.getTextSize(text, _FONT, scale, thickness)
    return width, height, baseline


def put_text(
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
    width, height, _ = text_size(text, scale, thickness)
    left = {"left": x, "center": x - width / 2, "right": x - width}[ha]
    baseline_y = {"top": y + height, "center": y + height / 2, "bottom": y}[va]
    cv2.putText(img, text, (round(left), round(baseline_y)), _FONT, scale, color, thickness, cv2.LINE_AA)


def put_text_vertical(img: Image, text: str, cx: float, cy: float, scale: float, color: BGR = BLACK) -> None:
    """Text rotated 90 degrees counter-clockwise (reading upward), centred on (cx, cy)."""
    width, height, baseline = text_size(text, scale)
    patch = blank(width + 4, height + baseline + 4)
    cv2.putText(patch, text, (2, height + 2), _FONT, scale, color, 1, cv2.LINE_AA)
    rotated = cv2.rotate(patch, cv2.ROTATE_90_COUNTERCLOCKWISE)
    _paste_darker(img, rotated, round(cx - rotated.shape[1] / 2), round(cy - (width + 4) / 2))


def _paste_darker(img: Image, patch: np.ndarray, x0: int, y0: int) -> None:
    """Darken img with patch at (x0, y0), clipped to img: dark text on white shows through."""
    h, w = patch.shape[:2]
    top, left = max(y0, 0), max(x0, 0)
    bottom, right = min(y0 + h, img.shape[0]), min(x0 + w, img.shape[1])
    if bottom <= top or right <= left:
        return
    region = img[top:bottom, left:right]
    np.minimum(region, patch[top - y0 : bottom - y0, left - x0 : right - x0], out=region)


def put_text_beside(
    img: Image, text: str, point: NDArray[np.float64], direction: NDArray[np.float64], gap: float, scale: float
) -> tuple[float, float]:
    """Text on the side of ``point`` that ``direction`` (unit, pixels) points to; returns its size."""
    width, height, _ = text_size(text, scale)
    reach = (abs(direction[0]) * width + abs(direction[1]) * height) / 2
    centre = point + direction * (gap + reach)
    put_text(img, text, centre[0], centre[1], scale, ha="center", va="center")
    return width, height


def fixed(points: NDArray[np.float64]) -> NDArray[np.int32]:
    return np.round(np.asarray(points) * (1 << SHIFT)).astype(np.int32)


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


def draw_polyline(img: Image, points_px: NDArray[np.float64], color: BGR, thickness: int = _LINE_THICKNESS) -> None:
    """A polyline in pixels, split at NaN, clipped to (a little beyond) the image."""
    height, width = img.shape[:2]
    margin = 4.0 * thickness
    lo, hi = (-margin, -margin), (width - 1 + margin, height - 1 + margin)
    for run in _finite_runs(np.asarray(points_px, dtype=float).reshape(-1, 2)):
        for piece in _clip_polyline(run, lo, hi):
            if len(piece) == 1:
                cv2.circle(img, tuple(fixed(piece[0])), (thickness << SHIFT) // 2 + 8, color, -1, cv2.LINE_AA, SHIFT)
            else:
                cv2.polylines(img, [fixed(piece)], False, color, thickness, cv2.LINE_AA, SHIFT)


def draw_marker(img: Image, center: NDArray[np.float64], kind: str, color: BGR, radius: int = MARKER_RADIUS) -> None:
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
        cv2.line(img, tuple(fixed(c - (dx, dy))), tuple(fixed(c + (dx, dy))), color, 2 if kind != "*" else 1, cv2.LINE_AA, SHIFT)

    r = float(radius)
    if kind == "o":
        cv2.circle(img, tuple(fixed(c)), radius << SHIFT, color, 1, cv2.LINE_AA, SHIFT)
    elif kind == ".":
        cv2.circle(img, tuple(fixed(c)), (radius << SHIFT) // 2, color, -1, cv2.LINE_AA, SHIFT)
    elif kind == "s":
        corner = fixed(np.array([[cx - r, cy - r], [cx + r, cy - r], [cx + r, cy + r], [cx - r, cy + r]]))
        cv2.polylines(img, [corner], True, color, 2, cv2.LINE_AA, SHIFT)
    else:
        diagonal = r / math.sqrt(2.0)
        if kind in ("+", "*"):
            segment(r + 1, 0.0)
            segment(0.0, r + 1)
        if kind in ("x", "*"):
            segment(diagonal + 1, diagonal + 1)
            segment(diagonal + 1, -(diagonal + 1))


@dataclass(frozen=True)
class LegendEntry:
    label: str
    color: BGR
    kind: str  # "line" or a marker


def _legend_size(entries: Sequence[LegendEntry]) -> tuple[int, int, int]:
    """(width, height, row height) of a legend box for the entries."""
    text = [text_size(e.label, _LEGEND_SCALE) for e in entries]
    row = max(max(h + b for _, h, b in text), 2 * MARKER_RADIUS + 2) + 6
    width = 8 + _LEGEND_SAMPLE + 8 + max(w for w, _, _ in text) + 8
    return width, len(entries) * row + 8, row


def _draw_legend(img: Image, entries: Sequence[LegendEntry], left: int, top: int) -> tuple[int, int, int, int]:
    width, height, row = _legend_size(entries)
    cv2.rectangle(img, (left, top), (left + width, top + height), WHITE, -1)
    cv2.rectangle(img, (left, top), (left + width, top + height), _LEGEND_BORDER, 1, cv2.LINE_AA)
    for i, entry in enumerate(entries):
        cy = top + 4 + i * row + row / 2
        x0 = left + 8
        if entry.kind == "line":
            draw_polyline(img, np.array([[x0, cy], [x0 + _LEGEND_SAMPLE, cy]]), entry.color)
        else:
            draw_marker(img, np.array([x0 + _LEGEND_SAMPLE / 2, cy]), entry.kind, entry.color)
        put_text(img, entry.label, x0 + _LEGEND_SAMPLE + 8, cy, _LEGEND_SCALE, va="center")
    return left, top, left + width, top + height


def place_legend(
    img: Image, entries: Sequence[LegendEntry], area: tuple[int, int, int, int], occupied: NDArray[np.bool_]
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


def text_height(scale: float) -> int:
    return text_size("0", scale)[1]


def _as_bgr(panel: ArrayLike) -> Image:
    array = np.asarray(panel)
    if array.dtype != np.uint8:
        raise ValueError(f"panels must be uint8 images, got {array.dtype}")
    if array.ndim == 2:
        return cast(Image, cv2.cvtColor(array, cv2.COLOR_GRAY2BGR))  # (typed as any Mat; uint8 in, uint8 out)
    if array.ndim == 3 and array.shape[2] == 3:
        return array
    raise ValueError(f"panels must be (H, W) or (H, W, 3) images, got shape {array.shape}")


def caption_strip(text: str, width: int) -> Image:
    """A white strip of the given width with ``text`` centred, shrunk to fit if needed."""
    scale = _CAPTION_SCALE
    while scale > 0.3 and text_size(text, scale)[0] > width - 2 * PAD:
        scale -= 0.05
    _, height, baseline = text_size(text, scale)
    strip = blank(width, height + baseline + 2 * PAD)
    put_text(strip, text, width / 2, PAD, scale, ha="center")
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
    out = blank(columns * cell_w, rows * cell_h)
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
