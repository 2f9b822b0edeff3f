"""The camera brought over the part by the image alone: the teaching aid "View the part".

The desired view the Teach tab computes from a part it sees ("Flange to view it") rests on
the nominal camera and hand-eye: on a cell never commissioned, with the focal length 20 %
off, it sends the flange tens of millimetres too low or aside (with Table 5-5's errors, the
cup below the workspace's floor). This aid needs no calibration: it moves the flange in
straight translations (its orientation kept: tool down) until, in the image,

- the laser spot lies on the part's top-face centre (the crossing of its diagonals), so
  that the spot is on the part at the desired view, where Z* is measured, and the thesis's
  stage 1 (the spot onto the part, section 4.4.1) has nothing left to do at the end; and
- the part spans ``target_scale_px`` (the RMS distance of its corners to their centroid),

a look-and-move servo of the three features f = (c - s, scale) on the translation t of the
flange, whose Jacobian J = df/dt is measured by three small jogs and kept up to date by
Broyden's rule (J += (df - J dt) dt^T / |dt|^2) as the arm moves: t += -gain J^-1 (f - f*).
Until the spot is seen, the image's centre stands in for it.

A frame that lags the arm (a busy host, docs/vision.md) shows the part where it was before
a move: a jog would then measure no motion and leave J singular. A move whose frame shows
less than a third of the motion J predicts (for a jog sideways or down, less than
MIN_JOG_PX; a step J predicts below MIN_JOG_PX is not judged) is looked at once more; a
second such frame is a ViewError naming the lag, never a step made from it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import ImageFeatures, pattern_scale
from vservo.core.production.placement_check import diagonals_crossing

JOG_M = 0.010  # each of the three jogs that measure J
GAIN = 0.8
MAX_STEP_M = 0.030  # no move longer: J is a local measure
DONE_PX = 0.5  # every feature within this of its target ends the servo
MAX_MOVES = 25
# Two frames from one pose differ by the detector's noise, tenths of a pixel; a 10 mm jog
# sideways from a view of the part (a few tenths of a metre above it) moves it 10 px or more.
MIN_JOG_PX = 1.0


class ViewError(VservoError, RuntimeError):
    """The camera could not be brought over the part; the message says why and what to do."""


@dataclass(frozen=True)
class ViewMotions:
    """What the aid drives: move the flange (a linear move), read its pose, the features of a
    fresh frame."""

    move_to: Callable[[Matrix], None]
    read_pose: Callable[[], Matrix]
    features: Callable[[], ImageFeatures]


def view_features(features: ImageFeatures, image_centre_px: Matrix) -> Matrix:
    """f = (c - s, scale): the part's centre from the spot (the image's centre until the spot
    is seen), and the part's spread (px)."""
    if not features.all_corners_visible:
        raise ViewError("the camera must see the part's four corners: jog until the page says Part seen, then try again")
    spot = features.laser_spot_px if features.spot_seen else np.asarray(image_centre_px, dtype=float)
    return np.append(diagonals_crossing(features.corners_px) - spot, pattern_scale(features.corners_px))


def view_part(cell: ViewMotions, target_scale_px: float, image_centre_px: Matrix) -> tuple[Matrix, int]:
    """The flange pose over the part (module docstring) and the moves it took."""
    target = np.array([0.0, 0.0, target_scale_px])
    bMe = np.array(cell.read_pose(), dtype=float)

    spot_seen = False

    def look() -> Matrix:
        nonlocal spot_seen
        features = cell.features()
        spot_seen = features.spot_seen
        return view_features(features, image_centre_px)

    def seen_at(translation: Matrix, f_before: Matrix, least_px: float) -> Matrix:
        """The features once moved to ``translation``, from a frame that shows the image
        moved by at least ``least_px`` from ``f_before`` (looked at twice at most)."""
        pose = bMe.copy()
        pose[:3, 3] = translation
        cell.move_to(pose)
        for _ in range(2):
            f_now = look()
            if np.linalg.norm(f_now - f_before) >= least_px:
                return f_now
        raise ViewError(
            f"the part moved {np.linalg.norm(f_now - f_before):.1f} px in the image where the move should have moved "
            f"it {least_px:.1f} px or more: the camera's frames lag the arm (a busy host); try again"
        )

    t = bMe[:3, 3].copy()
    f = look()
    J = np.empty((3, 3))
    f_jogged = f
    for axis in range(3):
        jog = np.zeros(3)
        jog[axis] = JOG_M if axis < 2 else -JOG_M  # down, not up: toward the part
        f_jogged = seen_at(t + jog, f_jogged, MIN_JOG_PX)  # each jog from the last one's pose
        J[:, axis] = (f_jogged - f) / jog[axis]
    f = seen_at(t, f_jogged, float(np.linalg.norm(f_jogged - f)) / 3.0)  # back by the last jog
    for move in range(MAX_MOVES):
        error = f - target
        if np.all(np.abs(error) < DONE_PX) and spot_seen:
            bMe[:3, 3] = t
            return bMe, move
        try:
            step = -GAIN * np.linalg.solve(J, error)
        except np.linalg.LinAlgError:  # the jogs moved the features along one line: no view to servo on
            raise ViewError("the part's image did not move as the arm jogged in three directions: try again") from None
        step *= min(1.0, MAX_STEP_M / max(float(np.linalg.norm(step)), 1e-12))
        expected_px = float(np.linalg.norm(J @ step))  # a small final step's frame is not judged
        f_new = seen_at(t + step, f, expected_px / 3.0 if expected_px >= MIN_JOG_PX else 0.0)
        J += np.outer((f_new - f) - J @ step, step) / float(step @ step)
        t, f = t + step, f_new
    raise ViewError(
        f"the camera did not settle over the part in {MAX_MOVES} moves (still {np.abs(f - target).max():.1f} px off): "
        "jog nearer the part and try again"
    )
