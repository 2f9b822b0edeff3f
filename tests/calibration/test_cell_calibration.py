"""Commissioning's estimation core on a synthetic cell whose truth is known: a camera off
its data sheet (focal length 5 %, principal point 16 px, a real lens's distortion), the
camera 20 mm and 5 deg off the flange, the laser 10 mm and 2 deg off its nominal beam,
corners found to 0.05 px. Images, where the board must be found, are rendered through
the true camera with exact pixel coverage (``Checkerboard.render``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vservo.core.calibration.board_views import BoardView, find_board
from vservo.core.calibration.cell_calibration import (
    AcceptanceCheck,
    acceptance_errors,
    board_pose,
    calibrate_camera_views,
    calibrate_hand_eye,
    grid_dataset,
    pose_error_mm_deg,
)
from vservo.core.calibration.checkerboard import BoardNotFound, Checkerboard
from vservo.core.calibration.laser_calibration import beam_line_error, fit_laser_beam
from vservo.core.calibration.mlp import train_nn
from vservo.core.cell.config import BoardConfig
from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics, sony_xc55
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import (
    Matrix,
    exp_twist,
    inverse,
    matrix_from_pose,
    pose_from_mm_deg,
    rot_x,
    rot_z,
    transform,
)

NOMINAL = sony_xc55()
TRUE_CAMERA = CameraModel(
    Intrinsics(1.05 * NOMINAL.intrinsics.fx, 1.05 * NOMINAL.intrinsics.fy, 336.0, 224.0, 640, 480),
    Distortion(-0.16, 0.11, 6e-4, -4e-4, -0.02),
)
BOARD = BoardConfig(0.010, (8, 5), matrix_from_pose(pose_from_mm_deg([-435.0, -30.0, -175.0, 0.0, 0.0, 0.0])))
# Where the board really lies: a few mm and a degree from the cell file's rough pose.
bMboard_TRUE = BOARD.bMboard @ matrix_from_pose(pose_from_mm_deg([3.0, -2.0, 1.0, 1.0, 0.4, -0.3]))
# The camera 20 mm and 5 deg off the flange (the nominal eMc is the identity).
eMc_TRUE = transform(
    exp_twist([0, 0, 0, *np.radians(5.0) * np.array([1.0, -1.0, 2.0]) / np.sqrt(6.0)])[:3, :3], [0.012, -0.016, 0.0]
)
# The thesis laser (d = 30 mm, alpha = 80 deg) moved 10 mm across and turned 2 deg.
cMl_NOMINAL = LaserPointer.in_plane(0.030, np.radians(80.0)).cMl
cMl_TRUE = (
    transform(np.eye(3), [0.006, 0.008, 0.0]) @ cMl_NOMINAL @ exp_twist([0, 0, 0, *np.radians(2.0) * np.array([0.6, 0.8, 0.0])])
)
NOISE_PX = 0.05
CENTRE_board = np.array([0.035, 0.020, 0.0])


def look_at(eye: Matrix, target: Matrix, roll_rad: float) -> Matrix:
    """boardMc of a camera at ``eye`` whose optical axis runs through ``target``, turned by
    ``roll_rad`` about that axis from 'image x along the board's x'."""
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    return transform(np.column_stack((x, np.cross(z, x), z)), eye) @ transform(rot_z(roll_rad))


def project(camera: CameraModel, boardMc: Matrix, points_board: Matrix) -> Matrix:
    cMboard = inverse(boardMc)
    return camera.project(points_board @ cMboard[:3, :3].T + cMboard[:3, 3])


def noisy_view(boardMc: Matrix, rng: np.random.Generator) -> BoardView:
    corners = BOARD.corners_board()
    return BoardView(project(TRUE_CAMERA, boardMc, corners) + rng.normal(0.0, NOISE_PX, (len(corners), 2)), corners)


def tilted_views(count: int, rng: np.random.Generator, tilt_deg: tuple[float, float] = (15.0, 35.0)) -> list[Matrix]:
    """boardMc of ``count`` views 150-260 mm from the board, tilted and rolled every way,
    the whole board in view with 20 px to spare."""
    poses: list[Matrix] = []
    while len(poses) < count:
        tilt, azimuth = np.radians(rng.uniform(*tilt_deg)), rng.uniform(0.0, 2 * np.pi)
        direction = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])
        target = CENTRE_board + np.append(rng.uniform(-0.025, 0.025, 2), 0.0)
        boardMc = look_at(target + rng.uniform(0.15, 0.26) * direction, target, rng.uniform(-np.pi, np.pi))
        if np.all(TRUE_CAMERA.in_view(project(TRUE_CAMERA, boardMc, BOARD.corners_board()), 20.0)):
            poses.append(boardMc)
    return poses


@pytest.fixture(scope="module")
def commissioning() -> dict:
    """The camera and hand-eye steps on 24 tilted views."""
    rng = np.random.default_rng(7)
    boardMc = tilted_views(24, rng)
    views = [noisy_view(M, rng) for M in boardMc]
    bMe = [bMboard_TRUE @ M @ inverse(eMc_TRUE) for M in boardMc]
    camera = calibrate_camera_views(views, NOMINAL)
    hand_eye = calibrate_hand_eye(bMe, views, camera.camera, camera.cMboard)
    return {"views": views, "bMe": bMe, "boardMc": boardMc, "camera": camera, "hand_eye": hand_eye}


# -- finding and naming the board -------------------------------------------------------

RENDER = Checkerboard(BOARD.square_m, (0, 7, 0, 4), table_height_m=0.0)


def rendered(boardMc: Matrix) -> np.ndarray:
    return RENDER.render(TRUE_CAMERA, boardMc)


@pytest.mark.parametrize("roll_deg", [0.0, 90.0, 180.0, 270.0, 30.0])
def test_find_board_names_the_corners_however_the_board_is_turned(roll_deg: float) -> None:
    boardMc = look_at(CENTRE_board + np.array([0.02, -0.03, 0.22]), CENTRE_board, np.radians(roll_deg))
    view = find_board(BOARD, rendered(boardMc))
    truth = project(TRUE_CAMERA, boardMc, BOARD.corners_board())
    np.testing.assert_array_equal(view.corners_board, BOARD.corners_board())
    assert np.max(np.linalg.norm(view.corners_px - truth, axis=1)) < 0.1
    assert not view.corners_px.flags.writeable and not view.corners_board.flags.writeable


def test_find_board_leaves_out_the_corners_near_the_spot() -> None:
    boardMc = look_at(CENTRE_board + np.array([0.0, 0.0, 0.2]), CENTRE_board, 0.0)
    image = rendered(boardMc)
    # The spot in the middle of square (3, 2): its four corners 30 px away, the next 67 px.
    spot = project(TRUE_CAMERA, boardMc, np.array([[0.035, 0.025, 0.0]]))[0]
    view = find_board(BOARD, cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), spot_px=spot, spot_radius_px=45.0)
    left_out = {tuple(np.round(c * 100)) for c in BOARD.corners_board()} - {tuple(np.round(c * 100)) for c in view.corners_board}
    assert left_out == {(3, 2, 0), (4, 2, 0), (3, 3, 0), (4, 3, 0)}
    truth = project(TRUE_CAMERA, boardMc, view.corners_board)
    assert np.max(np.linalg.norm(view.corners_px - truth, axis=1)) < 0.1


def test_find_board_refuses_what_it_cannot_find_or_name() -> None:
    boardMc = look_at(CENTRE_board + np.array([0.0, 0.0, 0.2]), CENTRE_board, 0.0)
    image = rendered(boardMc)
    with pytest.raises(BoardNotFound, match="no checkerboard of 8 x 5"):
        find_board(BOARD, np.full_like(image, 200))
    half_out = look_at(CENTRE_board + np.array([0.05, 0.0, 0.2]), CENTRE_board + np.array([0.05, 0.0, 0.0]), 0.0)
    with pytest.raises(BoardNotFound, match="all of it must be in view"):
        find_board(BOARD, rendered(half_out))
    # White blots in the middle of four black squares: the corners are found, the colouring is spoiled.
    blotted = image.copy()
    for centre in (0.005, 0.005), (0.025, 0.005), (0.045, 0.005), (0.065, 0.005):
        u, v = np.round(project(TRUE_CAMERA, boardMc, np.array([[*centre, 0.0]]))[0]).astype(int)
        blotted[v - 4 : v + 5, u - 4 : u + 5] = image.max()
    with pytest.raises(BoardNotFound, match="no ordering of the grid shows the board's colouring"):
        find_board(BOARD, blotted)
    with pytest.raises(BoardNotFound, match="looks the same turned half round"):
        find_board(BoardConfig(0.010, (7, 5), BOARD.bMboard), image)
    with pytest.raises(BoardNotFound, match="8-bit"):
        find_board(BOARD, image.astype(np.float32))


# -- the camera --------------------------------------------------------------------------


@pytest.mark.slow
def test_camera_calibration_recovers_the_true_camera(commissioning: dict) -> None:
    calibration = commissioning["camera"]
    found, truth = calibration.camera.intrinsics, TRUE_CAMERA.intrinsics
    assert abs(found.fx / truth.fx - 1.0) < 0.005 and abs(found.fy / truth.fy - 1.0) < 0.005
    assert abs(found.u0 - truth.u0) < 2.0 and abs(found.v0 - truth.v0) < 2.0
    assert calibration.rms_px == pytest.approx(np.sqrt(2) * NOISE_PX, rel=0.1)  # per corner: the noise on u and v
    assert len(calibration.view_rms_px) == 24 and np.all(calibration.view_rms_px < 0.1)
    assert calibration.std_fx_px < 0.002 * found.fx and calibration.std_u0_px < 1.0
    for boardMc, cMboard in zip(commissioning["boardMc"], calibration.cMboard):
        mm, deg = pose_error_mm_deg(cMboard, inverse(boardMc))
        assert mm < 0.5 and deg < 0.2  # a board 7 cm wide: its tilt is the least certain
    assert calibration.verdict.good, calibration.verdict.reason
    assert calibration.verdict.reason.startswith("good: RMS 0.0")


@pytest.mark.slow
def test_camera_verdict_says_retake_for_few_or_flat_views(commissioning: dict) -> None:
    few = calibrate_camera_views(commissioning["views"][:6], NOMINAL)
    assert not few.verdict.good and "only 6 views, take at least 10" in few.verdict.reason
    rng = np.random.default_rng(3)
    flat = calibrate_camera_views([noisy_view(M, rng) for M in tilted_views(12, rng, (0.0, 2.0))], NOMINAL)
    assert not flat.verdict.good and "tilt the camera more" in flat.verdict.reason


@pytest.mark.slow
def test_camera_refuses_bad_views(commissioning: dict) -> None:
    views = list(commissioning["views"][:5])
    with pytest.raises(ValueError, match="at least 3 views, got 2"):
        calibrate_camera_views(views[:2], NOMINAL)
    views[3] = BoardView(views[3].corners_px[:6], views[3].corners_board[:6])
    with pytest.raises(ValueError, match="view 3 has 6 corners: a view needs at least 10"):
        calibrate_camera_views(views, NOMINAL)
    with pytest.raises(ValueError, match=r"corners_px \(N, 2\) and corners_board \(N, 3\)"):
        BoardView(np.zeros((5, 2)), np.zeros((4, 3)))


@pytest.mark.slow
def test_a_blurred_view_is_named_in_the_verdict(commissioning: dict) -> None:
    views = list(commissioning["views"])
    rng = np.random.default_rng(5)
    views[4] = BoardView(views[4].corners_px + rng.normal(0.0, 2.0, views[4].corners_px.shape), views[4].corners_board)
    verdict = calibrate_camera_views(views, NOMINAL).verdict
    assert not verdict.good and "view 4 reprojects at" in verdict.reason


# -- hand-eye and the board -------------------------------------------------------------


@pytest.mark.slow
def test_hand_eye_recovers_eMc_and_the_board(commissioning: dict) -> None:
    hand_eye = commissioning["hand_eye"]
    mm, deg = pose_error_mm_deg(hand_eye.eMc, eMc_TRUE)
    assert mm < 1.0 and deg < 0.2
    mm, deg = pose_error_mm_deg(hand_eye.bMboard, bMboard_TRUE)
    assert mm < 0.5 and deg < 0.1
    assert hand_eye.rms_px == pytest.approx(np.sqrt(2) * NOISE_PX, rel=0.1)  # per corner: the noise on u and v
    assert hand_eye.spread_mm < 0.5 and hand_eye.spread_deg < 0.1
    assert hand_eye.turn_deg[1] > 10.0
    assert hand_eye.verdict.good, hand_eye.verdict.reason


@pytest.mark.slow
def test_hand_eye_holds_when_the_arm_is_off(commissioning: dict) -> None:
    """A 0.2 mm / 0.02 deg error in each reading: eMc still within 1 mm and 0.2 deg, and
    the reprojection through the arm's poses shows the readings' error."""
    rng = np.random.default_rng(11)
    bMe = [
        M @ exp_twist(np.concatenate((rng.normal(0, 0.2e-3, 3), np.radians(rng.normal(0, 0.02, 3)))))
        for M in commissioning["bMe"]
    ]
    hand_eye = calibrate_hand_eye(bMe, commissioning["views"], commissioning["camera"].camera, commissioning["camera"].cMboard)
    mm, deg = pose_error_mm_deg(hand_eye.eMc, eMc_TRUE)
    assert mm < 1.0 and deg < 0.2
    assert hand_eye.rms_px > 5 * commissioning["hand_eye"].rms_px
    assert hand_eye.verdict.good, hand_eye.verdict.reason


@pytest.mark.slow
def test_hand_eye_says_retake_for_turns_about_one_axis_and_a_moved_board(commissioning: dict) -> None:
    rng = np.random.default_rng(4)
    # Turns about the board's x axis, plus a sliver about y: solvable, badly posed.
    boardMc = [
        look_at(
            CENTRE_board + 0.22 * np.array([0.0, np.sin(a), np.cos(a)]) + np.array([1e-3 * a, 0, 0]),
            CENTRE_board,
            np.radians(0.5) * k,
        )
        for k, a in enumerate(np.radians(np.linspace(-20, 20, 10)))
    ]
    views = [noisy_view(M, rng) for M in boardMc]
    camera = commissioning["camera"].camera
    cMboard = [board_pose(camera, v) for v in views]
    bMe = [bMboard_TRUE @ M @ inverse(eMc_TRUE) for M in boardMc]
    verdict = calibrate_hand_eye(bMe, views, camera, cMboard).verdict
    assert not verdict.good and "tilt it about two axes" in verdict.reason
    moved = list(commissioning["bMe"])
    moved[5:] = [transform(np.eye(3), [0.004, 0.0, 0.0]) @ M for M in moved[5:]]
    verdict = calibrate_hand_eye(moved, commissioning["views"], camera, commissioning["camera"].cMboard).verdict
    assert not verdict.good and "the board moved" in verdict.reason


@pytest.mark.slow
def test_hand_eye_refuses_views_that_cannot_fix_eMc(commissioning: dict) -> None:
    views, camera = commissioning["views"], commissioning["camera"]
    with pytest.raises(ValueError, match="4 poses, 5 views, 5 board poses"):
        calibrate_hand_eye(commissioning["bMe"][:4], views[:5], camera.camera, camera.cMboard[:5])
    bMe = [transform(rot_z(0.1 * k) @ rot_x(np.pi), [-0.4, 0.0, 0.1]) for k in range(4)]
    cMboard = [inverse(bMe[k] @ eMc_TRUE) @ bMboard_TRUE for k in range(4)]
    with pytest.raises(ValueError, match="all about one axis"):
        calibrate_hand_eye(bMe, views[:4], camera.camera, cMboard)


# -- the laser -------------------------------------------------------------------------------


def laser_views(camera: CameraModel, rng: np.random.Generator) -> tuple[Matrix, list[Matrix]]:
    """The spot (N, 2) px and the board's pose measured through ``camera``, in views from
    150 to 280 mm, tilted up to 15 deg, the spot on the board sheet and the board in view."""
    laser = LaserPointer(cMl_TRUE)
    spots, cMboard = [], []
    while len(spots) < 12:
        depth = 0.15 + 0.13 * len(spots) / 11
        tilt = rot_x(np.pi) @ exp_twist([0, 0, 0, *np.radians(rng.uniform(-15, 15, 3))])[:3, :3]
        beam_point = tilt @ (cMl_TRUE[:3, 3] + (depth - cMl_TRUE[2, 3]) / cMl_TRUE[2, 2] * cMl_TRUE[:3, 2])
        spot_board = np.array([rng.uniform(0.0, 0.07), rng.uniform(0.0, 0.04), 0.0])
        boardMc = transform(tilt, spot_board - beam_point)
        if not np.all(TRUE_CAMERA.in_view(project(TRUE_CAMERA, boardMc, BOARD.corners_board()), 10.0)):
            continue
        cMb = inverse(boardMc)
        spot_c = laser.spot_on_plane(cMb[:3, 2], float(cMb[:3, 2] @ cMb[:3, 3]))
        spots.append(TRUE_CAMERA.project(spot_c)[0] + rng.normal(0.0, 0.1, 2))
        cMboard.append(board_pose(camera, noisy_view(boardMc, rng)))
    return np.array(spots), cMboard


@pytest.mark.slow
def test_laser_beam_is_recovered_through_the_calibrated_camera(commissioning: dict) -> None:
    camera = commissioning["camera"].camera
    spots, cMboard = laser_views(camera, np.random.default_rng(9))
    laser = fit_laser_beam(camera, spots, cMboard)
    angle_deg, offset_mm = beam_line_error(laser.cMl, cMl_TRUE, 0.162)
    assert angle_deg < 0.2 and offset_mm < 0.5
    nominal_angle, nominal_offset = beam_line_error(cMl_NOMINAL, cMl_TRUE, 0.162)
    assert nominal_angle > 1.9 and nominal_offset > 9.0  # the test's truth is far from nominal
    assert laser.rms_mm < 0.2 and laser.depth_span_mm > 100.0
    assert laser.verdict.good, laser.verdict.reason
    # The fixed form: origin on z_c = 0, y in the plane of the beam and the camera's y (x normal to it).
    assert laser.cMl[2, 3] == pytest.approx(0.0, abs=1e-12) and laser.cMl[1, 0] == pytest.approx(0.0, abs=1e-12)
    assert laser.baseline_m == pytest.approx(np.linalg.norm(laser.cMl[:3, 3]))


def test_the_in_plane_laser_is_written_as_in_plane() -> None:
    """A beam in the camera's x-z plane gives back LaserPointer.in_plane(d, alpha) exactly."""
    truth = LaserPointer.in_plane(0.030, np.radians(80.0))
    cMboard = [transform(rot_x(np.pi + np.radians(a)), [0.0, 0.0, z]) for a, z in ((5.0, 0.12), (-5.0, 0.2), (8.0, 0.3))]
    spots = np.array([NOMINAL.project(truth.spot_on_plane(M[:3, 2], float(M[:3, 2] @ M[:3, 3])))[0] for M in cMboard])
    laser = fit_laser_beam(NOMINAL, spots, cMboard)
    np.testing.assert_allclose(laser.cMl, truth.cMl, atol=1e-9)
    assert laser.baseline_m == pytest.approx(0.030) and np.degrees(laser.alpha_rad) == pytest.approx(80.0)


@pytest.mark.slow
def test_laser_verdict_and_refusals(commissioning: dict) -> None:
    camera = commissioning["camera"].camera
    spots, cMboard = laser_views(camera, np.random.default_rng(9))
    near = fit_laser_beam(camera, spots[:3], cMboard[:3])
    assert not near.verdict.good and "take views nearer to and farther from the board" in near.verdict.reason
    misfound = spots.copy()
    misfound[4] += (16.0, -12.0)  # a reflection taken for the spot
    verdict = fit_laser_beam(camera, misfound, cMboard).verdict
    assert not verdict.good and "a spot was misfound" in verdict.reason
    with pytest.raises(ValueError, match="at least 3 spots"):
        fit_laser_beam(camera, spots[:2], cMboard[:2])
    with pytest.raises(ValueError, match="5 spots, 4 board poses"):
        fit_laser_beam(camera, spots[:5], cMboard[:4])
    behind = [transform(np.eye(3), [0.0, 0.0, -0.2])] * 3
    with pytest.raises(ValueError, match="spot 0 .* does not meet its view's board"):
        fit_laser_beam(camera, spots[:3], behind)


def test_beam_line_error_measures_angle_and_offset_at_a_depth() -> None:
    a = LaserPointer.in_plane(0.030, np.radians(80.0)).cMl
    moved = transform(np.eye(3), [0.0, 0.002, 0.0]) @ a
    assert beam_line_error(a, moved, 0.162) == pytest.approx((0.0, 2.0))
    turned = LaserPointer.in_plane(0.030, np.radians(81.0)).cMl
    angle, offset = beam_line_error(a, turned, 0.0)
    assert angle == pytest.approx(1.0) and offset == pytest.approx(0.0, abs=1e-9)


# -- the network's data and the acceptance check ---------------------------------------


@pytest.mark.slow
def test_grid_dataset_and_acceptance(commissioning: dict) -> None:
    hand_eye = commissioning["hand_eye"]
    rng = np.random.default_rng(2)
    # The NN's views: one height and orientation, the arm moved over the board (planar inputs).
    offsets = [np.array([x, y, 0.0]) for x in (-0.01, 0.0, 0.01) for y in (-0.01, 0.0, 0.01)]
    boardMc = [transform(rot_x(np.pi), CENTRE_board + o + [0.0, 0.0, 0.25]) for o in offsets]
    views = [noisy_view(M, rng) for M in boardMc]
    bMe = [bMboard_TRUE @ M @ inverse(eMc_TRUE) for M in boardMc]
    dataset = grid_dataset(views, bMe, hand_eye.bMboard)
    assert dataset.validate().size == 9 * 40 and dataset.views == 9
    true_xy = np.concatenate([v.corners_board @ bMboard_TRUE[:3, :3].T + bMboard_TRUE[:3, 3] for v in views])[:, :2]
    assert np.max(np.linalg.norm(dataset.world_m - true_xy, axis=1)) < 0.5e-3
    network = train_nn(dataset, "planar")

    checks = []
    for _ in range(3):
        # Over the board within the views' range; the corner aimed at is the one below.
        boardMc = transform(rot_x(np.pi), CENTRE_board + np.append(rng.uniform(-0.008, 0.008, 2), 0.25))
        corner = BOARD.corners_board()[np.argmin(np.linalg.norm(BOARD.corners_board() - boardMc[:3, 3] * [1, 1, 0], axis=1))]
        pixel = project(TRUE_CAMERA, boardMc, corner[None, :])[0] + rng.normal(0.0, NOISE_PX, 2)
        checks.append(AcceptanceCheck(bMboard_TRUE @ boardMc @ inverse(eMc_TRUE), corner, pixel))
    geometric = acceptance_errors(hand_eye, hand_eye.bMboard, checks)
    assert geometric.max_mm < 0.3 and geometric.mean_mm <= geometric.max_mm
    learned = acceptance_errors(network, hand_eye.bMboard, checks)
    assert learned.max_mm < 1.0
    wrong_board = acceptance_errors(hand_eye, transform(np.eye(3), [0.002, 0.0, 0.0]) @ hand_eye.bMboard, checks)
    assert wrong_board.mean_mm == pytest.approx(2.0, abs=0.3)
    with pytest.raises(ValueError, match="at least one check"):
        acceptance_errors(hand_eye, hand_eye.bMboard, [])
