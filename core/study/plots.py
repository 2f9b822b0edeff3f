"""Report figures: line plots, image-plane trajectories, 3-D paths (the thesis's Figs. 5-1 ..
5-8). Every function is pure: it takes data and returns a new uint8 BGR image on a white
background; nothing here knows about robots. The ``*_with_axes`` / ``*_with_view``
variants also return the data-to-pixel mapping the figure was drawn with, so callers and
tests can locate data on the image.

Why drawn by hand on OpenCV rather than with matplotlib's Agg backend: matplotlib would
shrink the plotting code to a fraction, but it adds a large dependency (and its font cache
and import time) to a product that needs OpenCV anyway, and the tests find data on the
figures through the ``Axes`` / ``View3D`` mappings, which would have to be rebuilt from
matplotlib's transforms. So the chart code stays, split by concern: canvas.py (drawing
primitives and the figures' style), chart_axes.py (ticks, 2-D axes, the 3-D view) and
this module (the figures built on them).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vservo.core.study.canvas import (
    BGR,
    BLACK,
    GAP,
    LABEL_SCALE,
    MARKER_RADIUS,
    PAD,
    TICK_LEN,
    TICK_SCALE,
    TITLE_SCALE,
    WHITE,
    Image,
    LegendEntry,
    blank,
    check_color,
    check_size,
    default_color,
    draw_marker,
    draw_polyline,
    place_legend,
    put_text,
    text_height,
    text_size,
)
from vservo.core.study.chart_axes import (
    MARGIN,
    Axes,
    Limits3,
    View3D,
    axes_box,
    axis_ticks,
    draw_box_3d,
    draw_data_clipped,
    draw_frame,
    draw_grid,
    finite_range,
    fit_view,
    padded_limits,
    tick_edges,
    tick_labels,
    ticks_within,
    view_basis,
)

_OUTSIDE_IMAGE: BGR = (243, 243, 243)
_IMAGE_FRAME: BGR = (70, 70, 70)
_INITIAL_COLOR: BGR = BLACK
_DESIRED_COLOR: BGR = (40, 39, 214)


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
        object.__setattr__(self, "color", None if self.color is None else check_color(self.color))


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
        object.__setattr__(self, "color", None if self.color is None else check_color(self.color))


def _colors(items: Sequence[Series | Series3]) -> list[BGR]:
    return [item.color if item.color is not None else default_color(i) for i, item in enumerate(items)]


def _limits(given: tuple[float, float] | None, data: NDArray[np.float64]) -> tuple[float, float]:
    if given is not None:
        return finite_range(*given)
    return padded_limits(data)


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
    width, height = check_size(size)
    series = list(series)
    colors = _colors(series)
    if series:
        finite = [np.isfinite(s.x) & np.isfinite(s.y) for s in series]
        xs = np.concatenate([s.x[f] for s, f in zip(series, finite)])
        ys = np.concatenate([s.y[f] for s, f in zip(series, finite)])
    else:
        xs = ys = np.empty(0)
    x_lim, y_lim = _limits(xlim, xs), _limits(ylim, ys)
    x_ticks = ticks_within(*x_lim, max_ticks=int(np.clip(width // 90, 2, 10)))
    y_ticks = ticks_within(*y_lim, max_ticks=int(np.clip(height // 55, 2, 10)))
    box = axes_box((width, height), title, xlabel, ylabel, tick_labels(x_ticks), tick_labels(y_ticks))
    axes = Axes(x_lim, y_lim, box, False, tuple(map(float, x_ticks)), tuple(map(float, y_ticks)))

    img = blank(width, height)
    draw_grid(img, axes)

    def draw(layer: Image) -> None:
        for s, color in zip(series, colors):
            draw_polyline(layer, axes.to_pixel(s.x, s.y), color)

    occupied = draw_data_clipped(img, axes, draw)
    draw_frame(img, axes, title, xlabel, ylabel)
    legend = place_legend(img, [LegendEntry(s.label, c, "line") for s, c in zip(series, colors)], box, occupied)
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
    width, height = check_size(size)
    image_w, image_h = (float(v) for v in image_size)
    if image_w <= 0 or image_h <= 0:
        raise ValueError(f"image_size must be positive, got {image_size}")
    initial = _as_points(initial_marker_points, "initial_marker_points")
    desired = _as_points(desired_points, "desired_points")
    extras = []
    for item in extra_points:
        label, points, color = item[:3]
        kind = item[3] if len(item) > 3 else "s"
        extras.append((str(label), _as_points(points, f"extra points {label!r}"), check_color(color), kind))
    trajectories = list(trajectories)
    colors = _colors(trajectories)

    x_lim = (-margin * image_w, (1 + margin) * image_w)
    y_lim = (-margin * image_h, (1 + margin) * image_h)
    x_ticks = ticks_within(*x_lim, max_ticks=int(np.clip(width // 100, 2, 10)))
    y_ticks = ticks_within(*y_lim, max_ticks=int(np.clip(height // 60, 2, 10)))
    aspect = (x_lim[1] - x_lim[0]) / (y_lim[1] - y_lim[0])
    box = axes_box((width, height), title, xlabel, ylabel, tick_labels(x_ticks), tick_labels(y_ticks), aspect)
    axes = Axes(x_lim, y_lim, box, True, tuple(map(float, x_ticks)), tuple(map(float, y_ticks)))

    img = blank(width, height)
    left, top, right, bottom = box
    frame = np.round(axes.to_pixel([0.0, image_w], [0.0, image_h])).astype(int)
    cv2.rectangle(img, (left, top), (right, bottom), _OUTSIDE_IMAGE, -1)
    cv2.rectangle(img, tuple(frame[0]), tuple(frame[1]), WHITE, -1)
    draw_grid(img, axes)
    cv2.rectangle(img, tuple(frame[0]), tuple(frame[1]), _IMAGE_FRAME, 2)

    def draw(layer: Image) -> None:
        for s, color in zip(trajectories, colors):
            draw_polyline(layer, axes.to_pixel(s.x, s.y), color)
        for label, points, color, kind in extras:
            for p in axes.to_pixel(points[:, 0], points[:, 1]):
                draw_marker(layer, p, kind, color)
        for p in axes.to_pixel(initial[:, 0], initial[:, 1]):
            draw_marker(layer, p, "o", _INITIAL_COLOR)
        for p in axes.to_pixel(desired[:, 0], desired[:, 1]):
            draw_marker(layer, p, "*", _DESIRED_COLOR, radius=MARKER_RADIUS + 1)

    occupied = draw_data_clipped(img, axes, draw)
    draw_frame(img, axes, title, xlabel, ylabel)
    entries = [LegendEntry(s.label, c, "line") for s, c in zip(trajectories, colors)]
    if len(initial):
        entries.append(LegendEntry(initial_label, _INITIAL_COLOR, "o"))
    if len(desired):
        entries.append(LegendEntry(desired_label, _DESIRED_COLOR, "*"))
    entries += [LegendEntry(label, color, kind) for label, points, color, kind in extras if len(points)]
    legend = place_legend(img, entries, box, occupied)
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
        pad = MARGIN * extent
        limits.append((float(centre - half - pad), float(centre + half + pad)))
    return limits[0], limits[1], limits[2]


def path_3d_plot_with_view(
    paths: Sequence[Series3],
    title: str = "",
    azimuth_deg: float = -37.5,
    elevation_deg: float = 30.0,
    size: tuple[int, int] = (640, 480),
    axis_labels: tuple[str, str, str] = ("X (m)", "Y (m)", "Z (m)"),
) -> tuple[Image, View3D]:
    """``path_3d_plot`` that also returns the View3D projection it used."""
    width, height = check_size(size)
    if not -90.0 < elevation_deg < 90.0:
        raise ValueError(f"elevation_deg must be in (-90, 90), got {elevation_deg}")
    paths = list(paths)
    colors = _colors(paths)
    limits = _box_limits(paths)
    right, up = view_basis(azimuth_deg, elevation_deg)
    title_h = (text_height(TITLE_SCALE) + 4 + 2 * GAP) if title else 0
    label_room = TICK_LEN + GAP + 2 * GAP + text_height(LABEL_SCALE) + 4 + PAD

    # Two passes: tick counts need the scale, the margins need the tick label widths.
    view = fit_view(limits, right, up, (70, PAD + title_h + 10, width - 70, height - 70))
    edges = tick_edges(view)
    ticks = axis_ticks(view, edges)
    label_w = max((text_size(t, TICK_SCALE)[0] for axis in ticks for t in tick_labels(axis)), default=20)
    tick_h = text_height(TICK_SCALE)
    side = label_room + label_w
    area = (side, PAD + title_h + tick_h, width - 1 - side * 0.8, height - 1 - (label_room + tick_h + 8))
    view = fit_view(limits, right, up, area)
    edges = tick_edges(view)

    img = blank(width, height)
    draw_box_3d(img, view, edges, ticks, axis_labels)
    for path, color in zip(paths, colors):
        draw_polyline(img, view.to_pixel(path.xyz), color)
    for path, color in zip(paths, colors):
        finite = path.xyz[np.all(np.isfinite(path.xyz), axis=1)]
        if len(finite):
            draw_marker(img, view.to_pixel(finite[0]), "o", color)
            draw_marker(img, view.to_pixel(finite[-1]), "*", color, radius=MARKER_RADIUS + 1)
    if title:
        put_text(img, title, width / 2, PAD, TITLE_SCALE, ha="center")
    entries = [LegendEntry(p.label, c, "line") for p, c in zip(paths, colors)]
    if any(p.label for p in paths):
        entries += [LegendEntry("start", BLACK, "o"), LegendEntry("end", BLACK, "*")]
    occupied = np.any(img != 255, axis=-1)
    place_legend(img, entries, (0, title_h, width - 1, height - 1), occupied)
    return img, view


def path_3d_plot(*args: Any, **kwargs: Any) -> Image:
    """3-D polylines in an orthographic view with MATLAB's ``view(azimuth, elevation)``.

    The data's bounding box is drawn with a light grid on its three back faces and
    ticks on three edges (x and y along the bottom front, z on the left); one scale for
    all axes. Each path has an 'o' at its start and a '*' at its end. Z is up on the
    image for any elevation in (-90, 90).
    """
    return path_3d_plot_with_view(*args, **kwargs)[0]
