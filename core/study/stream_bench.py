"""``vservo bench stream``: what a network camera costs the vision in accuracy and time.

Views of the simulated cell (the demo job's desired view, and views around it as the
servo sees them on its way there) are rendered once, then each is served through an MJPEG
``CameraStream`` and read back by OpenCV through ``VideoCaptureSource`` on its URL, as
the product reads an IP camera. The feature extractor runs on the rendered image and on
the streamed one: their corner and spot differences are what JPEG and the decoder cost.

Timing: between two views the stream shows black. When the reader has seen black, the
stream switches to the view, noting the exposure of its first frame; the first frame
that is not black arrives ``exposure_to_read`` later (the source's arrival stamp on the
same monotonic clock): encoding, HTTP, FFmpeg's demuxer and decoder, the hand-over.
The stream adds no latency of its own here (``exposure_latency_s`` 0).
"""

from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from vservo.core.cell.config import CellConfig
from vservo.core.geometry.spatial import Matrix, Pose6, matrix_from_pose
from vservo.core.perception.camera_source import Frame, VideoCaptureSource
from vservo.core.production.demo_job import DESIRED_cMo
from vservo.core.production.rig import extractor_for
from vservo.core.sim.camera import SimulatedCamera
from vservo.core.sim.camera_stream import CameraStream, encode_jpeg
from vservo.core.sim.plant import SimulatedCell

# Views around the desired one: the camera moved up to these amounts along and about
# its own axes, the neighbourhood the servo's last cycles pass through.
OFFSET_M = 0.01
OFFSET_RAD = 0.1
BLACK_MAX = 32  # a streamed frame whose brightest pixel is below this shows the black screen
FPS = 30.0


@dataclass(frozen=True)
class ViewResult:
    """One view, direct against streamed: pixel differences of what both detected."""

    corner_diff_px: tuple[float, ...]  # per corner found in both
    corners_agree: bool  # the same corners found in both
    spot_diff_px: float  # NaN unless both found the spot
    jpeg_bytes: int
    exposure_to_read_s: float


def views_around_desired(count: int, seed: int) -> list[Matrix]:
    """cMo of ``count`` views: the desired one first, then random ones around it."""
    rng = np.random.default_rng(seed)
    views = [DESIRED_cMo]
    for _ in range(count - 1):
        offset = Pose6(*rng.uniform(-OFFSET_M, OFFSET_M, 3), *rng.uniform(-OFFSET_RAD, OFFSET_RAD, 3))
        views.append(matrix_from_pose(offset) @ DESIRED_cMo)
    return views


class _Screen:
    """What the stream shows: black, or a view, noting when its first frame was exposed."""

    def __init__(self, black: np.ndarray) -> None:
        self._lock = threading.Lock()
        self._image = black
        self._black = black
        self._first_exposure_s: float | None = None

    def __call__(self) -> np.ndarray:
        with self._lock:
            if self._first_exposure_s is None and self._image is not self._black:
                self._first_exposure_s = time.monotonic()
            return self._image

    def show(self, image: np.ndarray) -> None:
        with self._lock:
            self._image = image
            self._first_exposure_s = None

    def blank(self) -> None:
        self.show(self._black)

    @property
    def first_exposure_s(self) -> float:
        with self._lock:
            if self._first_exposure_s is None:
                raise RuntimeError("the view has not been exposed yet")
            return self._first_exposure_s


def _next_frame(source: VideoCaptureSource, black: bool) -> Frame:
    """The next frame that shows black (or, with ``black`` False, anything else)."""
    while True:
        frame = source.read()
        if (int(frame.image.max()) < BLACK_MAX) == black:
            return frame


def _compare(config: CellConfig, direct: np.ndarray, streamed: np.ndarray) -> tuple[tuple[float, ...], bool, float]:
    extractor = extractor_for(config)
    mine, _ = extractor.extract(direct)
    theirs, _ = extractor.extract(streamed)
    found_direct, found_streamed = mine.corners_visible, theirs.corners_visible
    both = found_direct & found_streamed
    corner_diff = np.linalg.norm(mine.corners_px[both] - theirs.corners_px[both], axis=1)
    spot_diff = float(np.linalg.norm(mine.laser_spot_px - theirs.laser_spot_px))  # NaN when either lacks it
    return tuple(float(d) for d in corner_diff), bool(np.array_equal(found_direct, found_streamed)), spot_diff


def bench_stream(config: CellConfig, views: int = 24, quality: int = 100, seed: int = 0) -> dict[str, Any]:
    """Serve ``views`` rendered views through an MJPEG stream at JPEG ``quality`` and
    compare the features extracted from the rendered and the streamed images."""
    if isinstance(views, bool) or not isinstance(views, int) or views < 1:
        raise ValueError(f"views must be an integer >= 1, got {views!r}")
    cell = SimulatedCell(config, seed)
    camera = SimulatedCamera(cell, seed=seed)
    images = []
    for cMo in views_around_desired(views, seed):
        cell.place_camera(cMo)
        images.append(camera.read().image)
    black = np.zeros_like(images[0])
    screen = _Screen(black)
    load_before = os.getloadavg()[0]
    results = []
    with (
        CameraStream(screen, fps=FPS, exposure_latency_s=0.0, jpeg_quality=quality) as stream,
        VideoCaptureSource(stream.url, reconnect_attempts=0) as source,
    ):
        for image in images:
            screen.blank()
            _next_frame(source, black=True)
            screen.show(image)
            streamed = _next_frame(source, black=False)
            corners, agree, spot = _compare(config, image, streamed.image)
            results.append(
                ViewResult(corners, agree, spot, len(encode_jpeg(image, quality)), streamed.timestamp_s - screen.first_exposure_s)
            )
    return _summary(results, quality, images[0].shape, load_before)


def _summary(results: list[ViewResult], quality: int, shape: tuple[int, ...], load_before: float) -> dict[str, Any]:
    corners = np.array([d for r in results for d in r.corner_diff_px])
    spots = np.array([r.spot_diff_px for r in results if not math.isnan(r.spot_diff_px)])
    latency_ms = 1000.0 * np.array([r.exposure_to_read_s for r in results])

    def px(values: np.ndarray) -> dict[str, float | int | None]:
        if values.size == 0:
            return {"median_px": None, "max_px": None, "n": 0}
        return {"median_px": round(float(np.median(values)), 4), "max_px": round(float(np.max(values)), 4), "n": int(values.size)}

    return {
        "views": len(results),
        "jpeg_quality": quality,
        "image_size": f"{shape[1]}x{shape[0]}",
        "corners": {**px(corners), "views_disagreeing": sum(not r.corners_agree for r in results)},
        "spot": px(spots),
        "jpeg_kib_median": round(float(np.median([r.jpeg_bytes for r in results])) / 1024.0, 1),
        "exposure_to_read": {"median_ms": round(float(np.median(latency_ms)), 2), "max_ms": round(float(np.max(latency_ms)), 2)},
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "cpu_count": os.cpu_count(),
    }
