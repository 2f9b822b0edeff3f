"""Control laws: interaction matrices against finite differences, the half turn that makes
IBVS retreat, and every switch of the IBVS with laser."""

from dataclasses import replace

import numpy as np
import pytest

from tests.servo_fixtures import CAMERA, CORNERS_O, DESIRED_SPOT, DESIRED_cMo, desired_image, features, project, rotate_about
from vservo.core.geometry.camera import CameraModel, Intrinsics
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import exp_twist, inverse, matrix_from_pose, transform, twist_transform
from vservo.core.perception.features import ImageFeatures, ObjectRegion
from vservo.core.servo.laws.base import Failure, SingularJacobian, Stage, checked_pinv
from vservo.core.servo.laws.hybrid import Hybrid25D, translation_interaction
from vservo.core.servo.laws.ibvs import ClassicIbvs
from vservo.core.servo.laws.laser_ibvs import LaserIbvs, image_rotation, rotational_jacobian, translational_jacobian
from vservo.core.servo.laws.pbvs import Pbvs
from vservo.core.servo.loop import hold_spot
from vservo.core.sim.plant import visible_region

LASER = LaserPointer.in_plane(0.030, np.radians(80.0))  # the thesis's beam, where DESIRED_SPOT lies at Z*

H = 1e-6


def moved(cMo, cVc, h):
    """The object pose after the camera held the twist cVc for h seconds."""
    return inverse(exp_twist(np.asarray(cVc) * h)) @ cMo


def pixel_velocity(cMo, cVc, points_o=CORNERS_O):
    """d(pixels)/dt of the points by central differences of the projection."""
    return ((project(moved(cMo, cVc, H), points_o) - project(moved(cMo, cVc, -H), points_o)) / (2 * H)).ravel()


@pytest.mark.parametrize("pose", [[0.011, -0.01, 0.162, np.pi, 0.0, -np.pi], [-0.05, 0.03, 0.3, 0.3, -0.2, -2.6]])
def test_rotational_and_translational_jacobians_match_finite_differences(pose):
    cMo = matrix_from_pose(pose)
    uv = project(cMo)
    depth = (CORNERS_O @ cMo[:3, :3].T + cMo[:3, 3])[:, 2]
    J_r = rotational_jacobian(CAMERA, uv)
    for k in range(3):
        w = np.zeros(6)
        w[3 + k] = 1.0
        assert np.allclose(J_r[:, k], pixel_velocity(cMo, w), rtol=1e-5, atol=1e-3)
    for i in range(4):  # J^t per point, at that point's own depth
        J_t = translational_jacobian(CAMERA, uv[i], depth[i])
        for k in range(3):
            v = np.zeros(6)
            v[k] = 1.0
            assert np.allclose(J_t[:, k], pixel_velocity(cMo, v)[2 * i : 2 * i + 2], rtol=1e-5, atol=1e-3)


def test_2_5d_interaction_matches_finite_differences():
    """(x, y, log Z) of a point against (L_v, L_vw) of Malis's 2.5D law."""
    cP = np.array([0.03, -0.02, 0.25])

    def features_of(twist, h):
        P = inverse(exp_twist(np.asarray(twist) * h)) @ np.append(cP, 1.0)
        return np.array([P[0] / P[2], P[1] / P[2], np.log(P[2])])

    L_v, L_vw = translation_interaction(cP[0] / cP[2], cP[1] / cP[2], cP[2])
    L = np.hstack([L_v, L_vw])
    for k in range(6):
        twist = np.zeros(6)
        twist[k] = 1.0
        numeric = (features_of(twist, H) - features_of(twist, -H)) / (2 * H)
        assert np.allclose(L[:, k], numeric, atol=1e-6)


def test_half_turn_makes_current_feature_ibvs_retreat():
    """Chaumette 1998: a pi turn about the optical axis gives a pure backward translation."""
    centre = np.array([CAMERA.intrinsics.u0, CAMERA.intrinsics.v0])
    desired_corners = centre + np.array([[-50.0, -50.0], [50.0, -50.0], [50.0, 50.0], [-50.0, 50.0]])
    desired = desired_image()
    desired = type(desired)(desired_corners, desired.laser_spot_px, 0.162, desired.cdMo, np.full(4, 0.162))
    current = features(rotate_about(desired_corners, centre, np.pi), depth=0.162)
    out = ClassicIbvs(CAMERA, interaction="current", depth="exact").step(current, desired, None)
    v, w = out.cVc[:3], out.cVc[3:]
    assert v[2] < 0.0  # backwards, away from the part
    assert abs(v[2]) > 1e3 * max(np.abs(v[:2]).max(), np.abs(w).max())
    # The laser method turns instead: its stage 1.A commands a rotation about the optical axis.
    turn = laser_law().step(current, desired, None)
    assert turn.stage == Stage.ALIGN_1A
    assert abs(turn.cVc[5]) > 10 * np.abs(turn.cVc[:5]).max()


def laser_law(**settings):
    return LaserIbvs(CAMERA, cTe=np.zeros(3), laser=LASER, **settings)


def test_stage_1a_starts_and_switches_to_2_on_the_imaginary_features():
    desired = desired_image()
    law = laser_law()
    # The part seen turned by 0.5 rad about the spot: far from the imaginary features.
    turned = features(rotate_about(desired.corners_px, DESIRED_SPOT, 0.5))
    first = law.step(turned, desired, None)
    assert first.stage == Stage.ALIGN_1A and not first.converged and first.failure is None
    assert first.stage_error > law.f0_px
    assert np.allclose(first.cVc[:3], 0.0)  # rotation only (cTe = 0: no compensation)

    # The corners on the imaginary features, the spot 40 px away from its desired place: 1.A -> 2.
    shift = np.array([-40.0, 0.0])
    at_imaginary = features(desired.corners_px + shift, spot_px=DESIRED_SPOT + shift)
    second = law.step(at_imaginary, desired, Stage.ALIGN_1A)
    assert second.stage == Stage.APPROACH_2 and "1A -> 2" in second.note


def test_stage_1a_turns_the_pattern_the_right_way():
    """One small step of the stage-1.A twist brings the corners closer to the imaginary ones."""
    desired = desired_image()
    for angle in (0.4, -0.4, np.pi - 0.01):
        cMo = transform(matrix_from_pose([0, 0, 0, angle, 0, 0])[:3, :3]) @ DESIRED_cMo
        current = features(project(cMo))
        out = laser_law().step(current, desired, None)
        after = features(project(moved(cMo, out.cVc, 0.05)))
        assert abs(image_rotation(after.corners_px, desired.corners_px)) < abs(
            image_rotation(current.corners_px, desired.corners_px)
        )


def test_stage_1b_turns_the_visible_region_onto_the_spot_with_two_dof():
    desired = desired_image()
    cMo = matrix_from_pose([-0.055, -0.01, 0.162, np.pi, 0.0, -np.pi])  # corners at u = 45 and -55 px
    projected = project(cMo)
    corners = np.where(CAMERA.in_view(projected)[:, None], projected, np.nan)
    assert np.isnan(corners).any() and not np.isnan(corners).all()
    seen = features(corners, region=visible_region(projected, CAMERA.image_size))
    out = laser_law().step(seen, desired, None)
    assert out.stage == Stage.CENTRE_1B and out.cVc[5] == 0.0 and np.allclose(out.cVc[:3], 0.0)
    # The centroid's rotational velocity points from the centroid to the spot
    # (eq. 4-36 as docs/thesis-notes.md section 5 reads it).
    centroid = seen.region.centroid_px
    velocity = rotational_jacobian(CAMERA, centroid) @ out.cVc[3:]
    assert velocity @ (DESIRED_SPOT - centroid) > 0.9 * np.linalg.norm(velocity) * np.linalg.norm(DESIRED_SPOT - centroid)
    # Once every corner is seen again, 1.B hands over to 1.A.
    assert laser_law().step(features(desired.corners_px + 30.0), desired, Stage.CENTRE_1B).stage == Stage.ALIGN_1A


def test_stage_1c_keeps_the_flange_in_place_while_the_camera_turns():
    eMc = matrix_from_pose([0.02, -0.03, 0.05, 0.1, 0.2, -0.1])
    law = LaserIbvs(CAMERA, cTe=inverse(eMc)[:3, 3], laser=LASER)
    desired = desired_image()
    out = law.step(features(rotate_about(desired.corners_px, DESIRED_SPOT, 0.5)), desired, None)
    eVe = twist_transform(eMc) @ out.cVc
    assert np.linalg.norm(out.cVc[:3]) > 1e-3  # the camera translates ...
    assert np.allclose(eVe[:3], 0.0, atol=1e-12)  # ... so that the flange only turns (eq. 4-38)


def test_stage_2_switches_to_3_at_the_laser_threshold_and_3_converges():
    desired = desired_image()
    law = laser_law()
    near = features(desired.corners_px + [3.0, -2.0], spot_px=DESIRED_SPOT + [4.0, 0.0])
    out = law.step(near, desired, Stage.APPROACH_2)
    assert out.stage == Stage.FINISH_3 and "2 -> 3" in out.note
    far = features(desired.corners_px * 0.8 + 60, spot_px=DESIRED_SPOT + [30.0, 0.0], depth=0.2)
    stay = law.step(far, desired, Stage.APPROACH_2)
    assert stay.stage == Stage.APPROACH_2 and stay.stage_error == pytest.approx(30.0)
    done = law.step(features(desired.corners_px + 0.2), desired, Stage.FINISH_3)
    assert done.converged and np.allclose(done.cVc, 0.0)


def test_stage_2_rotation_keeps_the_spot_on_the_centroid():
    desired = desired_image()
    corners = desired.corners_px * 0.7 + [110.0, 60.0]
    spot = DESIRED_SPOT + [30.0, 0.0]
    out = laser_law().step(features(corners, spot_px=spot, depth=0.25), desired, Stage.APPROACH_2)
    centroid = corners.mean(axis=0)
    velocity = rotational_jacobian(CAMERA, centroid) @ out.cVc[3:]
    assert velocity @ (spot - centroid) > 0.9 * np.linalg.norm(velocity) * np.linalg.norm(spot - centroid)


@pytest.mark.parametrize("stage", [Stage.APPROACH_2, Stage.FINISH_3])
def test_a_lost_corner_after_stage_1_stops_with_zero_twist(stage):
    desired = desired_image()
    corners = desired.corners_px + 20.0
    corners[2] = np.nan
    out = laser_law().step(features(corners, spot_px=DESIRED_SPOT + [30.0, 0.0]), desired, stage)
    assert out.failure is Failure.FEATURES_LOST and np.array_equal(out.cVc, np.zeros(6))


def test_with_no_spot_stage_1_turns_the_part_onto_the_desired_spot_and_stage_2_stops():
    """The beam lands out of sight (docs/thesis-notes.md section 5): stage 1.B aims the
    region's centroid at the spot's place in the desired image; stage 2 needs the spot."""
    desired = desired_image()
    unseen = features(desired.corners_px + 40.0, spot_px=[np.nan, np.nan], depth=np.nan)
    out = laser_law().step(unseen, desired, None)
    assert out.failure is None and out.stage == Stage.CENTRE_1B and "not seen" in out.note
    centroid = unseen.region.centroid_px
    velocity = rotational_jacobian(CAMERA, centroid) @ out.cVc[3:]
    assert velocity @ (DESIRED_SPOT - centroid) > 0.9 * np.linalg.norm(velocity) * np.linalg.norm(DESIRED_SPOT - centroid)
    out = laser_law().step(unseen, desired, Stage.APPROACH_2)
    assert out.failure is Failure.FEATURES_LOST and np.array_equal(out.cVc, np.zeros(6))


@pytest.mark.parametrize("law", [ClassicIbvs(CAMERA), Pbvs(CAMERA), Hybrid25D(CAMERA)])
def test_every_baseline_needs_all_four_corners_and_stops_at_the_final_threshold(law):
    desired = desired_image()
    corners = desired.corners_px + 15.0
    corners[0] = np.nan
    assert law.step(features(corners), desired, None).failure is Failure.FEATURES_LOST
    done = law.step(features(desired.corners_px + 0.3), desired, None)
    assert done.converged and np.array_equal(done.cVc, np.zeros(6))


@pytest.mark.parametrize("law", [ClassicIbvs(CAMERA), Pbvs(CAMERA), Hybrid25D(CAMERA), laser_law()])
def test_a_small_step_reduces_the_feature_error(law):
    """Every law, one step from a nearby pose (turned and shifted), moves the corners closer."""
    desired = desired_image()
    cMo = matrix_from_pose([0.015, -0.005, 0.175, np.pi - 0.1, 0.05, -np.pi + 0.05])
    stage = Stage.FINISH_3 if isinstance(law, LaserIbvs) else None
    out = law.step(
        features(project(cMo), depth=0.175, corner_depths=(CORNERS_O @ cMo[:3, :3].T + cMo[:3, 3])[:, 2]), desired, stage
    )
    after = project(moved(cMo, out.cVc, 0.1))
    assert np.linalg.norm(after - desired.corners_px) < 0.95 * np.linalg.norm(project(cMo) - desired.corners_px)


@pytest.mark.parametrize("swap", [False, True])
def test_stage_3_tolerates_the_intrinsics_errors_of_table_5_3(swap):
    """IBVS's robustness to calibration near the goal: with the features seen through one of
    Table 5-3's cameras and the law built on the other, a step still moves the corners closer."""
    cameras = (CAMERA, CameraModel(Intrinsics.from_sensor(7.2e-3, (7.4e-6, 7.4e-6), (384.0, 288.0), (640, 480))))
    seeing, believed = cameras[::-1] if swap else cameras
    desired = desired_image()
    desired = replace(desired, corners_px=project(DESIRED_cMo, camera=seeing))
    cMo = matrix_from_pose([0.015, -0.005, 0.175, np.pi - 0.1, 0.05, -np.pi + 0.05])
    out = LaserIbvs(believed, cTe=np.zeros(3), laser=LASER).step(features(project(cMo, camera=seeing)), desired, Stage.FINISH_3)
    before = project(cMo, camera=seeing) - desired.corners_px
    after = project(moved(cMo, out.cVc, 0.1), camera=seeing) - desired.corners_px
    # A tenth of the correction with the right model; the wrong one shortens the step.
    assert np.linalg.norm(after) < 0.97 * np.linalg.norm(before)


def test_pbvs_law_is_a_straight_line_of_the_camera_centre():
    desired = desired_image()
    cMo = matrix_from_pose([-0.02, 0.01, 0.2, np.pi - 0.2, 0.1, -np.pi])
    out = Pbvs(CAMERA).step(features(project(cMo)), desired, None)
    cdMc = desired.cdMo @ inverse(cMo)
    # v is along -(c*Rc)^T c*t_c: the centre heads straight for the desired centre.
    direction = -cdMc[:3, :3].T @ cdMc[:3, 3]
    assert np.allclose(np.cross(out.cVc[:3], direction), 0.0, atol=1e-6)


def test_checked_pinv_is_the_pseudo_inverse_or_says_singular():
    J = np.random.default_rng(3).normal(size=(8, 6))
    np.testing.assert_allclose(checked_pinv(J), np.linalg.pinv(J), atol=1e-12)
    for bad in (np.full((8, 6), np.nan), np.zeros((8, 6)), np.outer(np.arange(8.0), np.ones(6))):
        with pytest.raises(SingularJacobian):
            checked_pinv(bad)


def _frame(corners_px, spot_px):
    corners_px = np.asarray(corners_px, dtype=float)
    return ImageFeatures(
        corners_px,
        np.asarray(spot_px, dtype=float),
        0.16 if spot_px[0] == spot_px[0] else float("nan"),
        ObjectRegion(0.0, np.full(2, np.nan)),
        np.full(4, np.nan),
        np.full(2, np.nan),
    )


def test_a_spot_hidden_behind_the_part_is_held_while_the_part_moves_less_than_its_size():
    square = np.array([[300.0, 200.0], [400.0, 200.0], [400.0, 300.0], [300.0, 300.0]])
    seen = _frame(square, [320.0, 280.0])
    nan = [np.nan, np.nan]
    # Thirty cycles a pixel apart: the spot still behind the part's edge, still held.
    for shift in range(30):
        held = hold_spot(_frame(square + [shift, 0.0], nan), seen)
        assert np.allclose(held.laser_spot_px, [320.0, 280.0]) and held.laser_depth_m == 0.16
    # Moved beyond its own size (diagonal about 141 px): the spot is gone, not hidden.
    gone = hold_spot(_frame(square + [150.0, 0.0], nan), seen)
    assert not gone.laser_visible
    # No corner seen: nothing tells how far the part moved.
    assert not hold_spot(_frame(np.full((4, 2), np.nan), nan), seen).laser_visible
