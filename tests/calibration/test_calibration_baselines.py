"""The classical calibrations on exact projections of the board (no rendering): what each
recovers, what each model leaves out, and their files."""

import numpy as np
import pytest

from vservo.core.calibration.baselines import (
    FreeHandEye,
    HandEyeAXXB,
    PlanarHomography,
    calibrate_camera,
    load_classical,
    save_classical,
)
from vservo.core.calibration.dataset import CalibrationDataset
from vservo.core.geometry.camera import CameraModel, Distortion, sony_xc55
from vservo.core.geometry.spatial import exp_twist, inverse, rot_x, rot_z, rotation_angle, transform

TABLE_Z = -0.175
LENS = CameraModel(sony_xc55().intrinsics, Distortion(-0.16, 0.11, 6e-4, -4e-4, -0.02))
K1_ONLY = CameraModel(sony_xc55().intrinsics, Distortion(-0.16))
eMc_TRUE = exp_twist([0.0006, -0.0005, 0.0012, 0.006, -0.005, 0.007])


def projected(camera, bMe_list, eMc=eMc_TRUE):
    """Every lattice corner (10 mm) the camera sees from each pose, by exact projection."""
    pixels, world, view = [], [], []
    for k, bMe in enumerate(bMe_list):
        cMb = inverse(bMe @ eMc)
        centre = np.round((bMe[:2, 3]) / 0.01).astype(int)
        ij = np.stack(np.meshgrid(np.arange(-20, 21), np.arange(-20, 21), indexing="ij"), -1).reshape(-1, 2) + centre
        points = np.column_stack((ij * 0.01, np.full(len(ij), TABLE_Z)))
        uv = camera.project(points @ cMb[:3, :3].T + cMb[:3, 3])
        keep = camera.in_view(uv, margin_px=5.0)
        pixels.append(uv[keep])
        world.append(ij[keep] * 0.01)
        view.append(np.full(keep.sum(), k))
    return CalibrationDataset(np.concatenate(pixels), np.concatenate(world), np.concatenate(view), np.array(bMe_list))


def planar_poses(rng, n):
    return [
        transform(rot_x(np.pi), (-0.45 + rng.uniform(-0.04, 0.04), rng.uniform(-0.04, 0.04), TABLE_Z + 0.3)) for _ in range(n)
    ]


def rotated_poses(rng, n):
    poses = []
    for _ in range(n):
        axis = rng.uniform(0, 2 * np.pi)
        tilt = np.deg2rad(rng.uniform(8, 20)) * np.array([np.cos(axis), np.sin(axis), 0.0])
        bRc = exp_twist([0, 0, 0, *tilt])[:3, :3] @ rot_x(np.pi) @ rot_z(np.deg2rad(90 * rng.integers(4) + rng.uniform(-5, 5)))
        eye = np.array([-0.45, 0.0, TABLE_Z]) - 0.3 * bRc[:, 2]
        poses.append(transform(bRc, eye) @ inverse(eMc_TRUE))
    return poses


def world_error_mm(calibration, data):
    return 1000 * np.linalg.norm(calibration.world_of(data.pixels_px, data.bMe[data.view]) - data.world_m, axis=1)


@pytest.fixture(scope="module")
def cell_data():
    rng = np.random.default_rng(2)
    return projected(LENS, rotated_poses(rng, 12)), projected(LENS, planar_poses(rng, 10)), projected(LENS, planar_poses(rng, 5))


def test_axxb_recovers_the_hand_eye_transform_and_the_board(cell_data):
    rotated, _, test = cell_data
    axxb = HandEyeAXXB.fit(rotated, sony_xc55())
    assert np.linalg.norm(axxb.eMc[:3, 3] - eMc_TRUE[:3, 3]) < 2e-4
    assert np.rad2deg(rotation_angle(axxb.eMc[:3, :3].T @ eMc_TRUE[:3, :3])) < 0.02
    assert abs(axxb.bMw[2, 3] - TABLE_Z) < 2e-4
    assert np.mean(world_error_mm(axxb, test)) < 0.05


def test_the_camera_calibration_finds_the_lens(cell_data):
    camera, cMw, rms = calibrate_camera(cell_data[0], sony_xc55())
    assert rms < 1e-3 and len(cMw) == 12
    assert np.allclose(camera.distortion.as_opencv(), LENS.distortion.as_opencv(), atol=2e-3)


def test_the_planar_homography_is_exact_for_a_perfect_arm(cell_data):
    rotated, planar, test = cell_data
    camera, _, _ = calibrate_camera(rotated, sony_xc55())
    assert np.max(world_error_mm(PlanarHomography.fit(planar, camera), test)) < 0.01


def test_free_hand_eye_is_exact_with_a_k1_lens_and_misses_higher_order_distortion():
    rng = np.random.default_rng(4)
    planar_poses_, test_poses = planar_poses(rng, 6), planar_poses(rng, 4)
    k1_fit = FreeHandEye.fit(projected(K1_ONLY, planar_poses_), sony_xc55())
    assert np.max(world_error_mm(k1_fit, projected(K1_ONLY, test_poses))) < 0.01
    lens_fit = FreeHandEye.fit(projected(LENS, planar_poses_), sony_xc55())
    assert np.max(world_error_mm(lens_fit, projected(LENS, test_poses))) > 0.1


@pytest.mark.slow
def test_classical_calibrations_survive_a_save_load_round_trip(tmp_path, cell_data):
    rotated, planar, test = cell_data
    camera, _, _ = calibrate_camera(rotated, sony_xc55())
    bMe = test.bMe[test.view]
    for calibration in (
        FreeHandEye.fit(planar, sony_xc55()),
        HandEyeAXXB.fit(rotated, sony_xc55()),
        PlanarHomography.fit(planar, camera),
    ):
        loaded = load_classical(save_classical(calibration, tmp_path / f"{calibration.name}.npz"))
        assert type(loaded) is type(calibration)
        assert np.array_equal(loaded.world_of(test.pixels_px, bMe), calibration.world_of(test.pixels_px, bMe))
