"""Servoing at the camera's rate: each frame's features with the robot's pose at its exposure.

Look-and-move waits for the arm to stop, so the pose the robot reports after the motion is
the pose every later frame was taken from. A velocity-controlled arm streamed a twist every
frame never stops: the frame was exposed a camera latency ago, and the arm has moved since.
``ExposureMatchedCamera`` is the loop's measurement and its perception at once: the
measurement takes the next frame (the first exposed after the last one used, none skipped
waiting for a motion's end) and reads the flange pose at that frame's exposure time from
the robot's state history (a UR's RTDE packages, SafetyLayer.pose_at); the perception gives
that frame's features. The control law then sees features and pose of the same instant.
"""

from __future__ import annotations

from vservo.core.perception.camera_source import Frame
from vservo.core.perception.features import ImageFeatures
from vservo.core.perception.measurement import Measurement
from vservo.core.perception.vision.pipeline import CameraPerception
from vservo.core.robot.safety import SafetyLayer

# A frame newer than the last one used: its exposure later by at least this (s).
NEWER_S = 1e-6


class ExposureMatchedCamera:
    """The loop's MeasurementSource and Perception for a streamed servo (module docstring)."""

    uses_projection = False

    def __init__(self, perception: CameraPerception, robot: SafetyLayer) -> None:
        self.perception, self.robot = perception, robot
        self._after_s = robot.clock_s()  # the first frame: one exposed from now on
        self._frame: Frame | None = None

    def measure(self, look: bool = False) -> Measurement:
        """The next frame's exposure time, and the flange pose then (the joints of the arm's model for it)."""
        frame = self._frame = self.perception.source.read_after(self._after_s)
        self._after_s = frame.timestamp_s + NEWER_S
        bMe = self.robot.pose_at(frame.timestamp_s)
        return Measurement.flange_only(frame.timestamp_s, self.robot.model_joints(bMe), bMe)

    def perceive(self, measurement: Measurement, motion_ended_s: float) -> ImageFeatures:
        """The features of the frame ``measure`` took (the stream's own order, not the motion's end)."""
        if self._frame is None:
            raise RuntimeError("perceive before measure: the frame comes with the measurement")
        return self.perception.perceive_frame(self._frame)
