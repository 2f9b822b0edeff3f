"""Rigid-body conventions, checked against computations that do not go through vservo.core.geometry.spatial.

References used here: the element-by-element matrix of eq. 2-13, OpenCV's Rodrigues, a
numpy scaling-and-squaring matrix exponential, np.linalg.inv, and finite differences.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tests.reference import homogeneous, random_unit, rodrigues
from vservo.core.geometry.spatial import (
    Pose6,
    exp_twist,
    interpolate,
    inverse,
    matrix_from_pose,
    pose_error,
    pose_from_matrix,
    pose_from_mm_deg,
    pose_to_mm_deg,
    rot_z,
    rotation_angle,
    rotation_from_rpy,
    theta_u,
    transform,
    twist_transform,
)

# ---------------------------------------------------------------------------------------
# Independent references
# ---------------------------------------------------------------------------------------


def eq_2_13(phi, theta, psi):
    """The thesis matrix of eq. 2-13, written out element by element."""
    c, s = math.cos, math.sin
    return np.array(
        [
            [c(phi) * c(theta), c(phi) * s(theta) * s(psi) - s(phi) * c(psi), c(phi) * s(theta) * c(psi) + s(phi) * s(psi)],
            [s(phi) * c(theta), s(phi) * s(theta) * s(psi) + c(phi) * c(psi), s(phi) * s(theta) * c(psi) - c(phi) * s(psi)],
            [-s(theta), c(theta) * s(psi), c(theta) * c(psi)],
        ]
    )


def sk(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def expm(A):
    """Matrix exponential by scaling and squaring of a Taylor series (numpy only)."""
    norm = float(np.abs(A).sum(axis=1).max())
    k = max(0, math.ceil(math.log2(norm / 0.25))) if norm > 0.25 else 0
    X = A / 2.0**k
    result, term = np.eye(A.shape[0]), np.eye(A.shape[0])
    for n in range(1, 30):
        term = term @ X / n
        result = result + term
    for _ in range(k):
        result = result @ result
    return result


def twist_matrix(twist):
    """The 4x4 se(3) element [[sk(w), v], [0, 0]] of a twist (v, w)."""
    X = np.zeros((4, 4))
    X[:3, :3] = sk(twist[3:])
    X[:3, 3] = twist[:3]
    return X


def random_pose(rng, theta_limit=np.pi / 2):
    return np.concatenate(
        (
            rng.uniform(-1.0, 1.0, 3),
            [rng.uniform(-np.pi, np.pi), rng.uniform(-theta_limit, theta_limit), rng.uniform(-np.pi, np.pi)],
        )
    )


def random_rigid(rng):
    """A random aMb built without vservo.core.geometry.spatial."""
    return homogeneous(rodrigues(random_unit(rng) * rng.uniform(0.0, np.pi)), rng.uniform(-1.0, 1.0, 3))


def wrap(angle):
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


@pytest.fixture
def rng():
    return np.random.default_rng(20240611)


# ---------------------------------------------------------------------------------------
# Eq. 2-13 and pose <-> matrix
# ---------------------------------------------------------------------------------------


def test_rotation_from_rpy_is_eq_2_13(rng):
    for _ in range(200):
        phi, theta, psi = rng.uniform(-2 * np.pi, 2 * np.pi, 3)
        np.testing.assert_allclose(rotation_from_rpy(phi, theta, psi), eq_2_13(phi, theta, psi), atol=1e-14)


def test_matrix_from_pose_places_translation_and_rotation(rng):
    for _ in range(20):
        pose = random_pose(rng)
        M = matrix_from_pose(pose)
        np.testing.assert_allclose(M[:3, :3], eq_2_13(*pose[3:]), atol=1e-14)
        np.testing.assert_array_equal(M[:3, 3], pose[:3])
        np.testing.assert_array_equal(M[3], [0.0, 0.0, 0.0, 1.0])


def test_pose_round_trip_away_from_gimbal_lock(rng):
    for _ in range(300):
        pose = random_pose(rng, theta_limit=np.pi / 2 - 1e-3)
        back = pose_from_matrix(matrix_from_pose(pose))
        assert isinstance(back, Pose6)
        np.testing.assert_allclose(back[:3], pose[:3], atol=1e-15)
        # Unique angles here: they come back, up to 2 pi on phi and psi.
        np.testing.assert_allclose(wrap(np.array(back[3:]) - pose[3:]), 0.0, atol=1e-11)


def test_matrix_round_trip_at_random_rotations(rng):
    for _ in range(300):
        M = random_rigid(rng)
        pose = pose_from_matrix(M)
        assert -np.pi / 2 <= pose.theta <= np.pi / 2
        assert all(-np.pi <= a <= np.pi for a in (pose.phi, pose.psi))
        np.testing.assert_allclose(matrix_from_pose(pose), M, atol=1e-13)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_gimbal_lock_matrix_round_trips(rng, sign):
    """At theta = +-pi/2 only phi -+ psi is defined, but the matrix must come back."""
    for _ in range(200):
        pose = random_pose(rng)
        pose[4] = sign * np.pi / 2
        M = matrix_from_pose(pose)
        back = pose_from_matrix(M)
        assert back.theta == pytest.approx(sign * np.pi / 2, abs=1e-12)
        np.testing.assert_allclose(matrix_from_pose(back), M, atol=1e-13)
        # The rotation about the vertical that is defined at the lock is kept.
        combined = pose[3] - pose[5] if sign > 0 else pose[3] + pose[5]
        back_combined = back.phi - back.psi if sign > 0 else back.phi + back.psi
        assert abs(wrap(back_combined - combined)) < 1e-12


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_gimbal_lock_matrix_from_opencv_round_trips(rng, sign):
    """A locked rotation assembled by OpenCV (not from angles): Rz(a) Ry(+-pi/2) Rx(b)."""
    for _ in range(50):
        a, b = rng.uniform(-np.pi, np.pi, 2)
        R = rodrigues([0, 0, a]) @ rodrigues([0, sign * np.pi / 2, 0]) @ rodrigues([b, 0, 0])
        M = homogeneous(R, rng.normal(size=3))
        np.testing.assert_allclose(matrix_from_pose(pose_from_matrix(M)), M, atol=1e-12)


@pytest.mark.parametrize("offset", [1e-12, 1e-10, 1e-9, 2e-9, 1e-8, 1e-6])
def test_matrix_round_trips_next_to_gimbal_lock(rng, offset):
    """Within ~1e-9 rad of the lock the angles are degenerate; the matrix still comes back.

    The lock branch drops the cos(theta)-sized terms, so the error is bounded by ~2 cos(theta).
    """
    for sign in (1.0, -1.0):
        for _ in range(100):
            pose = random_pose(rng)
            pose[4] = sign * (np.pi / 2 - offset)
            M = matrix_from_pose(pose)
            np.testing.assert_allclose(matrix_from_pose(pose_from_matrix(M)), M, atol=1e-8)


# ---------------------------------------------------------------------------------------
# Units at the edges
# ---------------------------------------------------------------------------------------


def test_thesis_taught_pose_in_si():
    pose = pose_from_mm_deg([36, -66, 123, 0, 0, 13.7])
    assert isinstance(pose, Pose6)
    np.testing.assert_allclose(pose, [0.036, -0.066, 0.123, 0.0, 0.0, 13.7 * math.pi / 180.0], rtol=1e-15, atol=0)
    assert pose.psi == pytest.approx(0.2391101075, abs=1e-10)
    np.testing.assert_allclose(pose_to_mm_deg(pose), [36, -66, 123, 0, 0, 13.7], rtol=1e-14, atol=1e-14)


def test_mm_deg_round_trip(rng):
    for _ in range(50):
        values = np.concatenate((rng.uniform(-2000, 2000, 3), rng.uniform(-180, 180, 3)))
        si = pose_from_mm_deg(values)
        np.testing.assert_allclose(si[:3], values[:3] * 1e-3, rtol=1e-15)
        np.testing.assert_allclose(si[3:], values[3:] * math.pi / 180.0, rtol=1e-15)
        np.testing.assert_allclose(pose_to_mm_deg(si), values, rtol=1e-14)
        np.testing.assert_allclose(pose_from_mm_deg(pose_to_mm_deg(si)), si, rtol=1e-14)


@pytest.mark.parametrize("values", [[1, 2, 3, 4, 5], [1, 2, 3, 4, 5, 6, 7], [], [[1, 2, 3, 4, 5, 6]]])
def test_pose_from_mm_deg_rejects_wrong_length(values):
    with pytest.raises(ValueError):
        pose_from_mm_deg(values)


# ---------------------------------------------------------------------------------------
# Yaskawa fixed-axis reading
# ---------------------------------------------------------------------------------------


def test_yaskawa_fixed_axis_rotations_are_eq_2_13(rng):
    """Rotate about fixed X by Rx, then fixed Y by Ry, then fixed Z by Rz (each step
    pre-multiplies, since the axes are those of the fixed frame)."""
    for _ in range(100):
        Rx, Ry, Rz = rng.uniform(-np.pi, np.pi, 3)
        R = np.eye(3)
        R = rodrigues([Rx, 0, 0]) @ R
        R = rodrigues([0, Ry, 0]) @ R
        R = rodrigues([0, 0, Rz]) @ R
        np.testing.assert_allclose(rotation_from_rpy(phi=Rz, theta=Ry, psi=Rx), R, atol=1e-14)
        # The same thing said with points: a vector turned about fixed axes in that order.
        p = rng.normal(size=3)
        q = rodrigues([0, 0, Rz]) @ (rodrigues([0, Ry, 0]) @ (rodrigues([Rx, 0, 0]) @ p))
        np.testing.assert_allclose(rotation_from_rpy(Rz, Ry, Rx) @ p, q, atol=1e-13)


def test_yaskawa_order_matters():
    """Sanity: the opposite (moving-axis X, Y, Z) reading gives a different matrix."""
    Rx, Ry, Rz = 0.3, -0.5, 0.9
    moving = rodrigues([Rx, 0, 0]) @ rodrigues([0, Ry, 0]) @ rodrigues([0, 0, Rz])
    assert np.abs(rotation_from_rpy(Rz, Ry, Rx) - moving).max() > 1e-2


# ---------------------------------------------------------------------------------------
# inverse
# ---------------------------------------------------------------------------------------


def test_inverse(rng):
    for _ in range(100):
        aMb = random_rigid(rng)
        bMa = inverse(aMb)
        np.testing.assert_allclose(bMa @ aMb, np.eye(4), atol=1e-14)
        np.testing.assert_allclose(aMb @ bMa, np.eye(4), atol=1e-14)
        np.testing.assert_allclose(bMa, np.linalg.inv(aMb), atol=1e-14)


# ---------------------------------------------------------------------------------------
# twist_transform
# ---------------------------------------------------------------------------------------


def body_twist_by_central_difference(move, h):
    """(v, w) of the body twist of a frame whose pose at time s is move(s), from poses at +-h.

    Uses OpenCV for the rotation log and the translations directly: the central difference
    cancels the second-order terms of both.
    """
    M0 = move(0.0)
    plus = np.linalg.inv(M0) @ move(h)
    minus = np.linalg.inv(M0) @ move(-h)
    w_plus, _ = cv2.Rodrigues(plus[:3, :3])
    w_minus, _ = cv2.Rodrigues(minus[:3, :3])
    v = (plus[:3, 3] - minus[:3, 3]) / (2 * h)
    w = (w_plus.ravel() - w_minus.ravel()) / (2 * h)
    return np.concatenate((v, w))


def test_twist_transform_against_finite_differences(rng):
    h = 1e-4
    for _ in range(30):
        eMc = random_rigid(rng)
        cMe = np.linalg.inv(eMc)
        bMc = random_rigid(rng)
        cVc = np.concatenate((rng.uniform(-0.5, 0.5, 3), rng.uniform(-1.0, 1.0, 3)))

        def bMe_at(s):
            bMc_s = bMc @ expm(twist_matrix(cVc * s))  # C moved by its own body twist
            return bMc_s @ cMe  # E rigidly attached to C

        eVe = body_twist_by_central_difference(bMe_at, h)
        np.testing.assert_allclose(twist_transform(eMc) @ cVc, eVe, atol=1e-6)


def test_twist_transform_thesis_form_of_eq_4_16(rng):
    for _ in range(50):
        eMc = random_rigid(rng)
        eRc, eTc = eMc[:3, :3], eMc[:3, 3]
        cTe = -eRc.T @ eTc  # translation of cMe
        V = twist_transform(eMc)
        np.testing.assert_allclose(V[:3, :3], eRc, atol=1e-15)
        np.testing.assert_allclose(V[3:, 3:], eRc, atol=1e-15)
        np.testing.assert_array_equal(V[3:, :3], np.zeros((3, 3)))
        np.testing.assert_allclose(V[:3, 3:], -eRc @ sk(cTe), atol=1e-14)


def test_twist_transform_composes_and_inverts(rng):
    for _ in range(20):
        aMb, bMc = random_rigid(rng), random_rigid(rng)
        np.testing.assert_allclose(twist_transform(aMb) @ twist_transform(bMc), twist_transform(aMb @ bMc), atol=1e-13)
        np.testing.assert_allclose(twist_transform(aMb) @ twist_transform(np.linalg.inv(aMb)), np.eye(6), atol=1e-13)


def test_twist_transform_matches_conjugated_twist_matrix(rng):
    """aVb V expresses in a the same motion: [aVb V]^ = aMb [V]^ bMa."""
    for _ in range(20):
        aMb = random_rigid(rng)
        V = rng.normal(size=6)
        np.testing.assert_allclose(twist_matrix(twist_transform(aMb) @ V), aMb @ twist_matrix(V) @ np.linalg.inv(aMb), atol=1e-13)


# ---------------------------------------------------------------------------------------
# exp_twist
# ---------------------------------------------------------------------------------------


def test_expm_reference_is_sane():
    """The test's own expm against a closed form: rotation about z and a pure translation."""
    X = twist_matrix(np.array([0, 0, 0, 0, 0, 2.5]))
    np.testing.assert_allclose(expm(X)[:3, :3], rodrigues([0, 0, 2.5]), atol=1e-14)
    np.testing.assert_allclose(expm(twist_matrix(np.array([1.0, 2, 3, 0, 0, 0]))), transform(t=(1, 2, 3)), atol=1e-15)


def test_exp_twist_pure_translation(rng):
    for _ in range(20):
        v = rng.normal(size=3)
        np.testing.assert_allclose(exp_twist(np.concatenate((v, np.zeros(3)))), homogeneous(np.eye(3), v), atol=1e-15)


def test_exp_twist_pure_rotation_is_rodrigues(rng):
    for angle in (1e-12, 1e-8, 1e-3, 0.7, 2.0, np.pi, 4.0, 9.0):
        w = random_unit(rng) * angle
        M = exp_twist(np.concatenate((np.zeros(3), w)))
        np.testing.assert_allclose(M[:3, :3], rodrigues(w), atol=1e-14)
        np.testing.assert_allclose(M[:3, 3], 0.0, atol=1e-15)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-9, 3e-9, 1e-8, 1e-7, 1e-6, 1e-4, 0.1, 1.0, 3.0, np.pi, 6.0])
def test_exp_twist_against_matrix_exponential(rng, angle):
    for _ in range(10):
        v = rng.uniform(-2.0, 2.0, 3)
        twist = np.concatenate((v, random_unit(rng) * angle))
        scale = max(1.0, float(np.linalg.norm(v)))
        np.testing.assert_allclose(exp_twist(twist), expm(twist_matrix(twist)), atol=1e-13 * scale, rtol=0)


def test_exp_twist_inverse_and_screw_axis(rng):
    for _ in range(50):
        twist = np.concatenate((rng.uniform(-1, 1, 3), rng.uniform(-3, 3, 3)))
        np.testing.assert_allclose(exp_twist(twist) @ exp_twist(-twist), np.eye(4), atol=1e-13)
        # A pure rotation about the line through q has v = -w x q and leaves q fixed.
        w, q = twist[3:], rng.uniform(-1, 1, 3)
        M = exp_twist(np.concatenate((-np.cross(w, q), w)))
        np.testing.assert_allclose(M[:3, :3] @ q + M[:3, 3], q, atol=1e-13)


# ---------------------------------------------------------------------------------------
# theta_u, rotation_angle, pose_error
# ---------------------------------------------------------------------------------------


def test_theta_u_against_opencv(rng):
    for _ in range(300):
        rvec = random_unit(rng) * rng.uniform(0.0, np.pi - 1e-3)
        R = rodrigues(rvec)
        np.testing.assert_allclose(theta_u(R), rvec, atol=1e-12)
        back, _ = cv2.Rodrigues(R)
        np.testing.assert_allclose(theta_u(R), back.ravel(), atol=1e-9)


@pytest.mark.parametrize("angle", [0.0, 1e-14, 1e-10, 1e-9, 1e-8, 1e-6])
def test_theta_u_near_zero(rng, angle):
    for _ in range(20):
        rvec = random_unit(rng) * angle
        tu = theta_u(rodrigues(rvec))
        np.testing.assert_allclose(tu, rvec, rtol=0, atol=max(angle * 1e-6, 1e-20))
        assert rotation_angle(rodrigues(rvec)) == pytest.approx(angle, rel=1e-6, abs=1e-20)


@pytest.mark.parametrize("offset", [1e-3, 1.0001e-4, 9.999e-5, 5e-5, 1e-6, 1e-7, 1e-9])
def test_theta_u_near_pi(rng, offset):
    """Just short of pi the axis sign is still defined; theta u must come back exactly."""
    for _ in range(50):
        rvec = random_unit(rng) * (np.pi - offset)
        R = rodrigues(rvec)
        tu = theta_u(R)
        np.testing.assert_allclose(np.linalg.norm(tu), np.pi - offset, atol=1e-12)
        np.testing.assert_allclose(rodrigues(tu), R, atol=1e-12)
        if offset >= 1e-7:
            np.testing.assert_allclose(tu, rvec, atol=1e-8)


def test_theta_u_exactly_pi(rng):
    """At pi the axis sign is ambiguous: compare the rebuilt rotation and the axis line."""
    axes = [random_unit(rng) for _ in range(100)] + [np.eye(3)[i] for i in range(3)]
    axes += [np.array([1.0, 1.0, 0.0]) / math.sqrt(2), np.array([1.0, -1.0, 1.0]) / math.sqrt(3)]
    for u in axes:
        R = 2.0 * np.outer(u, u) - np.eye(3)  # rotation by pi about u, built directly
        tu = theta_u(R)
        assert np.linalg.norm(tu) == pytest.approx(np.pi, abs=1e-12)
        assert abs(abs(float(tu @ u)) - np.pi) < 1e-12
        np.testing.assert_allclose(rodrigues(tu), R, atol=1e-12)
        assert rotation_angle(R) == pytest.approx(np.pi, abs=1e-12)


def test_theta_u_beyond_pi_wraps(rng):
    for _ in range(50):
        u = random_unit(rng)
        angle = rng.uniform(np.pi + 1e-3, 2 * np.pi - 1e-3)
        tu = theta_u(rodrigues(u * angle))
        np.testing.assert_allclose(tu, -u * (2 * np.pi - angle), atol=1e-12)


def test_rotation_angle_against_opencv(rng):
    for _ in range(100):
        R = rodrigues(rng.normal(size=3) * 2)
        angle = float(np.linalg.norm(cv2.Rodrigues(R)[0]))
        assert rotation_angle(R) == pytest.approx(angle, abs=1e-9)


def test_pose_error_resolves_tiny_differences(rng):
    for _ in range(50):
        aMb = random_rigid(rng)
        small_angle = 1e-10 * rng.uniform(0.5, 2.0)
        small_shift = 1e-10 * rng.uniform(0.5, 2.0)
        bMc = homogeneous(rodrigues(random_unit(rng) * small_angle), random_unit(rng) * small_shift)
        aMc = aMb @ bMc
        translation, rotation = pose_error(aMb, aMc)
        assert translation == pytest.approx(small_shift, rel=1e-5)
        assert rotation == pytest.approx(small_angle, rel=1e-5)
        assert pose_error(aMc, aMb) == pytest.approx((translation, rotation), rel=1e-5)
        assert pose_error(aMb, aMb) == (0.0, 0.0)


def test_pose_error_large_differences(rng):
    for _ in range(50):
        aMb, aMc = random_rigid(rng), random_rigid(rng)
        translation, rotation = pose_error(aMb, aMc)
        assert translation == pytest.approx(float(np.linalg.norm(aMb[:3, 3] - aMc[:3, 3])), rel=1e-14)
        expected = float(np.linalg.norm(cv2.Rodrigues(aMb[:3, :3].T @ aMc[:3, :3])[0]))
        assert rotation == pytest.approx(expected, abs=1e-9)


def test_interpolate_moves_on_the_straight_line_and_turns_about_one_axis(rng):
    aMb = matrix_from_pose(rng.uniform(-1, 1, 6))
    aMc = aMb @ transform(rot_z(0.8), (0.3, -0.1, 0.2))
    assert np.allclose(interpolate(aMb, aMc, 0.0), aMb) and np.allclose(interpolate(aMb, aMc, 1.0), aMc)
    half = interpolate(aMb, aMc, 0.5)
    assert np.allclose(half[:3, 3], (aMb[:3, 3] + aMc[:3, 3]) / 2)
    assert np.allclose(aMb[:3, :3].T @ half[:3, :3], rot_z(0.4))
