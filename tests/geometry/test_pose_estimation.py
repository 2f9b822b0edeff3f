"""Pose from image points against ground truth projected by OpenCV.

Poses are drawn with vservo.core.geometry.spatial.matrix_from_pose and projected with cv2.projectPoints
(distortion included), errors are measured with OpenCV's Rodrigues, so nothing here
reuses the code under test to build what it is compared with.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics
from vservo.core.geometry.pose_estimation import (
    HomographyMotion,
    PoseEstimationError,
    decompose_homography,
    euclidean_homography,
    homography_solutions,
    pose_from_planar_points,
    pose_from_posit,
)
from vservo.core.geometry.spatial import exp_twist, inverse, matrix_from_pose

# The thesis's XC-55 geometry (f = 810.8 px, 640 x 480) with a moderate barrel lens, so
# that the undistortion is exercised.
CAMERA = CameraModel(
    Intrinsics(fx=810.8, fy=812.0, u0=322.0, v0=238.5, width=640, height=480),
    Distortion(k1=-0.21, k2=0.06, p1=7e-4, p2=-5e-4, k3=-0.01),
)

SIDE = 0.02  # the 20 mm top face of the part
SQUARE = np.array([[0.0, 0.0, 0.0], [SIDE, 0.0, 0.0], [SIDE, SIDE, 0.0], [0.0, SIDE, 0.0]])
# POSIT's model: the four top corners plus the cube's bottom corner under the first.
CUBE_FIVE = np.vstack((SQUARE, [0.0, 0.0, -SIDE]))


def random_object_pose(rng: np.random.Generator) -> np.ndarray:
    """cMo with the part 0.15 .. 0.45 m ahead, in view, tilted up to ~35 degrees."""
    z = rng.uniform(0.15, 0.45)
    return matrix_from_pose(
        [
            rng.uniform(-0.12, 0.12) * z,
            rng.uniform(-0.08, 0.08) * z,
            z,
            rng.uniform(-np.pi, np.pi),
            rng.uniform(-0.6, 0.6),
            rng.uniform(-0.6, 0.6),
        ]
    )


def project_px(cMo: np.ndarray, points_o: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(cMo[:3, :3])
    px, _ = cv2.projectPoints(points_o, rvec, cMo[:3, 3], CAMERA.intrinsics.K, CAMERA.distortion.as_opencv())
    return px.reshape(-1, 2)


def project_normalized(cMo: np.ndarray, points_o: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(cMo[:3, :3])
    xn, _ = cv2.projectPoints(points_o, rvec, cMo[:3, 3], np.eye(3), None)
    return xn.reshape(-1, 2)


def rotation_error(R_a: np.ndarray, R_b: np.ndarray) -> float:
    rvec, _ = cv2.Rodrigues(R_a.T @ R_b)
    return float(np.linalg.norm(rvec))


def pose_errors(aMb: np.ndarray, aMc: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(aMb[:3, 3] - aMc[:3, 3])), rotation_error(aMb[:3, :3], aMc[:3, :3])


def assert_rotation(R: np.ndarray) -> None:
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


# --- planar PnP (IPPE) ------------------------------------------------------------------


def test_planar_pnp_recovers_random_poses_exactly_without_noise():
    rng = np.random.default_rng(11)
    for _ in range(50):
        cMo = random_object_pose(rng)
        estimate = pose_from_planar_points(project_px(cMo, SQUARE), SQUARE, CAMERA)
        translation, rotation = pose_errors(cMo, estimate)
        assert translation < 1e-6 and rotation < 1e-6, (cMo, estimate)
        assert_rotation(estimate[:3, :3])
        np.testing.assert_array_equal(estimate[3], [0, 0, 0, 1])


def test_planar_pnp_with_half_pixel_noise_has_errors_of_the_expected_order():
    """Depth dominates: a square of side s at depth Z is s f / Z pixels wide, so sigma px of
    noise moves its centre by about Z^2 sigma / (f s) (1.2 mm at 0.2 m, 6 mm at 0.45 m).
    The orientation of so small a square is weakly observed (IPPE's two-fold ambiguity), so
    the check is the centre of the face and a reprojection error at the noise level."""
    rng = np.random.default_rng(12)
    sigma = 0.5
    centre = np.array([SIDE / 2, SIDE / 2, 0.0, 1.0])
    ratios, errors_mm = [], []
    for _ in range(200):
        cMo = random_object_pose(rng)
        noisy = project_px(cMo, SQUARE) + rng.normal(0.0, sigma, (4, 2))
        estimate = pose_from_planar_points(noisy, SQUARE, CAMERA)
        error = np.linalg.norm((estimate @ centre)[:3] - (cMo @ centre)[:3])
        depth = cMo[2, 3]
        ratios.append(error / (depth**2 * sigma / (CAMERA.intrinsics.fx * SIDE)))
        errors_mm.append(error * 1e3)
        residual = project_px(estimate, SQUARE) - noisy
        assert np.sqrt(np.mean(residual**2)) < 2 * sigma
    assert np.median(ratios) < 1.5 and max(ratios) < 5.0
    assert np.median(errors_mm) < 2.0


def test_planar_pnp_takes_any_plane_and_skips_unseen_points():
    rng = np.random.default_rng(13)
    # Five points on a tilted plane that does not pass through the origin of O.
    plane = matrix_from_pose([0.01, -0.02, 0.005, 0.3, 0.4, -0.2])
    in_plane = np.array([[0, 0, 0], [0.03, 0, 0], [0.03, 0.02, 0], [0, 0.025, 0], [0.012, 0.01, 0]], float)
    model = (plane[:3, :3] @ in_plane.T).T + plane[:3, 3]
    cMo = random_object_pose(rng)
    px = project_px(cMo, model)
    px[2] = np.nan
    translation, rotation = pose_errors(cMo, pose_from_planar_points(px, model, CAMERA))
    assert translation < 1e-6 and rotation < 1e-6


def test_planar_pnp_of_a_square_facing_the_camera_exactly():
    """The taught view: IPPE's closed form is NaN there, the fallback must still be exact."""
    cMo = matrix_from_pose([0.011, -0.01, 0.162, np.pi, 0.0, -np.pi])
    translation, rotation = pose_errors(cMo, pose_from_planar_points(project_px(cMo, SQUARE), SQUARE, CAMERA))
    assert translation < 1e-6 and rotation < 1e-6


def test_planar_pnp_needs_four_finite_points():
    cMo = matrix_from_pose([0.0, 0.0, 0.3, 0.1, 0.2, 0.3])
    px = project_px(cMo, SQUARE)
    with pytest.raises(PoseEstimationError, match="at least 4"):
        pose_from_planar_points(px[:3], SQUARE[:3], CAMERA)
    px[1] = [np.nan, np.nan]
    with pytest.raises(PoseEstimationError, match=r"got 3 \(1 of 4"):
        pose_from_planar_points(px, SQUARE, CAMERA)


def test_planar_pnp_rejects_bad_models():
    cMo = matrix_from_pose([0.0, 0.0, 0.3, 0.1, 0.2, 0.3])
    with pytest.raises(PoseEstimationError, match="not coplanar"):
        pose_from_planar_points(project_px(cMo, CUBE_FIVE), CUBE_FIVE, CAMERA)
    line = np.array([[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.03, 0, 0]], float)
    with pytest.raises(PoseEstimationError, match="collinear"):
        pose_from_planar_points(project_px(cMo, line), line, CAMERA)
    with pytest.raises(PoseEstimationError, match="correspond"):
        pose_from_planar_points(project_px(cMo, SQUARE), CUBE_FIVE, CAMERA)
    with pytest.raises(PoseEstimationError, match="finite"):
        pose_from_planar_points(project_px(cMo, SQUARE), SQUARE + [np.nan, 0, 0], CAMERA)
    assert issubclass(PoseEstimationError, ValueError)


# --- POSIT --------------------------------------------------------------------------------


def test_posit_recovers_random_poses_without_noise():
    rng = np.random.default_rng(21)
    for _ in range(50):
        cMo = random_object_pose(rng)
        estimate = pose_from_posit(project_px(cMo, CUBE_FIVE), CUBE_FIVE, CAMERA)
        translation, rotation = pose_errors(cMo, estimate)
        assert translation < 1e-6 and rotation < 1e-6, (cMo, estimate)
        assert_rotation(estimate[:3, :3])


def test_posit_iterations_are_what_removes_the_scaled_orthographic_error():
    cMo = matrix_from_pose([0.02, -0.01, 0.16, 0.4, 0.5, -0.3])
    px = project_px(cMo, CUBE_FIVE)
    pos_only = pose_errors(cMo, pose_from_posit(px, CUBE_FIVE, CAMERA, iterations=1))
    posit = pose_errors(cMo, pose_from_posit(px, CUBE_FIVE, CAMERA))
    assert pos_only[0] > 1e-4 or pos_only[1] > 1e-3  # POS alone is the weak-perspective pose
    assert posit[0] < 1e-9 and posit[1] < 1e-9


def test_posit_returns_the_pose_of_the_object_frame_whatever_the_reference_point():
    # The off-plane point first, so the reference M0 is not the origin of O; and one NaN row.
    rng = np.random.default_rng(22)
    model = CUBE_FIVE[[4, 2, 0, 1, 3]] + [0.005, -0.01, 0.002]
    model = np.vstack((model, [0.02, 0.0, -0.02]))
    cMo = random_object_pose(rng)
    px = project_px(cMo, model)
    px[3] = np.nan
    translation, rotation = pose_errors(cMo, pose_from_posit(px, model, CAMERA))
    assert translation < 1e-6 and rotation < 1e-6


def test_posit_rejects_coplanar_and_too_few_points():
    cMo = matrix_from_pose([0.0, 0.0, 0.3, 0.1, 0.2, 0.3])
    coplanar = np.vstack((SQUARE, [SIDE / 2, SIDE / 3, 0.0]))
    with pytest.raises(PoseEstimationError, match="coplanar"):
        pose_from_posit(project_px(cMo, coplanar), coplanar, CAMERA)
    with pytest.raises(PoseEstimationError, match="coplanar"):
        pose_from_posit(project_px(cMo, SQUARE), SQUARE, CAMERA)
    with pytest.raises(PoseEstimationError, match="at least 4"):
        pose_from_posit(project_px(cMo, CUBE_FIVE[[0, 1, 4]]), CUBE_FIVE[[0, 1, 4]], CAMERA)
    px = project_px(cMo, CUBE_FIVE)
    px[[1, 3]] = np.nan
    with pytest.raises(PoseEstimationError, match="at least 4"):
        pose_from_posit(px, CUBE_FIVE, CAMERA)
    with pytest.raises(ValueError, match="iterations"):
        pose_from_posit(project_px(cMo, CUBE_FIVE), CUBE_FIVE, CAMERA, iterations=0)


# --- homography ---------------------------------------------------------------------------


def plane_motion(cdMo: np.ndarray, cMo: np.ndarray):
    """Ground truth (cRc*, ct_c*/d*, n*, Z/Z*) for the plane z_o = 0 seen from two poses."""
    cMcd = cMo @ inverse(cdMo)
    normal = cdMo[:3, 2].copy()  # z_o in C*
    distance = normal @ cdMo[:3, 3]
    if distance < 0:
        normal, distance = -normal, -distance
    homogeneous = np.column_stack((SQUARE, np.ones(len(SQUARE)))).T
    depth_ratio = (cMo @ homogeneous)[2] / (cdMo @ homogeneous)[2]
    return cMcd[:3, :3], cMcd[:3, 3] / distance, normal, depth_ratio


def test_euclidean_homography_is_r_plus_t_n_over_d():
    rng = np.random.default_rng(31)
    for _ in range(30):
        cdMo, cMo = random_object_pose(rng), random_object_pose(rng)
        R, t_over_d, normal, _ = plane_motion(cdMo, cMo)
        H = euclidean_homography(project_normalized(cdMo, SQUARE), project_normalized(cMo, SQUARE))
        np.testing.assert_allclose(H, R + np.outer(t_over_d, normal), atol=1e-9)
        assert np.linalg.svd(H, compute_uv=False)[1] == pytest.approx(1.0, abs=1e-12)


def test_decomposition_recovers_the_true_motion_with_the_true_normal_as_hint():
    rng = np.random.default_rng(32)
    for _ in range(50):
        cdMo, cMo = random_object_pose(rng), random_object_pose(rng)
        R, t_over_d, normal, depth_ratio = plane_motion(cdMo, cMo)
        desired, current = project_normalized(cdMo, SQUARE), project_normalized(cMo, SQUARE)
        motion = decompose_homography(euclidean_homography(desired, current), desired, normal)
        assert isinstance(motion, HomographyMotion)
        assert rotation_error(motion.cRcd, R) < 1e-8
        np.testing.assert_allclose(motion.t_over_d, t_over_d, atol=1e-8)
        np.testing.assert_allclose(motion.normal_d, normal, atol=1e-8)
        np.testing.assert_allclose(motion.depth_ratio(desired), depth_ratio, rtol=1e-10)
        assert_rotation(motion.cRcd)
        d_star = normal @ cdMo[:3, 3]
        np.testing.assert_allclose(motion.cMcd(d_star), cMo @ inverse(cdMo), atol=1e-9)


def test_a_rough_hint_is_enough():
    rng = np.random.default_rng(33)
    for _ in range(30):
        cdMo, cMo = random_object_pose(rng), random_object_pose(rng)
        R, t_over_d, normal, _ = plane_motion(cdMo, cMo)
        desired, current = project_normalized(cdMo, SQUARE), project_normalized(cMo, SQUARE)
        solutions = homography_solutions(euclidean_homography(desired, current), desired, normal)
        if len(solutions) < 2:
            continue  # the mirror solution is not physically valid for this motion
        # Tilt the hint by a third of the angle between the two candidate normals.
        gap = np.arccos(np.clip(solutions[0].normal_d @ solutions[1].normal_d, -1.0, 1.0))
        axis = np.cross(normal, rng.normal(size=3))
        rough, _ = cv2.Rodrigues(axis / np.linalg.norm(axis) * gap / 3.0)
        motion = decompose_homography(solutions[0].H, desired, rough @ normal * 7.0)
        np.testing.assert_allclose(motion.normal_d, normal, atol=1e-8)


def test_the_wrong_hint_picks_the_mirror_solution_which_explains_the_images_as_well():
    """Four coplanar points in two views are explained by two planes and motions. The mirror
    one is checked as a scene: its plane through the desired rays, moved by its motion,
    projects exactly onto the current image, in front of both cameras."""
    rng = np.random.default_rng(34)
    found = 0
    for _ in range(30):
        cdMo, cMo = random_object_pose(rng), random_object_pose(rng)
        R, t_over_d, normal, _ = plane_motion(cdMo, cMo)
        desired, current = project_normalized(cdMo, SQUARE), project_normalized(cMo, SQUARE)
        H = euclidean_homography(desired, current)
        solutions = homography_solutions(H, desired, normal)
        assert 1 <= len(solutions) <= 2
        assert rotation_error(solutions[0].cRcd, R) < 1e-8
        if len(solutions) == 1:
            continue
        found += 1
        mirror = decompose_homography(H, desired, -normal)
        assert mirror.normal_d @ normal < 1.0 - 1e-6 and rotation_error(mirror.cRcd, R) > 1e-6
        np.testing.assert_allclose(mirror.normal_d, solutions[1].normal_d, atol=1e-12)
        assert_rotation(mirror.cRcd)
        assert np.linalg.norm(mirror.normal_d) == pytest.approx(1.0)
        # The mirror scene, with d* = 1: X* on the rays of the desired points.
        rays = np.column_stack((desired, np.ones(4)))
        X_star = rays / (rays @ mirror.normal_d)[:, None]
        X = X_star @ mirror.cRcd.T + mirror.t_over_d
        assert np.all(X_star[:, 2] > 0) and np.all(X[:, 2] > 0)
        np.testing.assert_allclose(X[:, :2] / X[:, 2:], current, atol=1e-10)
        np.testing.assert_allclose(mirror.depth_ratio(desired), X[:, 2] / X_star[:, 2], rtol=1e-9)
        # And asking with its own normal returns it again.
        again = decompose_homography(H, desired, mirror.normal_d)
        np.testing.assert_allclose(again.cRcd, mirror.cRcd, atol=1e-12)
    assert found >= 20


@pytest.mark.parametrize("size", [0.0, 1e-9, 1e-6, 1e-4, 4e-4, 2e-3])
def test_small_motions_and_identity_are_stable(size):
    """OpenCV calls |H^T H - I| < 1e-3 a pure rotation (R = H, t = n = 0); the normal is then
    not observable and the hint is used, which is exact when the hint is the true normal
    and leaves an error of order |t/d*| times the hint error otherwise."""
    rng = np.random.default_rng(35)
    cdMo = matrix_from_pose([0.01, -0.005, 0.3, 0.4, 0.3, -0.2])
    twist = rng.normal(size=6)
    cMcd = exp_twist(twist / np.linalg.norm(twist) * size)
    cMo = cMcd @ cdMo
    R, t_over_d, normal, depth_ratio = plane_motion(cdMo, cMo)
    desired, current = project_normalized(cdMo, SQUARE), project_normalized(cMo, SQUARE)
    H = euclidean_homography(desired, current)
    motion = decompose_homography(H, desired, normal)
    assert rotation_error(motion.cRcd, R) < 1e-10
    np.testing.assert_allclose(motion.t_over_d, t_over_d, atol=1e-10)
    np.testing.assert_allclose(motion.depth_ratio(desired), depth_ratio, rtol=1e-10)
    assert_rotation(motion.cRcd)
    hint_error = 0.1
    tilted, _ = cv2.Rodrigues(np.cross(normal, [1.0, 0.0, 0.0]) / np.linalg.norm(np.cross(normal, [1, 0, 0])) * hint_error)
    # Every solution offered, with a hint 0.1 rad off, is a motion of the order of the true one.
    scale = max(size, float(np.linalg.norm(t_over_d)))
    for solution in homography_solutions(H, desired, tilted @ normal):
        assert rotation_error(solution.cRcd, np.eye(3)) < 3 * scale + 1e-12
        assert np.linalg.norm(solution.t_over_d) < 3 * scale + 1e-12
        assert_rotation(solution.cRcd)


def test_identical_views_give_no_motion():
    cdMo = matrix_from_pose([0.01, -0.005, 0.3, 0.4, 0.3, -0.2])
    desired = project_normalized(cdMo, SQUARE)
    H = euclidean_homography(desired, desired)
    np.testing.assert_allclose(H, np.eye(3), atol=1e-12)
    hint = np.array([0.1, -0.2, 1.0])
    solutions = homography_solutions(H, desired, hint)
    for solution in solutions:
        np.testing.assert_allclose(solution.cRcd, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(solution.t_over_d, 0.0, atol=1e-12)
        np.testing.assert_allclose(solution.depth_ratio(desired), 1.0, atol=1e-12)
    np.testing.assert_allclose(solutions[0].normal_d, hint / np.linalg.norm(hint), atol=1e-12)


def test_homography_rejects_degenerate_input():
    cdMo = matrix_from_pose([0.01, -0.005, 0.3, 0.4, 0.3, -0.2])
    cMo = matrix_from_pose([0.0, 0.01, 0.25, 0.2, 0.1, -0.1])
    desired, current = project_normalized(cdMo, SQUARE), project_normalized(cMo, SQUARE)
    with pytest.raises(PoseEstimationError, match="at least 4"):
        euclidean_homography(desired[:3], current[:3])
    gappy = current.copy()
    gappy[0] = np.nan
    with pytest.raises(PoseEstimationError, match="at least 4"):
        euclidean_homography(desired, gappy)
    # Three of the four plane points on a line: both images have them collinear.
    model = SQUARE.copy()
    model[2] = (model[1] + model[3]) / 2.0
    with pytest.raises(PoseEstimationError, match="collinear"):
        euclidean_homography(project_normalized(cdMo, model), project_normalized(cMo, model))
    with pytest.raises(PoseEstimationError, match="correspond"):
        euclidean_homography(desired, current[:3])
    H = euclidean_homography(desired, current)
    with pytest.raises(PoseEstimationError, match="normal_hint_d"):
        decompose_homography(H, desired, np.zeros(3))
    with pytest.raises(PoseEstimationError, match="3 x 3"):
        decompose_homography(H[:2], desired, [0, 0, 1])


def test_homography_with_more_points_and_a_lost_one():
    rng = np.random.default_rng(36)
    grid = np.array([[x, y, 0.0] for x in (0.0, 0.01, 0.02) for y in (0.0, 0.01, 0.02)])
    cdMo, cMo = random_object_pose(rng), random_object_pose(rng)
    R, t_over_d, normal, _ = plane_motion(cdMo, cMo)
    desired, current = project_normalized(cdMo, grid), project_normalized(cMo, grid)
    current[4] = np.nan
    H = euclidean_homography(desired, current)
    motion = decompose_homography(H, desired, normal)
    assert rotation_error(motion.cRcd, R) < 1e-8
    np.testing.assert_allclose(motion.t_over_d, t_over_d, atol=1e-8)
