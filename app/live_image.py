"""The live camera image as the operator sees it: the frame with what the servo is doing drawn on it.

Drawn with OpenCV on the decoded JPEG (grey camera image, colour overlays):

- detected corners: green rings, numbered in the vision's order (corner 0 carries the mark);
- desired corners: red squares joined into the taught outline, where the corners must go;
- corner trajectories so far in this run: one thin line per corner;
- laser spot: a yellow cross; its target (the taught spot): a yellow ring, joined to the spot.

Pixels arrive as the channel's FrameMeta carries them, NaN for a feature not seen (a
recording's, replayed, as lists with -1 or None).
Drawing uses fixed-point coordinates (OpenCV's ``shift``) so a marker sits within 1/16 px
of the sub-pixel measurement. Viser-free.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, TypeGuard

import cv2
import numpy as np

from vservo.core.production.protocol import FrameMeta

SHIFT = 4  # fixed-point bits of the drawn coordinates
SEEN_BGR = (60, 220, 60)
DESIRED_BGR = (60, 60, 255)
SPOT_BGR = (0, 230, 255)
TRAIL_BGR = ((255, 200, 0), (255, 120, 200), (200, 255, 120), (120, 180, 255))  # one per corner
JPEG_QUALITY = 80


def pixel_array(values: object, shape: tuple[int, ...]) -> np.ndarray | None:
    """Pixels as floats with NaN for the unseen (negative or None), or None when absent entirely."""
    if values is None:
        return None
    array = np.array([np.nan if v is None else v for v in np.ravel(np.array(values, dtype=object))], float)
    if array.size != int(np.prod(shape)):
        return None
    array = array.reshape(shape)
    array[array < 0] = np.nan
    return array


@dataclass(frozen=True)
class Overlay:
    """What to draw on one frame (pixels; NaN rows are features not seen)."""

    corners_px: np.ndarray | None = None  # (4, 2)
    laser_spot_px: np.ndarray | None = None  # (2,)
    desired_corners_px: np.ndarray | None = None  # (4, 2)
    desired_laser_px: np.ndarray | None = None  # (2,)
    trail_px: np.ndarray | None = None  # (T, 4, 2)

    @classmethod
    def from_meta(cls, meta: FrameMeta) -> Overlay:
        """From what the controller saw in a frame (its shapes checked: a bad one is not drawn)."""
        trail = meta.trail_px
        return cls(
            corners_px=pixel_array(meta.corners_px, (4, 2)),
            laser_spot_px=pixel_array(meta.laser_spot_px, (2,)),
            desired_corners_px=pixel_array(meta.desired_corners_px, (4, 2)),
            desired_laser_px=pixel_array(meta.desired_laser_px, (2,)),
            trail_px=None if trail is None or len(trail) == 0 else pixel_array(trail, (len(trail), 4, 2)),
        )


def _fixed(point: np.ndarray) -> tuple[int, int]:
    return int(round(point[0] * (1 << SHIFT))), int(round(point[1] * (1 << SHIFT)))


def _seen(point: np.ndarray | None) -> TypeGuard[np.ndarray]:
    return point is not None and bool(np.all(np.isfinite(point)))


def decode(jpeg: bytes) -> np.ndarray:
    """A JPEG from the channel as an 8-bit grey image."""
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError("the camera frame from the controller is not a readable JPEG")
    return image


def draw(image: np.ndarray, overlay: Overlay) -> np.ndarray:
    """The frame (grey or BGR) as a BGR image with the overlay drawn on it."""
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    aa = cv2.LINE_AA
    if overlay.trail_px is not None and len(overlay.trail_px) > 1:
        for corner in range(4):
            track = overlay.trail_px[:, corner]
            track = track[np.all(np.isfinite(track), axis=1)]
            if len(track) > 1:
                fixed = np.round(track * (1 << SHIFT)).astype(np.int32).reshape(-1, 1, 2)
                cv2.polylines(canvas, [fixed], False, TRAIL_BGR[corner], 1, aa, SHIFT)
    desired = overlay.desired_corners_px
    if desired is not None and np.all(np.isfinite(desired)):
        outline = np.round(desired * (1 << SHIFT)).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(canvas, [outline], True, DESIRED_BGR, 1, aa, SHIFT)
        half = 6 << SHIFT
        for point in desired:
            x, y = _fixed(point)
            cv2.rectangle(canvas, (x - half, y - half), (x + half, y + half), DESIRED_BGR, 2, aa, SHIFT)
    if overlay.corners_px is not None:
        for index, point in enumerate(overlay.corners_px):
            if _seen(point):
                cv2.circle(canvas, _fixed(point), 7 << SHIFT, SEEN_BGR, 2, aa, SHIFT)
                cv2.putText(
                    canvas, str(index), (int(point[0]) + 9, int(point[1]) - 9), cv2.FONT_HERSHEY_SIMPLEX, 0.5, SEEN_BGR, 1, aa
                )
    spot, target = overlay.laser_spot_px, overlay.desired_laser_px
    if _seen(target):
        cv2.circle(canvas, _fixed(target), 10 << SHIFT, SPOT_BGR, 2, aa, SHIFT)
        if _seen(spot):
            cv2.line(canvas, _fixed(spot), _fixed(target), SPOT_BGR, 1, aa, SHIFT)
    if _seen(spot):
        arm = 8 << SHIFT
        x, y = _fixed(spot)
        cv2.line(canvas, (x - arm, y), (x + arm, y), SPOT_BGR, 2, aa, SHIFT)
        cv2.line(canvas, (x, y - arm), (x, y + arm), SPOT_BGR, 2, aa, SHIFT)
    _legend(canvas)
    return canvas


def _legend(canvas: np.ndarray) -> None:
    entries = (("seen", SEEN_BGR), ("desired", DESIRED_BGR), ("laser / target", SPOT_BGR))
    x = 8
    for text, colour in entries:
        cv2.putText(canvas, text, (x, canvas.shape[0] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
        x += 12 + cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)[0][0]


def encode_jpeg(image: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    """The drawn image as JPEG bytes, encoded once and sent to every browser."""
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("the live image could not be encoded as JPEG")
    return jpeg.tobytes()


def render(jpeg: bytes, meta: FrameMeta) -> bytes:
    """The channel's frame with its overlay, as JPEG: one call per frame for all browsers."""
    return encode_jpeg(draw(decode(jpeg), Overlay.from_meta(meta)))


def show_jpeg(handle: Any, jpeg: bytes) -> None:
    """Put already-encoded JPEG bytes in a viser image element. Its ``image`` setter would
    encode the array again per element; viser 1.1.1 is pinned, so its props are known."""
    handle._format = "jpeg"
    handle._data = jpeg
