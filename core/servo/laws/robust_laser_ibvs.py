"""The switching IBVS with laser, robust to calibration error: beyond the thesis.

The thesis's law (core/servo/laws/laser_ibvs.py, section 4.4) is robust to calibration
error on its own task 2 (section 5.2.2); on random scenes the camera sees, with the model
off by Table 5-3's or Table 5-5's amounts, it breaks in four places
(docs/thesis-notes.md, "The robust law"):

- the laser spot is seen but the wrong model cannot triangulate it (the viewing ray
  through the spot meets the model's beam behind the laser), so stage 1 takes it for
  unseen and aims at where the model believes the beam runs, which can be beside the
  part, where no spot ever appears;
- stage 1.A turns back and forth when the beam grazes the part's edge: the spot hops
  between the top face and the table, and the imaginary features (Fig. 4-5) with it;
- stage 2 balances its translation (eq. 4-42) against its rotation (eq. 4-48) with the
  spot 12 .. 15 px from its place, or regulates a spot held while the part hides it;
- stage 3's constant interaction matrix at the desired features (eqs. 4-50, 4-51),
  like the mean of the current and desired ones, is built on the model's normalized
  coordinates: with the principal point 60 px off and the view still 30 deg round the
  part from the desired direction, its weakest direction (the turn about the part,
  which a 20 mm face shows only in its perspective) takes the wrong sign, and the
  camera turns away until the corners leave the image.

This law keeps the turns of stage 1 (1.A: eqs. 4-22 .. 4-29 with the reading of
docs/thesis-notes.md section 5; 1.B: eqs. 4-30 .. 4-36; 1.C: eqs. 4-37, 4-38) and
changes what they aim at and what follows:

- stage 1.B, while a corner is out of view, turns the visible region's centroid onto the
  image centre: the spot (or the model's beam) lies far off the centre at a close start,
  and a part 200 px wide centred there cannot be wholly in view;
- a spot seen is a spot: stage 1.A turns by its pixel, which the model does not need to
  triangulate (the imaginary features are pixels); it is skipped when the aligned
  pattern would leave the image, and hands over once its turn removes less of
  ||f_id - f|| than it leaves;
- then, or as soon as every corner is seen without a spot, the law finishes with 2.5D
  visual servoing (Malis, Chaumette & Boudet 1999; core/servo/laws/hybrid.py, the
  thesis's second method), labelled stage 3: the rotation from the homography of the
  taught corners to the current ones, the translation on the reference point's image
  and log(Z / Z*), with Z = (Z / Z*) Z* and Z* the laser depth taught at the desired
  pose. Wrong intrinsics turn the estimated rotation into a conjugate of the true one
  (the same angle), so the rotation and translation stay decoupled and converge; the
  pixel error still decides the end, at the same final threshold. There is no stage 2;
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
from vservo.core.servo.laws.laser_ibvs import LaserIbvs, imaginary_features


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
        """Stage 1 with the robust targets: 1.B onto the image centre (eqs. 4-30 .. 4-36), then
        1.A on the imaginary features (eqs. 4-26 .. 4-29) when there is a spot and they fit in
        the image, else 3 once the part is centred."""
        centre = np.array([self.camera.intrinsics.u0, self.camera.intrinsics.v0])
        if not features.all_corners_visible:
            return self._stage_1b(features, error_px, centre, note="centring the part")
        if features.spot_seen and self.camera.in_view(imaginary_features(desired, features)).all():
            return super()._stage_1(features, desired, error_px)
        if features.spot_seen:  # the aligned pattern would leave the image: a close start
            return self._stage_3(features, desired, error_px, note="1 -> 3: the aligned pattern would leave the image")
        # No spot to turn by: 2.5D, which needs none, from a part centred in the view (from
        # the image's edge its first turn can take the part out).
        if np.linalg.norm(features.region.centroid_px - centre) > self.f0_px:
            return self._stage_1b(features, error_px, centre, note="every corner seen, no spot: centring the part")
        return self._stage_3(features, desired, error_px, note="1 -> 3: every corner seen, no spot")

    def _turning_helps(self, turning_px: float, stage_error: float) -> bool:
        """Whether the turn still removes more of ||f_id - f|| than it leaves: linearised, the
        part a turn cannot remove is sqrt(||e||^2 - turning^2), so more than 1/sqrt(2) of it.
        What a turn cannot remove is the pattern's shape, or a spot hopping across the part's
        edge (the beam grazing it, the imaginary features jumping with it every cycle)."""
        return turning_px > max(self.f0_turn_px, stage_error / np.sqrt(2.0))

    def _aligned(self, features: ImageFeatures, desired: DesiredImage, error_px: float, why: str) -> ControlOutput:
        """Stage 1.A is done: 2.5D takes the camera the rest of the way (no stage 2)."""
        return self._stage_3(features, desired, error_px, note=f"1A -> 3: {why}")

    def _stage_3(self, features: ImageFeatures, desired: DesiredImage, error_px: float, note: str) -> ControlOutput:
        """2.5D visual servoing on the corners (Malis 1999), labelled stage 3."""
        output = Hybrid25D(self.camera, self.k_final, self.final_threshold_px).step(features, desired, None)
        notes = "; ".join(text for text in (note, output.note) if text)
        return replace(output, stage=Stage.FINISH_3, note=notes)
