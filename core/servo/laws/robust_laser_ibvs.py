"""The switching IBVS with laser, robust to calibration error: beyond the thesis.

The thesis's law (core/servo/laws/laser_ibvs.py, section 4.4) is robust to calibration
error on its own task 2 (section 5.2.2); on random scenes the camera sees, and with
the model off by Table 5-3's or Table 5-5's amounts, three parts of it break
(docs/thesis-notes.md, "The robust law"):

- the laser spot is seen but the wrong model cannot triangulate it (the viewing ray
  through the spot meets the model's beam behind the laser), so stage 1 takes it for
  unseen and aims at where the model believes the beam runs, which can be beside the
  part, where no spot ever appears;
- stage 2 balances its translation (eq. 4-42) against its rotation (eq. 4-48) with the
  spot 12 .. 15 px from its place, or regulates a spot held while the part hides it;
- stage 3's constant interaction matrix at the desired features (eqs. 4-50, 4-51),
  like the mean of the current and desired ones, is built on the model's normalized
  coordinates: with the principal point 60 px off and the view still 30 deg round the
  part from the desired direction, its weakest direction (the turn about the part,
  which a 20 mm face shows only in its perspective) takes the wrong sign, and the
  camera turns away until the corners leave the image.

This law keeps stage 1 (1.A, 1.B, 1.C: eqs. 4-22 .. 4-38, with the reading of
docs/thesis-notes.md section 5) and changes what follows:

- a spot seen is a spot: stage 1 turns by its pixel, which the model does not need to
  triangulate (the imaginary features of Fig. 4-5 are pixels);
- once stage 1 has aligned (eq. 4-27, or turning no longer helps), or has aimed at the
  beam and still sees no spot, the law finishes with 2.5D visual servoing (Malis,
  Chaumette & Boudet 1999; core/servo/laws/hybrid.py, the thesis's second method):
  the rotation from the homography of the taught corners to the current ones, the
  translation on the reference point's image and log(Z / Z*), with Z = (Z / Z*) Z* and
  Z* the laser depth taught at the desired pose. Wrong intrinsics turn the estimated
  rotation into a conjugate of the true one (the same angle), so the rotation and
  translation stay decoupled and converge; the pixel error still decides the end,
  at the same final threshold;
- the loop's retreat test reads the camera's distance to the part instead of the
  image area (``distance_m``, from the viewing rays' spread), so turning the part from
  the image's edge to its centre or looking at it tilted is not a retreat.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import DesiredImage, ImageFeatures
from vservo.core.servo.laws.base import ControlOutput, Stage
from vservo.core.servo.laws.hybrid import Hybrid25D
from vservo.core.servo.laws.laser_ibvs import LaserIbvs


def view_spread_rad(camera: CameraModel, corners_px: Matrix) -> float:
    """The largest angle between the viewing rays of two corners (rad), NaN unless all are seen.

    Unlike the image area it does not change when the camera turns in place (the part
    moved to the image's centre looks smaller in pixels, not in angle), and of a tilted
    face it keeps the diagonal that is foreshortened least. A wrong focal length scales
    it by about the same factor everywhere, so ratios of it stand.
    """
    if np.isnan(corners_px).any():
        return float("nan")
    rays = camera.ray(corners_px)
    return float(np.arccos(np.clip(rays @ rays.T, -1.0, 1.0).min()))


@dataclass(frozen=True)
class RobustLaserIbvs(LaserIbvs):
    """The switching IBVS with laser, robust to calibration error (the module's docstring)."""

    def distance_m(self, features: ImageFeatures, desired: DesiredImage) -> float:
        """The camera's distance to the part: Z* times the desired view's spread over the
        current one's (NaN unless every corner is seen)."""
        spread = view_spread_rad(self.camera, features.corners_px)
        return desired.depth_m * view_spread_rad(self.camera, desired.corners_px) / spread

    def step(self, features: ImageFeatures, desired: DesiredImage, stage: Stage | None) -> ControlOutput:
        return replace(super().step(features, desired, stage), distance_m=self.distance_m(features, desired))

    def _spot_seen(self, features: ImageFeatures) -> bool:
        """A spot seen, triangulated or not: stage 1 turns by its pixel."""
        return features.spot_seen

    def _stage_1(self, features: ImageFeatures, desired: DesiredImage, error_px: float) -> ControlOutput:
        output = super()._stage_1(features, desired, error_px)
        aimed = output.stage is Stage.CENTRE_1B and output.stage_error <= self.f0_px
        if aimed and not features.spot_seen and features.all_corners_visible:
            # The model's beam is not the cell's: it lands beside the part, out of sight.
            return self._stage_3(features, desired, error_px, note="1B -> 3: aimed at the beam, its spot still not seen")
        return output

    def _turning_helps(self, turning_px: float, stage_error: float) -> bool:
        """Whether the turn still removes at least half of ||f_id - f||: the rest is the
        pattern's shape, or a spot hopping across the part's edge (the beam grazing it,
        the imaginary features jumping with it from one cycle to the next)."""
        return turning_px > max(self.f0_turn_px, 0.5 * stage_error)

    def _aligned(self, features: ImageFeatures, desired: DesiredImage, error_px: float, why: str) -> ControlOutput:
        """Stage 1.A is done: 2.5D takes the camera the rest of the way (no stage 2)."""
        return self._stage_3(features, desired, error_px, note=f"1A -> 3: {why}")

    def _stage_3(self, features: ImageFeatures, desired: DesiredImage, error_px: float, note: str) -> ControlOutput:
        """2.5D visual servoing on the corners (Malis 1999), labelled stage 3."""
        output = Hybrid25D(self.camera, self.k_final, self.final_threshold_px).step(features, desired, None)
        notes = "; ".join(text for text in (note, output.note) if text)
        return replace(output, stage=Stage.FINISH_3, note=notes)
