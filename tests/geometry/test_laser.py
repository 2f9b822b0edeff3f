"""Laser pointer geometry: the thesis set-up, ray casting, and depth from the spot."""

from __future__ import annotations

import numpy as np
import pytest

from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics, sony_xc55
from vservo.core.geometry.laser import LaserPointer, Ray, in_plane_range
from vservo.core.geometry.spatial import matrix_from_pose, pose_from_mm_deg, rotation_from_rpy, transform

BASELINE = 0.030
ALPHA = np.deg2rad(80.0)

DISTORTED = CameraModel(
    Intrinsics(fx=790.0, fy=795.0, u0=318.0, v0=243.0, width=640, height=480),
    Distortion(k1=-0.22, k2=0.08, p1=6e-4, p2=-4e-4, k3=-0.01),
)
CAMERAS = pytest.mark.parametrize("camera", [sony_xc55(), DISTORTED], ids=["xc55", "distorted"])


def plane_through(point, normal):
    """(n, offset) of the plane {p : n . p = offset} through ``point``."""
    normal = np.asarray(normal, dtype=float)
    return normal, float(normal @ point)


def tilted_normal(rng, max_tilt_rad):
    """A unit normal within max_tilt_rad of the optical axis."""
    roll, pitch = rng.uniform(-max_tilt_rad, max_tilt_rad, 2)
    return rotation_from_rpy(0.0, pitch, roll) @ [0.0, 0.0, 1.0]


# --- the thesis configuration ---------------------------------------------------------


def test_in_plane_is_the_thesis_hand_laser_pose():
    laser = LaserPointer.in_plane(BASELINE, ALPHA)
    np.testing.assert_allclose(laser.cMl, matrix_from_pose(pose_from_mm_deg([30, 0, 0, 0, -10, 0])), rtol=0, atol=1e-15)
    np.testing.assert_allclose(laser.origin_c, [0.030, 0.0, 0.0])
    # Tilted towards the optical axis, at alpha from the baseline (laser -> lens is -x).
    np.testing.assert_allclose(laser.direction_c, [-np.cos(ALPHA), 0.0, np.sin(ALPHA)], atol=1e-15)


def test_the_thesis_laser_check():
    """d = 30 mm, alpha = 80 deg, XC-55, plane facing the camera at 162 mm: spot at (327.2, 240)."""
    camera = sony_xc55()
    laser = LaserPointer.in_plane(BASELINE, ALPHA)
    spot_c = laser.spot_on_plane([0.0, 0.0, 1.0], 0.162)
    assert spot_c[2] == pytest.approx(0.162)
    spot_px = camera.project(spot_c)[0]
    np.testing.assert_allclose(spot_px, [327.0, 240.0], atol=0.5)
    assert spot_px[0] == pytest.approx(327.2, abs=0.05)

    depth = laser.triangulate(camera, spot_px)
    assert depth.depth_m == pytest.approx(0.162, abs=1e-12)
    range_m, depth_m = in_plane_range(spot_px, camera, BASELINE, ALPHA)
    assert depth_m == pytest.approx(0.162, abs=1e-12)
    assert range_m > depth_m


# --- ray casting ------------------------------------------------------------------------


def test_ray_basics():
    ray = Ray(origin=[1.0, 2.0, 3.0], direction=[0.0, 0.0, 2.0])
    np.testing.assert_allclose(ray.direction, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(ray.point_at(0.5), [1.0, 2.0, 3.5])
    np.testing.assert_allclose(ray.point_at([0.0, 1.0]), [[1.0, 2.0, 3.0], [1.0, 2.0, 4.0]])
    assert ray.intersect_plane([0.0, 0.0, 2.0], 10.0) == pytest.approx(2.0)
    assert ray.intersect_plane([0.0, 0.0, 1.0], 1.0) is None  # behind the origin
    assert ray.intersect_plane([1.0, 0.0, 0.0], 5.0) is None  # parallel
    with pytest.raises(ValueError, match="direction"):
        Ray([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        ray.origin[0] = 5.0  # frozen means frozen


def test_beam_in_the_world_frame():
    laser = LaserPointer.in_plane(BASELINE, ALPHA)
    wMc = matrix_from_pose([0.4, -0.1, 0.6, 0.5, 2.8, -0.3])
    beam_w = laser.beam(wMc)
    np.testing.assert_allclose(beam_w.origin, (wMc @ laser.cMl)[:3, 3], atol=1e-15)
    np.testing.assert_allclose(beam_w.direction, (wMc @ laser.cMl)[:3, 2], atol=1e-15)
    np.testing.assert_allclose(laser.beam().origin, laser.origin_c)


def test_spot_on_plane_misses():
    laser = LaserPointer.in_plane(BASELINE, ALPHA)
    assert laser.spot_on_plane([0.0, 0.0, 1.0], -0.1) is None  # plane behind the laser
    assert laser.spot_on_plane([0.0, 1.0, 0.0], 0.1) is None  # the beam runs in the plane y = 0


def test_laser_pose_must_be_rigid():
    with pytest.raises(ValueError, match="rotation"):
        LaserPointer(np.diag([1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="cMl"):
        LaserPointer(np.eye(3))


# --- depth from the spot -----------------------------------------------------------------


def laser_rotation(alpha_rad):
    return LaserPointer.in_plane(BASELINE, alpha_rad).cMl[:3, :3]


@CAMERAS
def test_triangulation_recovers_the_ray_cast_spot_for_any_laser_pose(camera):
    rng = np.random.default_rng(11)
    for _ in range(200):
        misalignment = rotation_from_rpy(*rng.uniform(-np.deg2rad(3.0), np.deg2rad(3.0), 3))
        offset = np.array([BASELINE, 0.0, 0.0]) + rng.uniform(-0.005, 0.005, 3)
        laser = LaserPointer(transform(laser_rotation(ALPHA) @ misalignment, offset))
        n_c, offset_c = plane_through([0.0, 0.0, rng.uniform(0.08, 0.5)], tilted_normal(rng, np.deg2rad(35.0)))

        spot_c = laser.spot_on_plane(n_c, offset_c)
        spot_px = camera.project(spot_c)[0]
        assert camera.in_view(spot_px)[0]

        depth = laser.triangulate(camera, spot_px)
        assert depth.depth_m == pytest.approx(spot_c[2], abs=1e-5)
        np.testing.assert_allclose(depth.point_c, spot_c, rtol=0, atol=1e-9)
        assert depth.range_m == pytest.approx(np.linalg.norm(spot_c), abs=1e-9)
        assert depth.ray_gap_m < 1e-9


def test_ray_gap_reveals_a_wrong_calibration():
    camera = sony_xc55()
    true_laser = LaserPointer.in_plane(BASELINE, ALPHA)
    spot_px = camera.project(true_laser.spot_on_plane([0.0, 0.0, 1.0], 0.2))[0]
    # The same laser believed to sit 2 mm lower (+y): the beam no longer meets the viewing ray.
    believed = LaserPointer(transform(true_laser.cMl[:3, :3], [BASELINE, 0.002, 0.0]))
    assert believed.triangulate(camera, spot_px).ray_gap_m == pytest.approx(0.002, rel=1e-3)
    assert true_laser.triangulate(camera, spot_px).ray_gap_m < 1e-12


def test_triangulation_rejects_impossible_spots():
    camera = sony_xc55()
    laser = LaserPointer.in_plane(BASELINE, ALPHA)
    fx = camera.intrinsics.fx
    # The viewing ray with x = -cot(alpha) runs parallel to the beam.
    parallel_px = [320.0 - fx / np.tan(ALPHA), 240.0]
    with pytest.raises(ValueError, match="parallel"):
        laser.triangulate(camera, parallel_px)
    # Further left, the two lines cross behind the camera.
    with pytest.raises(ValueError, match="behind the camera"):
        laser.triangulate(camera, [100.0, 240.0])
    with pytest.raises(ValueError, match="in front of the camera"):
        in_plane_range([100.0, 240.0], camera, BASELINE, ALPHA)


@pytest.mark.parametrize("plane_depth_m", [0.08, 0.12, 0.162, 0.17, 0.25, 0.4, 0.8])
@CAMERAS
def test_eq_4_21_agrees_with_the_general_triangulation(camera, plane_depth_m):
    """The closed form of the thesis, with the spot right of, at, and left of the principal point.

    The beam crosses the optical axis at Z = d tan(alpha) = 170 mm: nearer planes put the
    spot on the laser's side (u > u0), further ones on the other side.
    """
    laser = LaserPointer.in_plane(BASELINE, ALPHA)
    normal = rotation_from_rpy(0.0, 0.3, 0.2) @ [0.0, 0.0, 1.0]
    spot_c = laser.spot_on_plane(*plane_through([0.0, 0.0, plane_depth_m], normal))
    spot_px = camera.project(spot_c)[0]
    assert (spot_c[0] > 0.0) == (plane_depth_m < BASELINE * np.tan(ALPHA))

    range_m, depth_m = in_plane_range(spot_px, camera, BASELINE, ALPHA)
    general = laser.triangulate(camera, spot_px)
    assert depth_m == pytest.approx(general.depth_m, abs=1e-9)
    assert range_m == pytest.approx(general.range_m, abs=1e-9)
    assert depth_m == pytest.approx(spot_c[2], abs=1e-9)


def test_in_plane_range_rejects_a_bad_geometry():
    camera = sony_xc55()
    with pytest.raises(ValueError, match="baseline_m"):
        in_plane_range([327.0, 240.0], camera, 0.0, ALPHA)
    with pytest.raises(ValueError, match="alpha_rad"):
        in_plane_range([327.0, 240.0], camera, BASELINE, np.pi)
