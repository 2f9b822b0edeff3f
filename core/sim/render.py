"""Synthetic monochrome camera: the 8-bit image the TRUE camera sees of the cell.

The simulator holds the true cell; this module turns it into pixels, so that image
processing (corner and spot detection) can be exercised on something that looks like a
camera frame, and measured against the exact projections of ``CameraModel.project``.

A frame is made in two stages, one module each: raster.py draws the scene's boxes with
exact pixel coverage into a float frame (clipping, lens distortion, painter's order),
and sensor.py applies what the sensor and the grabber add to it (uneven lighting, the
laser spot, blur, motion smear, noise, 8-bit quantisation, dropped and repeated frames).
The settings of both are one ``RenderSettings`` (render_settings.py).

Speed (2-core machine, 640 x 480, median of 50): 1.5 ms for the task-1 desired view,
3.5-4 ms for an oblique view of cube, metal part and table with distortion, 5-6 ms for a
view of the laid checkerboard with distortion; noise, blur and lighting together add ~1.5 ms.
"""

from __future__ import annotations

import numpy as np

from vservo.core.cell.scene import Scene
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import Matrix, inverse
from vservo.core.sim.raster import SceneRasterizer
from vservo.core.sim.render_settings import RenderSettings
from vservo.core.sim.sensor import FaultKind, FrameFault, SensorEffects


class SceneRenderer:
    """Renders the true camera's 8-bit monochrome frame of a scene (module docstring)."""

    def __init__(self, camera: CameraModel, settings: RenderSettings = RenderSettings()) -> None:
        self.camera = camera
        self.settings = settings
        self.rasterizer = SceneRasterizer(camera, settings)
        self.sensor = SensorEffects(camera.image_size, settings)
        self._last_frame: np.ndarray | None = None

    @property
    def last_frame(self) -> np.ndarray | None:
        """The last frame really rendered (what a REPEAT fault hands out again)."""
        return None if self._last_frame is None else self._last_frame.copy()

    def render(
        self,
        scene: Scene,
        bMc: Matrix,
        spot_b: Matrix | None,
        rng: np.random.Generator,
        fault: FrameFault | None = None,
    ) -> np.ndarray:
        """The (height, width) uint8 frame of ``scene`` from a camera at ``bMc``.

        ``spot_b`` is the laser spot in B (None when the simulator finds it hidden); it
        is drawn at its projection. All randomness (sensor noise) comes from ``rng``.
        """
        width, height = self.camera.image_size
        if fault is not None and fault.kind is FaultKind.DROPPED:
            return np.zeros((height, width), dtype=np.uint8)
        if fault is not None and fault.kind is FaultKind.REPEAT:
            if self._last_frame is None:
                return np.zeros((height, width), dtype=np.uint8)
            return self._last_frame.copy()
        smear = fault if fault is not None and fault.kind is FaultKind.SMEAR else None
        pad = self.sensor.margin_px(smear.smear_px if smear is not None else 0.0)
        bMc = np.asarray(bMc, dtype=float)
        image = self.rasterizer.draw(scene, bMc, pad)
        spot_uv = None if spot_b is None else self.project_b(bMc, np.asarray(spot_b, dtype=float))[0]
        frame = self.sensor.expose(image, pad, spot_uv, smear, rng)
        self._last_frame = frame
        return frame.copy()

    def project_b(self, bMc: Matrix, points_b: Matrix) -> np.ndarray:
        """Pixels (N, 2) of points given in B, seen from bMc (a convenience for callers)."""
        cMb = inverse(np.asarray(bMc, dtype=float))
        points = np.atleast_2d(np.asarray(points_b, dtype=float))
        return self.camera.project(points @ cMb[:3, :3].T + cMb[:3, 3])
