"""Camera model against OpenCV, and the interaction matrices against finite differences."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics, as_points, sony_xc55
from vservo.core.geometry.interaction import pixel_interaction_matrix, point_interaction_matrix
from vservo.core.geometry.spatial import exp_twist, inverse, matrix_from_pose

# A realistic barrel lens on a wider camera than the XC-55, so the image corners reach
# r ~ 0.8 in normalized units, where the higher-order terms matter.
WIDE = CameraModel(
    Intrinsics(fx=500.0, fy=505.0, u0=322.5, v0=236.0, width=640, height=480),
    Distortion(k1=-0.28, k2=0.09, p1=8e-4, p2=-6e-4, k3=-0.015),
)


def image_corners(camera: CameraModel) -> np.ndarray:
    """The outer corners of the sensor: pixel centres are integers, so its edges are at -0.5."""
    width, height = camera.image_size
    return np.array([[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]])


def normalized_grid(camera: CameraModel, n: int = 41) -> np.ndarray:
    """Undistorted normalized points on a grid whose bounding box holds all image corners."""
    corners = camera.pixel_to_normalized(image_corners(camera))
    low, high = corners.min(axis=0), corners.max(axis=0)
    x, y = np.meshgrid(np.linspace(low[0], high[0], n), np.linspace(low[1], high[1], n))
    return np.column_stack((x.ravel(), y.ravel()))


# --- intrinsics and the XC-55 ---------------------------------------------------------


def test_xc55_matches_thesis_table_3_1():
    camera = sony_xc55()
    k = camera.intrinsics
    assert k.fx == pytest.approx(6.0 / 0.0074, rel=1e-12)
    assert k.fy == pytest.approx(6.0 / 0.0074, rel=1e-12)
    assert k.fx == pytest.approx(810.8, abs=0.05)
    assert (k.u0, k.v0) == (320.0, 240.0)
    assert camera.image_size == (640, 480)
    assert camera.distortion.is_zero
    np.testing.assert_array_equal(k.K, [[k.fx, 0, 320], [0, k.fy, 240], [0, 0, 1]])


def test_distortion_coefficients_in_opencv_order():
    d = Distortion(k1=1.0, k2=2.0, p1=3.0, p2=4.0, k3=5.0)
    np.testing.assert_array_equal(d.as_opencv(), [1, 2, 3, 4, 5])
    assert not d.is_zero
    assert Distortion().is_zero


@pytest.mark.parametrize(
    ("fields", "name"),
    [
        ({"fx": 0.0}, "fx"),
        ({"fy": -800.0}, "fy"),
        ({"fx": float("nan")}, "fx"),
        ({"width": 0}, "width"),
        ({"height": -1}, "height"),
    ],
)
def test_intrinsics_reject_non_positive_values(fields, name):
    values = {"fx": 800.0, "fy": 800.0, "u0": 320.0, "v0": 240.0, "width": 640, "height": 480}
    with pytest.raises(ValueError, match=name):
        Intrinsics(**(values | fields))


@pytest.mark.parametrize(
    ("arguments", "name"),
    [
        ({"focal_length_m": 0.0}, "focal_length_m"),
        ({"focal_length_m": -6e-3}, "focal_length_m"),
        ({"pixel_size_m": (0.0, 7.4e-6)}, r"pixel_size_m\[0\]"),
        ({"pixel_size_m": (7.4e-6, -7.4e-6)}, r"pixel_size_m\[1\]"),
        ({"image_size_px": (0, 480)}, "width"),
        ({"image_size_px": (640, 0)}, "height"),
    ],
)
def test_from_sensor_rejects_bad_data_sheets(arguments, name):
    values = {
        "focal_length_m": 6e-3,
        "pixel_size_m": (7.4e-6, 7.4e-6),
        "principal_point_px": (320.0, 240.0),
        "image_size_px": (640, 480),
    }
    with pytest.raises(ValueError, match=name):
        Intrinsics.from_sensor(**(values | arguments))


def test_point_arrays_must_have_the_right_width():
    with pytest.raises(ValueError, match="cP"):
        sony_xc55().project([1.0, 2.0])
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        as_points(np.zeros((4, 3)), 2)


# --- projection and distortion --------------------------------------------------------


def test_projection_matches_opencv_with_distortion():
    rng = np.random.default_rng(7)
    Z = rng.uniform(0.1, 2.0, 500)
    cP = np.column_stack((rng.uniform(-0.6, 0.6, (500, 2)) * Z[:, None], Z))
    expected, _ = cv2.projectPoints(cP, np.zeros(3), np.zeros(3), WIDE.intrinsics.K, WIDE.distortion.as_opencv())
    np.testing.assert_allclose(WIDE.project(cP), expected.reshape(-1, 2), rtol=0, atol=1e-9)


def test_projection_of_a_single_point_and_of_points_behind_the_camera():
    camera = sony_xc55()
    uv = camera.project([0.01, -0.02, 0.5])
    assert uv.shape == (1, 2)
    np.testing.assert_allclose(uv[0], [320 + camera.intrinsics.fx * 0.02, 240 - camera.intrinsics.fy * 0.04])
    uv = camera.project([[0.0, 0.0, 1.0], [0.1, 0.1, 0.0], [0.1, 0.1, -1.0]])
    assert np.isfinite(uv[0]).all()
    assert np.isnan(uv[1:]).all()


@pytest.mark.parametrize("camera", [WIDE, sony_xc55()], ids=["wide", "xc55"])
def test_undistort_inverts_distort_up_to_the_image_corners(camera):
    xn = normalized_grid(camera)
    assert np.isfinite(xn).all()
    np.testing.assert_allclose(camera.undistort(camera.distort(xn)), xn, rtol=0, atol=1e-10)


@pytest.mark.parametrize("camera", [WIDE, sony_xc55()], ids=["wide", "xc55"])
def test_pixel_and_normalized_coordinates_round_trip(camera):
    xn = normalized_grid(camera)
    np.testing.assert_allclose(camera.pixel_to_normalized(camera.normalized_to_pixel(xn)), xn, rtol=0, atol=1e-10)
    corners = image_corners(camera)
    np.testing.assert_allclose(camera.normalized_to_pixel(camera.pixel_to_normalized(corners)), corners, rtol=0, atol=1e-8)


def test_distortion_is_actually_applied():
    # Barrel distortion pulls the corner points towards the centre.
    xn = normalized_grid(WIDE)
    assert np.max(np.abs(WIDE.distort(xn) - xn)) > 0.05
    corner = np.array([[0.6, 0.45]])
    assert np.linalg.norm(WIDE.distort(corner)) < np.linalg.norm(corner)


def test_ray_points_back_at_the_projected_point():
    rng = np.random.default_rng(3)
    Z = rng.uniform(0.2, 1.5, 50)
    cP = np.column_stack((rng.uniform(-0.5, 0.5, (50, 2)) * Z[:, None], Z))
    rays = WIDE.ray(WIDE.project(cP))
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rays, cP / np.linalg.norm(cP, axis=1, keepdims=True), rtol=0, atol=1e-10)
    np.testing.assert_allclose(sony_xc55().ray([320.0, 240.0]), [[0.0, 0.0, 1.0]])


def test_in_view():
    camera = sony_xc55()
    inside = np.vstack((image_corners(camera), [[320.0, 240.0]]))
    assert camera.in_view(inside).all()
    outside = [[-0.6, 240.0], [639.6, 240.0], [320.0, -1.0], [320.0, 479.6], [np.nan, 240.0]]
    assert not camera.in_view(outside).any()
    assert camera.in_view([320.0, 240.0]).shape == (1,)
    with_margin = camera.in_view(
        [[5.0, 240.0], [634.0, 240.0], [320.0, 5.0], [320.0, 474.0], [10.0, 10.0], [629.0, 469.0]],
        margin_px=10.0,
    )
    np.testing.assert_array_equal(with_margin, [False, False, False, False, True, True])


# --- interaction matrices -------------------------------------------------------------


def rate_by_finite_differences(features, cMw, wP, h=1e-6):
    """(2N, 6): column j is d features / dt while the camera moves with the unit twist e_j.

    The camera frame moves by exp_twist(twist * h) expressed in itself, so the world,
    seen from the camera, moves by its inverse.
    """
    columns = []
    for twist in np.eye(6):
        plus = features(inverse(exp_twist(twist * h)) @ cMw @ wP)
        minus = features(inverse(exp_twist(-twist * h)) @ cMw @ wP)
        columns.append((plus - minus).ravel() / (2.0 * h))
    return np.column_stack(columns)


# Three world points (homogeneous, as rows of wP.T) and a camera looking at them obliquely.
WORLD_POINTS = np.array([[0.05, -0.03, 0.0, 1.0], [-0.08, 0.02, 0.03, 1.0], [0.02, 0.09, -0.02, 1.0]]).T
CAMERA_IN_WORLD = matrix_from_pose([0.03, 0.02, -0.45, 0.3, -0.08, -0.1])


def test_point_interaction_matrix_against_finite_differences():
    cMw = inverse(CAMERA_IN_WORLD)
    cP = (cMw @ WORLD_POINTS)[:3].T
    L = point_interaction_matrix(cP[:, :2] / cP[:, 2:], cP[:, 2])
    assert L.shape == (6, 6)

    def normalized(cP_h):
        return (cP_h[:2] / cP_h[2]).T

    numeric = rate_by_finite_differences(normalized, cMw, WORLD_POINTS)
    np.testing.assert_allclose(L, numeric, rtol=0, atol=1e-7)


def test_pixel_interaction_matrix_against_finite_differences():
    # fx != fy and an off-centre principal point, so a swapped scale would show. No
    # distortion: the pixel matrix neglects its Jacobian by design.
    camera = CameraModel(Intrinsics(fx=800.0, fy=830.0, u0=331.0, v0=229.0, width=640, height=480))
    cMw = inverse(CAMERA_IN_WORLD)
    cP = (cMw @ WORLD_POINTS)[:3].T
    uv = camera.project(cP)
    assert camera.in_view(uv).all()
    L = pixel_interaction_matrix(camera, uv, cP[:, 2])

    def pixels(cP_h):
        return camera.project(cP_h[:3].T)

    numeric = rate_by_finite_differences(pixels, cMw, WORLD_POINTS)
    np.testing.assert_allclose(L, numeric, rtol=0, atol=1e-4)


def test_interaction_matrix_of_a_point_on_the_optical_axis():
    L = point_interaction_matrix([0.0, 0.0], 0.5)
    np.testing.assert_allclose(L, [[-2, 0, 0, 0, -1, 0], [0, -2, 0, 1, 0, 0]])
    with pytest.raises(ValueError, match="positive"):
        point_interaction_matrix([[0.0, 0.0], [0.1, 0.1]], [0.5, 0.0])
