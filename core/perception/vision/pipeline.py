"""From one camera image to the features a control law sees (sections 4.3, 4.4, 5.3).

The laser spot by a fixed-level threshold, the four top-face corners (ordered by the
part's orientation mark, or by the last frame's corners when the mark is hidden), the
visible object region by image moments, and the spot's depth triangulated with the
NOMINAL laser and camera. A detector that fails leaves its features NaN with a reason;
the control law decides what it can do without them, the loop never sees an exception.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import Matrix, rot_x, transform
from vservo.core.perception.camera_source import Frame, FrameSource
from vservo.core.perception.features import ImageFeatures, laser_depth, pixel_or_none
from vservo.core.perception.vision.corners import CornerDetection, detect_corners
from vservo.core.perception.vision.region import RegionDetection, detect_object_region
from vservo.core.perception.vision.spot import SpotDetection, detect_laser_spot


@dataclass(frozen=True)
class VisionReport:
    """Every detector's verdict on one frame, for logs, recordings and the UI."""

    spot: SpotDetection
    corners: CornerDetection
    region: RegionDetection

    def as_dict(self) -> dict:
        return {
            "laser_spot": {
                "px": pixel_or_none(self.spot.spot_px),
                "confidence": self.spot.confidence,
                "reason": self.spot.reason,
            },
            "corners": {
                "px": [pixel_or_none(c) for c in self.corners.corners_px],
                "confidence": self.corners.confidence,
                "reason": self.corners.reason,
                "mark_px": pixel_or_none(self.corners.mark_px),
            },
            "region_centroid": {
                "px": pixel_or_none(self.region.region.centroid_px),
                "area_px2": round(float(self.region.region.area_px2), 3),
                "touches_border": self.region.touches_border,
                "confidence": self.region.confidence,
                "reason": self.region.reason,
            },
        }


def winding_of(corners_px: Matrix) -> int:
    """+1 if the corners run with a positive signed area in (u, v), v down; -1 otherwise."""
    u, v = corners_px[:, 0], corners_px[:, 1]
    return 1 if np.sum(u * np.roll(v, -1) - np.roll(u, -1) * v) > 0 else -1


def front_winding(corners_o: Matrix) -> int:
    """The winding of a planar face's corners seen from its front (its +z side in O).

    A turn of the camera about its axis keeps it, so the part model alone fixes the
    order in which detected corners must come to match the taught ones.
    """
    cMo = transform(rot_x(np.pi), (0.0, 0.0, 1.0))  # a camera 1 m in front, looking down -z of O
    cP = corners_o @ cMo[:3, :3].T + cMo[:3, 3]
    return winding_of(cP[:, :2] / cP[:, 2:])


@dataclass(frozen=True)
class ImageFeatureExtractor:
    """The detectors with their settings, on the nominal camera and laser.

    winding is the turning sense of the part's corners seen from the front
    (``front_winding`` of the model), so detected corners come in the model's order.
    """

    camera: CameraModel
    laser: LaserPointer
    winding: int = 1
    spot_threshold: int = 250
    region_threshold: int = 100

    def extract(self, image: np.ndarray, previous_corners_px: Matrix | None = None) -> tuple[ImageFeatures, VisionReport]:
        spot = detect_laser_spot(image, threshold=self.spot_threshold)
        corners = detect_corners(image, spot=spot, previous_px=previous_corners_px, winding=self.winding)
        region = detect_object_region(image, threshold=self.region_threshold)
        features = ImageFeatures(
            corners_px=corners.corners_px,
            laser_spot_px=spot.spot_px,
            laser_depth_m=laser_depth(self.laser, self.camera, spot.spot_px),
            region=region.region,
            corner_depths_m=np.full(4, np.nan),  # a camera gives no per-corner range
            reference_px=np.full(2, np.nan),
        )
        return features, VisionReport(spot, corners, region)


class CameraPerception:
    """Features from a camera source, frame after frame (it ignores the measurement).

    It remembers the last frame's corners, the tracking that keeps their order when the
    orientation mark is hidden (under the laser spot, say), and the last frame and report
    (for recordings and the UI).
    """

    def __init__(self, source: FrameSource, extractor: ImageFeatureExtractor) -> None:
        self.source = source
        self.extractor = extractor
        self.previous_corners_px: Matrix | None = None
        self.last_report: VisionReport | None = None
        self.last_frame: Frame | None = None
        self.uses_projection = False

    def perceive(self, measurement: object, motion_ended_s: float) -> ImageFeatures:
        """The features of the first frame the source exposed at or after ``motion_ended_s``
        (the robot's clock): never a frame that waited in a buffer through the motion."""
        return self.perceive_frame(self.source.read_after(motion_ended_s))

    def perceive_frame(self, frame: Frame) -> ImageFeatures:
        """The features of ``frame``, tracked from the frames before it."""
        self.last_frame = frame
        features, self.last_report = self.extractor.extract(frame.image, self.previous_corners_px)
        if features.all_corners_visible:
            self.previous_corners_px = features.corners_px
        return features
