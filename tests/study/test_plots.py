"""OpenCV report figures: tick choice, and data landing where the plot's own mapping says."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from vservo.core.study.canvas import PALETTE, grid, write_png
from vservo.core.study.chart_axes import Axes, format_tick, nice_ticks, tick_labels
from vservo.core.study.plots import (
    Series,
    Series3,
    image_trajectory_plot,
    image_trajectory_plot_with_axes,
    line_plot,
    line_plot_with_axes,
    path_3d_plot,
    path_3d_plot_with_view,
)

# Colors no decoration uses (axes, grid and text are gray levels; the palette is tab10).
MAGENTA = (255, 0, 255)
TEAL = (128, 128, 0)


def color_mask(image: np.ndarray, color: tuple[int, int, int], tolerance: int = 40) -> np.ndarray:
    """Pixels within ``tolerance`` (sum of channel differences) of color."""
    return np.abs(image.astype(int) - np.array(color)).sum(axis=-1) <= tolerance


def outside(mask: np.ndarray, box: tuple[int, int, int, int] | None) -> np.ndarray:
    """mask with the pixels of box (left, top, right, bottom) cleared."""
    mask = mask.copy()
    if box is not None:
        left, top, right, bottom = box
        mask[top : bottom + 1, left : right + 1] = False
    return mask


def near(mask: np.ndarray, pixel: np.ndarray, radius: int = 3) -> bool:
    column, row = (round(float(v)) for v in pixel)
    return bool(mask[max(row - radius, 0) : row + radius + 1, max(column - radius, 0) : column + radius + 1].any())


# --------------------------------------------------------------------------- ticks


def is_nice_step(step: float) -> bool:
    exponent = math.floor(math.log10(step) + 1e-9)
    mantissa = step / 10.0**exponent
    return any(math.isclose(mantissa, m, rel_tol=1e-6) for m in (1.0, 2.0, 5.0, 10.0))


@pytest.mark.parametrize("max_ticks", [2, 3, 4, 5, 6, 8, 10])
def test_nice_ticks_cover_the_range_with_1_2_5_steps(max_ticks: int) -> None:
    rng = np.random.default_rng(7)
    for _ in range(300):
        centre = rng.uniform(-1, 1) * 10.0 ** rng.integers(-4, 5)
        span = 10.0 ** rng.uniform(-5, 5)
        lo, hi = centre - span * rng.uniform(0, 1), centre + span * rng.uniform(0, 1)
        ticks = nice_ticks(lo, hi, max_ticks)
        steps = np.diff(ticks)
        assert 2 <= len(ticks) <= max_ticks + 1, (lo, hi, ticks)
        assert ticks[0] <= lo + 1e-9 * span and ticks[-1] >= hi - 1e-9 * span, (lo, hi, ticks)
        assert np.allclose(steps, steps[0], rtol=1e-6), ticks
        assert is_nice_step(steps[0]), (lo, hi, ticks)
        # Ticks are multiples of the step (so a range across zero has a tick at 0).
        assert np.allclose(ticks / steps[0], np.round(ticks / steps[0]), atol=1e-6)


def test_nice_ticks_use_the_finest_step_that_fits() -> None:
    assert nice_ticks(0, 10, 5).tolist() == [0, 2, 4, 6, 8, 10]
    assert nice_ticks(0, 1, 10).tolist() == pytest.approx(np.arange(11) / 10)
    assert nice_ticks(-0.1, 0.1, 4).tolist() == [-0.1, -0.05, 0.0, 0.05, 0.1]
    assert nice_ticks(3, 97, 6).tolist() == [0, 20, 40, 60, 80, 100]
    # Exact decimals, no 0.30000000000000004.
    assert 0.3 in nice_ticks(0.0, 1.0, 10).tolist()


@pytest.mark.parametrize(
    ("lo", "hi", "inside"),
    [
        (5.0, 5.0, 5.0),
        (0.0, 0.0, 0.0),
        (-2e-7, -2e-7, -2e-7),
        (float("nan"), 4.0, 4.0),
        (4.0, float("nan"), 4.0),
        (float("-inf"), 4.0, 4.0),
        (float("nan"), float("nan"), 0.5),
        (9.0, 1.0, 5.0),  # reversed
    ],
)
def test_nice_ticks_degenerate_ranges(lo: float, hi: float, inside: float) -> None:
    ticks = nice_ticks(lo, hi, 6)
    assert np.all(np.isfinite(ticks))
    assert 2 <= len(ticks) <= 7
    assert ticks[0] <= inside <= ticks[-1]
    assert is_nice_step(ticks[1] - ticks[0])
    assert np.all(np.diff(ticks) > 0)


def test_nice_ticks_rejects_too_few_ticks() -> None:
    with pytest.raises(ValueError, match="max_ticks"):
        nice_ticks(0, 1, 1)


def test_tick_labels_are_compact() -> None:
    assert tick_labels(nice_ticks(-0.1, 0.1, 4)) == ["-0.1", "-0.05", "0", "0.05", "0.1"]
    assert tick_labels([0, 100, 200, 300]) == ["0", "100", "200", "300"]
    assert tick_labels([1.5, 2.0, 2.5]) == ["1.5", "2", "2.5"]
    assert format_tick(-1e-17, 0.1) == "0"
    assert format_tick(2e-6, 1e-6) == "2e-6"
    assert format_tick(3e7, 1e7) == "3e7"


# --------------------------------------------------------------------------- line plot


def horizontal_plot(y: np.ndarray) -> tuple[np.ndarray, Axes, np.ndarray]:
    x = np.linspace(0.0, 10.0, y.size)
    ramp = Series("ramp", x, np.linspace(-1.0, 3.0, y.size), color=TEAL)
    image, axes = line_plot_with_axes([ramp, Series("level", x, y, color=MAGENTA)], "t", "time (s)", "value")
    return image, axes, x


def test_line_plot_draws_a_level_on_the_row_its_axes_map_it_to() -> None:
    image, axes, _ = horizontal_plot(np.full(200, 1.7))
    assert image.shape == (400, 640, 3) and image.dtype == np.uint8
    assert tuple(image[0, 0]) == (255, 255, 255)
    assert axes.y_lim[0] < -1.0 and axes.y_lim[1] > 3.0  # data plus a margin
    assert axes.y_lim[1] - axes.y_lim[0] < 4.0 * 1.2

    mask = outside(color_mask(image, MAGENTA), axes.legend_box)
    rows, columns = np.nonzero(mask)
    assert rows.size > 300
    expected_row = axes.to_pixel(5.0, 1.7)[1]
    assert abs(np.median(rows) - expected_row) <= 1.0
    assert np.all(np.abs(rows - expected_row) <= 2.0)
    # Spans x = 0 .. 10 exactly, as mapped.
    assert abs(columns.min() - axes.to_pixel(0.0, 1.7)[0]) <= 2.0
    assert abs(columns.max() - axes.to_pixel(10.0, 1.7)[0]) <= 2.0


def test_line_plot_axes_mapping_is_y_up_inside_the_box() -> None:
    _, axes, _ = horizontal_plot(np.full(50, 1.7))
    left, top, right, bottom = axes.box
    low, high = axes.to_pixel([axes.x_lim[0], axes.x_lim[1]], [axes.y_lim[0], axes.y_lim[1]])
    assert low.tolist() == [left, bottom] and high.tolist() == [right, top]
    assert all(axes.x_lim[0] <= t <= axes.x_lim[1] for t in axes.x_ticks)
    assert all(axes.y_lim[0] <= t <= axes.y_lim[1] for t in axes.y_ticks)
    assert len(axes.x_ticks) >= 3 and len(axes.y_ticks) >= 3


def test_line_plot_leaves_a_nan_gap_empty() -> None:
    y = np.full(201, 1.7)
    x = np.linspace(0.0, 10.0, 201)
    y[(x > 4.0) & (x < 6.0)] = np.nan
    image, axes, _ = horizontal_plot(y)
    mask = outside(color_mask(image, MAGENTA), axes.legend_box)
    gap_from, gap_to = axes.to_pixel(4.0, 0.0)[0], axes.to_pixel(6.0, 0.0)[0]
    columns = np.nonzero(mask)[1]
    assert not np.any((columns > gap_from + 3) & (columns < gap_to - 3))
    assert np.any(columns < gap_from) and np.any(columns > gap_to)


def test_line_plot_legend_shows_each_series_color() -> None:
    image, axes, _ = horizontal_plot(np.full(50, 1.7))
    assert axes.legend_box is not None
    left, top, right, bottom = axes.legend_box
    legend = image[top : bottom + 1, left : right + 1]
    assert color_mask(legend, MAGENTA).sum() > 20
    assert color_mask(legend, TEAL).sum() > 20
    # Text in the legend.
    assert (legend.sum(axis=-1) < 100).sum() > 20


def test_line_plot_legend_avoids_the_data() -> None:
    x = np.linspace(0.0, 1.0, 100)
    image, axes = line_plot_with_axes([Series("diagonal", x, x, color=MAGENTA)], "", "x", "y")
    left, top, right, bottom = axes.legend_box
    pixels = axes.to_pixel(x, x)
    inside = (pixels[:, 0] >= left - 2) & (pixels[:, 0] <= right + 2) & (pixels[:, 1] >= top - 2) & (pixels[:, 1] <= bottom + 2)
    assert not inside.any()


def test_line_plot_default_colors_cycle_through_the_palette() -> None:
    x = np.linspace(0.0, 1.0, 20)
    series = [Series(f"s{i}", x, np.full_like(x, float(i))) for i in range(len(PALETTE) + 1)]
    image, axes = line_plot_with_axes(series, "", "", "")
    data = outside(np.ones(image.shape[:2], bool), axes.legend_box)
    for i, color in enumerate(PALETTE):
        mask = color_mask(image, color, 10) & data
        assert mask.any(), i
        if i == 0:  # series 0 and series len(PALETTE) share the first color
            rows = set(np.nonzero(mask)[0].tolist())
            for level in (0.0, float(len(PALETTE))):
                assert round(float(axes.to_pixel(0.5, level)[1])) in rows


def test_line_plot_without_data_or_labels_still_draws_axes() -> None:
    image = line_plot([], "empty", "x", "y")
    assert image.shape == (400, 640, 3)
    image, axes = line_plot_with_axes([Series("", [0.0, 1.0], [np.nan, np.nan])], "", "", "", size=(300, 200))
    assert image.shape == (200, 300, 3)
    assert axes.legend_box is None
    assert (image.sum(axis=-1) < 100).any()  # axes and ticks


def test_series_validates_shapes_and_colors() -> None:
    with pytest.raises(ValueError, match="equal length"):
        Series("bad", np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="BGR"):
        Series("bad", np.zeros(3), np.zeros(3), color=(0, 0, 300))
    with pytest.raises(ValueError, match="T, 3"):
        Series3("bad", np.zeros((4, 2)))


# --------------------------------------------------------------------------- image plane


def test_image_trajectory_plot_puts_v_downward() -> None:
    trajectory = Series("point", np.linspace(100, 500, 100), np.linspace(100, 400, 100), color=MAGENTA)
    image, axes = image_trajectory_plot_with_axes([trajectory], (640, 480), "traj")
    assert axes.y_down
    start, middle, end = axes.to_pixel([100.0, 300.0, 500.0], [100.0, 250.0, 400.0])
    assert start[1] < end[1] and start[0] < end[0]  # u right, v down

    mask = outside(color_mask(image, MAGENTA), axes.legend_box)
    for pixel in (start, middle, end):
        assert near(mask, pixel, 2)
    # Not where a y-up plot would have drawn it.
    for pixel in axes.to_pixel([100.0, 500.0], [400.0, 100.0]):
        assert not near(mask, pixel, 6)
    # Equal scale on u and v.
    scale_u = (end[0] - start[0]) / 400.0
    scale_v = (end[1] - start[1]) / 300.0
    assert scale_u == pytest.approx(scale_v, rel=0.02)


def test_image_trajectory_plot_frames_the_image_and_shows_a_margin_around_it() -> None:
    image, axes = image_trajectory_plot_with_axes([], (640, 480))
    assert axes.x_lim == pytest.approx((-160.0, 800.0)) and axes.y_lim == pytest.approx((-120.0, 600.0))
    dark = image.sum(axis=-1) < 400
    for u, v in ((0, 240), (640, 240), (320, 0), (320, 480)):
        assert near(dark, axes.to_pixel(u, v), 1), (u, v)
    assert not near(dark, axes.to_pixel(320, 240), 10)


def test_image_trajectory_plot_draws_points_outside_the_image_and_clips_far_ones() -> None:
    away = Series("away", [320.0, -100.0, -1e9], [240.0, -80.0, -1e9], color=MAGENTA)
    image, axes = image_trajectory_plot_with_axes([away], (640, 480))
    mask = outside(color_mask(image, MAGENTA), axes.legend_box)
    assert near(mask, axes.to_pixel(-100.0, -80.0), 2)
    left, top, right, bottom = axes.box
    rows, columns = np.nonzero(mask)
    assert rows.min() >= top and columns.min() >= left  # clipped at the axes box


def test_image_trajectory_plot_markers_and_legend() -> None:
    initial = np.array([[100.0, 100.0], [200.0, 300.0]])
    desired = np.array([[300.0, 200.0], [400.0, 350.0]])
    extra = np.array([[600.0, 450.0]])
    image, axes = image_trajectory_plot_with_axes([], (640, 480), "markers", initial, desired, [("spot", extra, MAGENTA)])
    dark = (image.sum(axis=-1) < 200) & outside(np.ones(image.shape[:2], bool), axes.legend_box)
    for u, v in initial:  # 'o': a ring, hollow in the middle
        column, row = axes.to_pixel(u, v)
        assert near(dark, (column + 5, row), 1) and near(dark, (column - 5, row), 1)
        assert not near(dark, (column, row), 1)
    red = color_mask(image, (40, 39, 214)) & outside(np.ones(image.shape[:2], bool), axes.legend_box)
    for u, v in desired:  # '*': filled through the centre
        assert near(red, axes.to_pixel(u, v), 1)
    spot = color_mask(image, MAGENTA)
    assert near(outside(spot, axes.legend_box), axes.to_pixel(600.0, 450.0), 6)
    left, top, right, bottom = axes.legend_box
    assert spot[top:bottom, left:right].any()


def test_image_trajectory_plot_returns_an_image() -> None:
    image = image_trajectory_plot([Series("p", [1.0, 2.0], [3.0, 4.0])], (320, 240), size=(400, 360))
    assert image.shape == (360, 400, 3) and image.dtype == np.uint8


# --------------------------------------------------------------------------- 3-D paths


def test_path_3d_plot_draws_both_paths() -> None:
    t = np.linspace(0.0, 1.0, 50)
    first = Series3("first", np.stack([t, t**2, 1 - t], axis=1), color=MAGENTA)
    second = Series3("second", np.stack([1 - t, t, 0.5 + 0 * t], axis=1), color=TEAL)
    image = path_3d_plot([first, second], "paths", size=(500, 420))
    assert image.shape == (420, 500, 3) and image.dtype == np.uint8
    assert color_mask(image, MAGENTA).sum() > 100
    assert color_mask(image, TEAL).sum() > 100
    assert (image < 250).any(axis=-1).mean() > 0.02


def test_path_3d_plot_z_goes_up_the_image() -> None:
    z = np.linspace(0.0, 1.0, 30)
    path = Series3("", np.stack([0 * z, 0 * z, z], axis=1), color=MAGENTA)  # no label: no legend
    for azimuth, elevation in ((-37.5, 30.0), (60.0, 10.0), (150.0, 75.0), (-37.5, -30.0)):
        image, view = path_3d_plot_with_view([path], "", azimuth, elevation)
        bottom, top = view.to_pixel(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
        assert top[1] < bottom[1] - 50
        mask = color_mask(image, MAGENTA)
        assert near(mask, bottom, 2) and near(mask, top, 2)
        rows, columns = np.nonzero(mask)
        assert np.ptp(rows) > 3 * np.ptp(columns)


def test_path_3d_plot_has_equal_scale_and_matlab_orientation() -> None:
    square = Series3("square", [[0, 0, 0], [1, 0, 0], [1, 2, 0], [0, 0, 3]])
    _, view = path_3d_plot_with_view([square], "", 0.0, 0.0)
    origin, x, z = view.to_pixel(np.array([[0.0, 0, 0], [1, 0, 0], [0, 0, 1]]))
    assert x[0] - origin[0] == pytest.approx(origin[1] - z[1])  # 1 m along x == 1 m up z
    assert x[1] == pytest.approx(origin[1])
    _, view = path_3d_plot_with_view([square])  # default view(-37.5, 30)
    origin, x, y = view.to_pixel(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]))
    assert x[0] > origin[0] and y[0] < origin[0]  # x to the right, y to the left
    assert x[1] < origin[1] and y[1] < origin[1]  # both recede upward
    lengths = [np.hypot(*(view.to_pixel(e) - view.to_pixel(np.zeros(3)))) for e in np.eye(3)]
    assert max(lengths) <= view.scale * (1 + 1e-9)


def test_path_3d_plot_marks_start_and_end() -> None:
    path = Series3("", [[0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [1.0, 1.0, 1.0]], color=MAGENTA)
    image, view = path_3d_plot_with_view([path])
    mask = color_mask(image, MAGENTA, 150)  # the '*' strokes are thin, antialiased
    start, end = view.to_pixel(np.array([[0.0, 0, 0], [1.0, 1, 1]]))
    back = (start - end) / np.hypot(*(start - end))  # away from the line, into the 'o'
    assert near(mask, start + 5 * back, 1) and not near(mask, start + 2.5 * back, 0)  # hollow 'o'
    assert near(mask, end - 5 * back, 1)  # '*' reaches beyond the end of the line
    assert not near(mask, end - 9 * back, 1)


def test_path_3d_plot_splits_at_nan_and_handles_degenerate_data() -> None:
    path = Series3("", [[0.0, 0.0, 0.0], [0.2, 0, 0], [np.nan, 0, 0], [0.8, 0, 0], [1.0, 0, 0]], color=MAGENTA)
    image, view = path_3d_plot_with_view([path], "", 0.0, 0.0)
    mask = color_mask(image, MAGENTA)
    assert near(mask, view.to_pixel(np.array([0.1, 0, 0])), 1)
    assert not near(mask, view.to_pixel(np.array([0.5, 0, 0])), 3)
    for data in ([[1.0, 2.0, 3.0]], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], [[np.nan] * 3]):
        image = path_3d_plot([Series3("p", data)])
        assert image.shape == (480, 640, 3)


# --------------------------------------------------------------------------- composition and output


def test_grid_pads_panels_to_the_largest() -> None:
    panels = [np.zeros((100, 200, 3), np.uint8), np.zeros((120, 150, 3), np.uint8), np.zeros((80, 210, 3), np.uint8)]
    figure = grid(panels, columns=2)
    assert figure.shape == (240, 420, 3)
    assert (figure[10:110, 5:205] == 0).all()  # first panel, centred in its 120 x 210 cell
    assert (figure[0:10, 0:210] == 255).all()
    assert (figure[0:120, 240:390] == 0).all()  # second panel fills its cell's height
    assert (figure[120:240, 210:420] == 255).all()  # the empty cell
    assert grid(panels, columns=5).shape == (120, 630, 3)
    assert grid(panels, columns=1).shape == (360, 210, 3)
    assert grid([np.zeros((50, 60), np.uint8)], 1).shape == (50, 60, 3)


def test_grid_caption_adds_a_line_of_text_below() -> None:
    panels = [np.full((100, 200, 3), 255, np.uint8)] * 2
    figure = grid(panels, 2, "(a) image trajectory")
    assert figure.shape[1] == 400 and 110 < figure.shape[0] < 150
    caption = figure[100:]
    assert (caption.sum(axis=-1) < 300).sum() > 50
    assert (figure[:100] == 255).all()
    with pytest.raises(ValueError):
        grid([], 2)
    with pytest.raises(ValueError):
        grid(panels, 0)


def test_write_png_makes_directories_and_round_trips(tmp_path: Path) -> None:
    image = line_plot([Series("s", [0.0, 1.0], [0.0, 1.0])], "t", "x", "y", size=(320, 240))
    path = write_png(tmp_path / "a" / "b" / "figure.png", image)
    assert path == tmp_path / "a" / "b" / "figure.png"
    assert path.read_bytes().startswith(b"\x89PNG")
    assert np.array_equal(cv2.imread(str(path)), image)


def test_write_png_failure_names_the_path(tmp_path: Path) -> None:
    target = tmp_path / "taken.png"
    target.mkdir()
    with pytest.raises(OSError, match="taken.png"):
        write_png(target, np.zeros((10, 10, 3), np.uint8))
