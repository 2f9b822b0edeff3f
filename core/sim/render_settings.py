"""How the synthetic camera renders: the scene's greys and the sensor's effects, one value."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RenderSettings:
    """How the synthetic camera renders. Grey levels are 0..255 before lighting.

    supersample: the rasteriser computes exact area coverage, so 1 is already exact for
        polygon edges; k > 1 renders at k times the resolution and area-averages
        (cv2.INTER_AREA) down, kept for comparison and for very strong distortion.
    blur_sigma_px: optical blur, a Gaussian of this sigma (px) on the whole frame.
    noise_sigma: additive Gaussian sensor noise in grey levels (then clipped to 0..255).
    lighting_gradient: relative strength s of uneven lighting: a smooth multiplicative
        field 1 + s (0.5 g - 0.5 r^2), g a linear ramp in [-1, 1] along
        ``lighting_angle_deg`` and r the distance from the image centre over the half
        diagonal; it spans [1 - s, 1 + s/2]. The laser spot is not affected.
    spot_sigma_px, spot_amplitude: the laser spot (see sensor.py).
    light_azimuth_deg: direction in the horizontal plane of B from which the fixed
        light comes; side faces facing it are brighter.
    edge_segment_px: length of the chords that approximate a distorted straight edge.
    mark_vertices: vertices of the polygon standing for the orientation mark.
    board_white_grey, board_black_grey: the printed checkerboard's paper and ink.
    near_m: the near clipping plane (m in front of the camera).
    """

    supersample: int = 1
    blur_sigma_px: float = 0.0
    noise_sigma: float = 0.0
    lighting_gradient: float = 0.0
    lighting_angle_deg: float = 30.0
    spot_sigma_px: float = 1.2
    spot_amplitude: float = 800.0
    background_grey: float = 0.0
    table_grey: float = 60.0
    top_grey: float = 205.0
    side_grey_dark: float = 110.0
    side_grey_bright: float = 170.0
    mark_grey: float = 35.0
    metal_grey: float = 85.0
    metal_side_shading: float = 0.15
    pocket_floor_grey: float = 55.0
    board_white_grey: float = 215.0
    board_black_grey: float = 25.0
    light_azimuth_deg: float = 60.0
    edge_segment_px: float = 6.0
    mark_vertices: int = 64
    near_m: float = 1e-3

    def __post_init__(self) -> None:
        if int(self.supersample) != self.supersample or self.supersample < 1:
            raise ValueError(f"supersample must be a whole number >= 1, got {self.supersample!r}")
        for name in ("blur_sigma_px", "noise_sigma", "lighting_gradient"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        if self.lighting_gradient >= 1.0:
            raise ValueError(f"lighting_gradient must be below 1, got {self.lighting_gradient!r}")
        for name in ("spot_sigma_px", "edge_segment_px", "near_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive, got {value!r}")
        if self.mark_vertices < 8:
            raise ValueError(f"mark_vertices must be at least 8, got {self.mark_vertices!r}")
