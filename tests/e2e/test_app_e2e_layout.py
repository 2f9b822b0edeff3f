"""The 3D arm in sight beside the E-STOP: no panel covers the arm, at 1024x640, 1280x720 and 1920x1080.

`vservo serve` as a real process and headless Chromium, one page resized to each window size.
At each size:

- what covers the 3D view: ``document.elementFromPoint`` on a grid of points 8 px apart over
  the 3D canvas (three.js's, ``canvas[data-engine]``), clipped to the window; a point is
  uncovered when the canvas itself is on top there. The uncovered area must be a real part of
  the window (at least an eighth of it);
- where the arm is drawn: a screenshot of the canvas alone (every other element made
  invisible for it, which moves nothing), the arm as its largest blue blob (its links; the
  camera's body and frustum on the flange are blue too). The whole arm must be in the canvas
  (its blob clear of the canvas's edges, else the view cuts it off) and at every grid point
  where the arm is drawn, the canvas must be uncovered.

Before the E-STOP's panel was docked (it floated over the 3D view's top left) this failed: at
1280x720 the view was 242 px wide and the panel covered the arm at 91 of its 136 grid points; at
1024x640 the view was 121 px wide, 85 of 90 covered and the arm cut off at the view's edge.
The uncovered area per size goes to $VSERVO_ARTIFACTS/layout.txt.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.polling import wait_until
from vservo.app.browser import ServeProcess, dismiss_notifications, open_pages

TOKEN = "e2e-layout-token"
SIZES = [(1024, 640), (1280, 720), (1920, 1080)]
STEP_PX = 8  # the grid over the 3D canvas
MIN_UNCOVERED = 1 / 8  # of the window's area
EDGE_PX = 4  # the arm's blob keeps this clear of the canvas's edges: nothing of it cut off
MIN_ARM_POINTS = 40  # grid points on the arm: the arm is drawn at a size one can see (~2500 px^2)
ARM_HSV_LOW, ARM_HSV_HIGH = np.array([100, 150, 40]), np.array([130, 255, 255])  # OpenCV's HSV: blue, saturated
ARTIFACTS = Path(os.environ.get("VSERVO_ARTIFACTS", Path(__file__).resolve().parents[2] / "test-artifacts"))

# The 3D canvas's box clipped to the window, and for each grid point (row by row) whether the
# canvas is the element on top there.
UNCOVERED_GRID = """(step) => {
    const canvas = document.querySelector('canvas[data-engine]');
    const box = canvas.getBoundingClientRect();
    const left = Math.max(0, box.left), top = Math.max(0, box.top);
    const right = Math.min(window.innerWidth, box.right), bottom = Math.min(window.innerHeight, box.bottom);
    const rows = [];
    for (let y = top + step / 2; y < bottom; y += step) {
        const row = [];
        for (let x = left + step / 2; x < right; x += step) { row.push(document.elementFromPoint(x, y) === canvas); }
        rows.push(row);
    }
    return {left, top, width: right - left, height: bottom - top, rows};
}"""
# Everything but the 3D canvas invisible (visibility keeps every box where it is), or back.
CANVAS_ALONE = """(alone) => {
    let style = document.getElementById('canvas-alone');
    if (alone && !style) {
        style = document.createElement('style');
        style.id = 'canvas-alone';
        style.textContent = 'body * { visibility: hidden !important } canvas[data-engine] { visibility: visible !important }';
        document.head.appendChild(style);
    } else if (!alone && style) { style.remove(); }
}"""


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    with ServeProcess.start(tmp_path_factory.mktemp("data"), TOKEN, cycle_period_s=0.0) as serve:
        yield serve


def _arm_mask(png: bytes) -> np.ndarray:
    """The largest blue blob of a screenshot of the canvas alone (True where the arm is drawn)."""
    hsv = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2HSV)
    blue = cv2.inRange(hsv, ARM_HSV_LOW, ARM_HSV_HIGH)  # shaded or lit, never the grey base or table
    count, labels, stats, _ = cv2.connectedComponentsWithStats(blue, connectivity=8)
    if count < 2:
        return np.zeros(blue.shape, bool)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == largest


def _measure(page) -> dict:
    """At the page's size: the uncovered area of the 3D view, and where the arm is against it."""
    grid = page.evaluate(UNCOVERED_GRID, STEP_PX)
    clip = {key: grid[key] for key in ("left", "top", "width", "height")}
    clip["x"], clip["y"] = clip.pop("left"), clip.pop("top")
    page.evaluate(CANVAS_ALONE, True)
    try:
        arm = _arm_mask(page.screenshot(clip=clip))
    finally:
        page.evaluate(CANVAS_ALONE, False)
    uncovered = np.array(grid["rows"], bool)
    # The screenshot in device pixels (1 per CSS pixel here); the grid's points in it.
    ys = np.minimum((np.arange(uncovered.shape[0]) * STEP_PX + STEP_PX // 2), arm.shape[0] - 1)
    xs = np.minimum((np.arange(uncovered.shape[1]) * STEP_PX + STEP_PX // 2), arm.shape[1] - 1)
    on_arm = arm[np.ix_(ys, xs)]
    rows, columns = np.nonzero(arm)
    return {
        "window_px": page.viewport_size["width"] * page.viewport_size["height"],
        "canvas": (round(grid["width"]), round(grid["height"])),
        "uncovered_px": int(uncovered.sum()) * STEP_PX**2,
        "arm_points": int(on_arm.sum()),
        "arm_points_covered": int((on_arm & ~uncovered).sum()),
        "arm_clear_of_edges": bool(
            rows.size
            and rows.min() >= EDGE_PX
            and columns.min() >= EDGE_PX
            and rows.max() < arm.shape[0] - EDGE_PX
            and columns.max() < arm.shape[1] - EDGE_PX
        ),
    }


def _settled(page, what: str) -> dict:
    """The measures once two in a row agree with the arm drawn (the scene is redrawn for a new
    size within a few frames, the panels take their places as the page settles)."""
    last: list[dict] = [{}]

    def same_again() -> bool:
        now, last[0] = _measure(page), _measure(page)
        return now == last[0] and now["arm_points"] >= MIN_ARM_POINTS

    wait_until(same_again, what, 30)
    return last[0]


def test_layout_keeps_the_whole_3d_arm_uncovered_at_every_window_size(app, chromium):
    (page,) = open_pages(chromium, app.url, [SIZES[0]])
    measured = {}
    for width, height in SIZES:
        page.set_viewport_size({"width": width, "height": height})
        dismiss_notifications(page)  # a reply's toast lies over the 3D view's top left for a while
        measured[(width, height)] = _settled(page, f"the arm drawn at {width}x{height}")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "layout.txt").write_text(
        "".join(
            f"{w}x{h}: 3D view {m['canvas'][0]}x{m['canvas'][1]} px, uncovered {m['uncovered_px']} px "
            f"({m['uncovered_px'] / m['window_px']:.0%} of the window), arm on {m['arm_points']} grid points, "
            f"{m['arm_points_covered']} covered, clear of the view's edges: {m['arm_clear_of_edges']}\n"
            for (w, h), m in measured.items()
        )
    )
    failed = {
        size: m
        for size, m in measured.items()
        if m["uncovered_px"] < MIN_UNCOVERED * m["window_px"] or m["arm_points_covered"] or not m["arm_clear_of_edges"]
    }
    assert not failed, failed
