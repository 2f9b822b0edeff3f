"""The switching IBVS with a laser pointer (thesis section 4.4, Appendix C).

Three stages, each a law of its own, switched on image errors:

- Stage 1.A (all corners seen): turn the camera (3 rotational DOF) until the corners sit
  on the imaginary desired features, the desired corners shifted by the current laser
  spot minus the desired spot (Fig. 4-5) and scaled to the current pattern (below); the laser then lies on the part where it lies
  in the desired image, and a half turn about the optical axis is done here by rotation
  rather than by IBVS's retreat (eqs. 4-26 .. 4-29). Switch when ||f_id - f|| <= f0.
- Stage 1.B (part of the object outside the image): turn the camera (2 DOF) to bring the
  visible object region's centroid (image moments, eqs. 4-33 .. 4-35) onto the laser
  spot (eqs. 4-30 .. 4-32, 4-36), until every corner is seen; then 1.A.
- Stage 1.C: during stage 1 the camera also translates by v = cTe x w (eqs. 4-37, 4-38),
  so that the end effector turns in place instead of swinging around the camera.
- Stage 2: translation from the stacked corners and laser spot with the laser depth
  (eqs. 4-39 .. 4-42, 4-23), rotation that keeps the spot on the corners' centroid
  (eqs. 4-45 .. 4-48), gains K1, K2 (eq. 4-49). Switch to 3 when ||f_d^l - f^l|| <= f0^l
  (eq. 4-43).
- Stage 3: classic IBVS with the constant interaction matrix at the desired features and
  depth (eqs. 4-50, 4-51) until ||f_d - f|| is below the final threshold.

Interpretation (docs/thesis-notes.md section 5). Fig. 4-5 shifts the desired corners to the
current spot; from 0.42 m the part's image is less than half the desired size and no
rotation can make the corners match that, so ||f_id - f|| would never fall below f0.
The imaginary features therefore also take the current pattern's scale (about the
spot): at the desired depth this is the construction of Fig. 4-5, and the stage then
regulates what rotation can change, which eq. 4-26 (a sum of errors) already hinted
at. Stage 1.A takes w_z from the orientation of the
pattern, the angle that turns the current corners onto the imaginary ones, and w_x, w_y
from the least squares of eq. 4-29 for what is left (the partitioning of Corke &
Hutchinson 2001): at a half turn about the optical axis every error is radial, the
least-squares w_z of eq. 4-29 is exactly zero, and only this turns the camera round as
Fig. 5-1 shows. And the laser spot is rigid with the camera, so a
rotation does not move the spot in the image, it moves the object. Stages 1.B and 2
therefore turn the camera so that the object centroid c moves onto the spot,
J^r(c) w = -K (c - f^l); the thesis writes the same goal as the spot moving onto the
centroid, with the lit point taken as stationary on the part. Taken literally, with the
signs of eqs. 4-36 and 4-48, the two terms would push the centroid away from the spot.

Every stage writes its error as current minus desired, e = s - s*, and commands
-K J+ e, the convention of every law here (ViSP's); the thesis writes s* - s with +K.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.interaction import pixel_interaction_matrix
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.features import DesiredImage, ImageFeatures, pattern_scale
from vservo.core.servo.laws.base import ControlOutput, Failure, SingularJacobian, Stage, checked_pinv, feature_error_px

# Rotation-only Jacobians do not depend on depth; any positive value fills the slot.
_ANY_DEPTH = 1.0


def rotational_jacobian(camera: CameraModel, uv: Matrix) -> Matrix:
    """J^r of eqs. 4-24 / 4-31: the rotational columns of the pixel interaction matrix."""
    return pixel_interaction_matrix(camera, uv, _ANY_DEPTH)[:, 3:]


def translational_jacobian(camera: CameraModel, uv: Matrix, Z: float) -> Matrix:
    """J^t of eq. 4-23 stacked for every point (eq. 4-42) at the common depth Z."""
    return pixel_interaction_matrix(camera, uv, Z)[:, :3]


def image_rotation(from_px: Matrix, to_px: Matrix) -> float:
    """Angle in (-pi, pi] of the plane rotation that best turns one point pattern onto
    another about their centroids (2D Procrustes), counter-clockwise in (u, v)."""
    a = from_px - from_px.mean(axis=0)
    b = to_px - to_px.mean(axis=0)
    return float(np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b)))


def _largest_extent(points_px: Matrix) -> float:
    """The largest distance between two of the points (px)."""
    return float(np.max(np.linalg.norm(points_px[:, None, :] - points_px[None, :, :], axis=2)))


def imaginary_features(desired: DesiredImage, features: ImageFeatures) -> Matrix:
    """The desired corners moved with the laser spot (Fig. 4-5) and scaled to the current
    pattern about the spot: where the corners are when the spot lies on the part as in
    the desired image, seen from the current distance."""
    scale = pattern_scale(features.corners_px) / pattern_scale(desired.corners_px)
    return features.laser_spot_px + scale * (desired.corners_px - desired.laser_spot_px)


@dataclass(frozen=True)
class LaserIbvs:
    """Settings of the switching law; gains and thresholds of section 5.2."""

    camera: CameraModel
    cTe: Matrix  # position of the flange E in the camera frame (stage 1.C)
    laser: LaserPointer  # where the beam runs, to aim it while its spot is not seen
    k_rotation_1a: float = 1.0  # K_l, eq. 4-29
    k_rotation_1b: float = 1.0  # K_l2, eq. 4-36
    k_translation: float = 1.0  # K1, eq. 4-49
    k_rotation: float = 1.0  # K2, eq. 4-49; raise it under a bad laser calibration
    k_final: float = 1.0  # stage 3
    f0_px: float = 10.0  # eq. 4-27
    f0_laser_px: float = 10.0  # eq. 4-43
    f0_turn_px: float = 1.0  # stages 1.A and 2 also end when their step moves the corners no more than this
    final_threshold_px: float = 1.0
    name: str = "laser"

    def step(self, features: ImageFeatures, desired: DesiredImage, stage: Stage | None) -> ControlOutput:
        error_px = feature_error_px(features, desired)
        try:
            if stage in (None, Stage.ALIGN_1A, Stage.CENTRE_1B):
                return self._stage_1(features, desired, error_px)
            if stage == Stage.APPROACH_2:
                return self._stage_2(features, desired, error_px, note="")
            return self._stage_3(features, desired, error_px, note="")
        except SingularJacobian as exc:
            return ControlOutput.stop(stage or Stage.ALIGN_1A, error_px, Failure.SINGULAR_JACOBIAN, str(exc))

    def _with_compensation(self, w: Matrix) -> Matrix:
        """Stage 1.C: v = cTe x w keeps the flange in place while the camera turns (eq. 4-38)."""
        return np.concatenate([np.cross(self.cTe, w), w])

    def _spot_seen(self, features: ImageFeatures) -> bool:
        """Whether stage 1 has a laser spot to turn by: one seen and triangulated with the model."""
        return features.laser_visible

    def _stage_1(self, features: ImageFeatures, desired: DesiredImage, error_px: float) -> ControlOutput:
        if not self._spot_seen(features):
            # The beam lands nowhere the camera sees (it passes beside the part and off the
            # table, from a camera looking across the cell): turn the part onto the beam's
            # image at the part's estimated depth. Once the camera looks at the part the
            # beam lands on or by it.
            aim_px = self._beam_at_part(features, desired)
            return self._stage_1b(features, error_px, aim_px, note="laser spot not seen: aiming")
        if not features.all_corners_visible:
            return self._stage_1b(features, error_px, features.laser_spot_px)

        # Stage 1.A: imaginary features, Fig. 4-5, at the scale of the current pattern.
        f_id = imaginary_features(desired, features)
        e = (features.corners_px - f_id).ravel()
        stage_error = float(np.linalg.norm(e))
        if stage_error <= self.f0_px:
            return self._aligned(features, desired, error_px, f"||f_id - f|| = {stage_error:.2f} px")
        J = rotational_jacobian(self.camera, features.corners_px)
        # The turn about the optical axis comes from the pattern's orientation: a least-
        # squares w_z vanishes at a half turn, where every error is radial (eq. 4-25).
        # An image pattern turns at -w_z (x right, y down), hence the sign.
        w_z = -self.k_rotation_1a * image_rotation(features.corners_px, f_id)
        # J_xy w_xy + J_z w_z = -K_l e (eq. 4-29), solved for what w_z leaves.
        w_xy = -checked_pinv(J[:, :2]) @ (self.k_rotation_1a * e + J[:, 2] * w_z)
        w = np.array([w_xy[0], w_xy[1], w_z])
        # What this turn still removes of e (linearised, per unit of gain). The rest is the
        # pattern's shape, which only a translation changes: a beam out of the camera's x-z
        # plane (a real laser mount) can leave more than f0 of it, and 1.A would turn forever.
        turning_px = float(np.linalg.norm(J @ w)) / self.k_rotation_1a
        if not self._turning_helps(turning_px, stage_error):
            why = f"turned as far as turning helps (||f_id - f|| = {stage_error:.2f} px)"
            return self._aligned(features, desired, error_px, why)
        return ControlOutput(self._with_compensation(w), Stage.ALIGN_1A, error_px, stage_error)

    def _turning_helps(self, turning_px: float, stage_error: float) -> bool:
        """Whether stage 1.A's turn still moves the corners by more than f0_turn_px."""
        return turning_px > self.f0_turn_px

    def _aligned(self, features: ImageFeatures, desired: DesiredImage, error_px: float, why: str) -> ControlOutput:
        """Stage 1.A is done (eq. 4-27, or turning no longer helps): on to stage 2."""
        return self._stage_2(features, desired, error_px, note=f"1A -> 2: {why}")

    def _beam_at_part(self, features: ImageFeatures, desired: DesiredImage) -> Matrix:
        """The beam's image point at the part's depth, estimated from the pattern's largest
        extent against the desired one (the extent a tilted view foreshortens least); at
        the desired depth Z* with fewer than two corners seen."""
        seen = features.corners_px[features.corners_visible]
        depth_m = desired.depth_m
        if len(seen) >= 2:
            depth_m *= _largest_extent(desired.corners_px) / _largest_extent(seen)
        origin, direction = self.laser.origin_c, self.laser.direction_c
        point_c = origin + direction * (depth_m - origin[2]) / direction[2]
        return self.camera.project(point_c[None, :])[0]

    def _stage_1b(self, features: ImageFeatures, error_px: float, spot_px: Matrix, note: str = "") -> ControlOutput:
        """Turn the visible region's centroid onto spot_px (eq. 4-36): the laser spot, or
        the beam's image at the part's depth while the spot is not seen."""
        region = features.region
        if not region.seen:
            return ControlOutput.stop(Stage.CENTRE_1B, error_px, Failure.FEATURES_LOST, "object not in the image")
        e = region.centroid_px - spot_px
        J = rotational_jacobian(self.camera, region.centroid_px)[:, :2]  # w_x, w_y only (eq. 4-31)
        w_xy = -self.k_rotation_1b * checked_pinv(J) @ e
        w = np.array([w_xy[0], w_xy[1], 0.0])
        return ControlOutput(self._with_compensation(w), Stage.CENTRE_1B, error_px, float(np.linalg.norm(e)), note=note)

    def _stage_2(self, features: ImageFeatures, desired: DesiredImage, error_px: float, note: str) -> ControlOutput:
        if not (features.all_corners_visible and features.laser_visible):
            return ControlOutput.stop(Stage.APPROACH_2, error_px, Failure.FEATURES_LOST, "corners or laser spot lost in stage 2")
        laser_error = features.laser_spot_px - desired.laser_spot_px
        laser_error_px = float(np.linalg.norm(laser_error))
        if laser_error_px <= self.f0_laser_px:
            switch = f"2 -> 3: ||f_d^l - f^l|| = {laser_error_px:.2f} px"
            return self._stage_3(features, desired, error_px, note=f"{note}; {switch}" if note else switch)

        # Translation: corners and laser spot as stationary points at the laser depth (4-42).
        points = np.vstack([features.corners_px, features.laser_spot_px])
        e_t = np.concatenate([(features.corners_px - desired.corners_px).ravel(), laser_error])
        v = -self.k_translation * checked_pinv(translational_jacobian(self.camera, points, features.laser_depth_m)) @ e_t
        # Rotation: keep the spot on the centroid of the corners (4-47, 4-48).
        centroid = features.corners_px.mean(axis=0)
        e_r = centroid - features.laser_spot_px
        w = -self.k_rotation * checked_pinv(rotational_jacobian(self.camera, centroid)) @ e_r
        cVc = np.concatenate([v, w])
        # How far this step still moves the corners (linearised, per unit of gain). From a
        # view tilted well off the desired direction (a close start, turned in place by
        # stage 1) the translation and the rotation of eq. 4-49 balance with the spot a few
        # px beyond f0^l, and stage 2 would creep on forever; stage 3 regulates the corners
        # themselves and takes the view round.
        moving_px = (
            float(np.linalg.norm(pixel_interaction_matrix(self.camera, features.corners_px, features.laser_depth_m) @ cVc))
            / self.k_translation
        )
        if moving_px <= self.f0_turn_px:
            switch = f"2 -> 3: stage 2 moves the corners no more ({moving_px:.2f} px, ||f_d^l - f^l|| = {laser_error_px:.2f} px)"
            return self._stage_3(features, desired, error_px, note=f"{note}; {switch}" if note else switch)
        return ControlOutput(cVc, Stage.APPROACH_2, error_px, laser_error_px, note=note)

    def _stage_3(self, features: ImageFeatures, desired: DesiredImage, error_px: float, note: str) -> ControlOutput:
        if not features.all_corners_visible:
            return ControlOutput.stop(Stage.FINISH_3, error_px, Failure.FEATURES_LOST, "corners lost in stage 3")
        if error_px <= self.final_threshold_px:
            return ControlOutput(np.zeros(6), Stage.FINISH_3, error_px, error_px, converged=True, note=note)
        # Constant interaction matrix at the desired features and depth (4-50, 4-51).
        L_desired = pixel_interaction_matrix(self.camera, desired.corners_px, desired.depth_m)
        e = (features.corners_px - desired.corners_px).ravel()
        return ControlOutput(-self.k_final * checked_pinv(L_desired) @ e, Stage.FINISH_3, error_px, error_px, note=note)
