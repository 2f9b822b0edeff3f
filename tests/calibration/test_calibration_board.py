"""The checkerboard: rendered through the true camera, found by OpenCV, named by the board.

Every check compares with the exact projection of the board's lattice by the true
camera from its true pose (CameraModel.project), which the detector never sees.
"""

import numpy as np
import pytest

from vservo.core.calibration.checkerboard import BoardNotFound, Checkerboard, detect_board, find_corners
from vservo.core.geometry.camera import CameraModel, Distortion, sony_xc55
from vservo.core.geometry.spatial import exp_twist, rot_x, transform

BOARD = Checkerboard.covering((-0.6, -0.3), (-0.15, 0.15), table_height_m=-0.175)
LENS = CameraModel(sony_xc55().intrinsics, Distortion(-0.16, 0.11, 6e-4, -4e-4, -0.02))


def tool_down(x, y, height=0.3, tilt=(0.0, 0.0, 0.0)):
    bMc = transform(rot_x(np.pi), (x, y, BOARD.table_height_m + height))
    return bMc @ exp_twist(np.concatenate((np.zeros(3), tilt)))


def named(camera, bMc_true, bMc_model, model_camera):
    image = BOARD.render(camera, bMc_true)
    return detect_board(BOARD, image, lambda px: BOARD.back_project(model_camera, bMc_model, px) / BOARD.square_m)


@pytest.mark.parametrize("camera", [sony_xc55(), LENS], ids=["pinhole", "distorted"])
def test_corners_are_found_to_a_few_hundredths_of_a_pixel_and_named_by_the_board(camera):
    bMc = tool_down(-0.4513, 0.0127, tilt=(0.004, -0.003, 0.02))
    view = named(camera, bMc, bMc, camera)
    assert len(view.corners_px) > 300
    error = np.linalg.norm(BOARD.predict_px(camera, bMc, view.lattice_ij) - view.corners_px, axis=1)
    assert np.mean(error) < 0.05 and np.percentile(error, 95) < 0.1 and np.max(error) < 0.5
    assert np.allclose(view.corners_w, view.lattice_ij * 0.010)


def test_a_model_a_few_millimetres_off_still_names_every_corner_right():
    bMc = tool_down(-0.4487, -0.0213, tilt=(0.006, 0.005, 0.0))
    # The nominal model: a pinhole without distortion, 4 mm and 0.3 deg away from the truth.
    bMc_model = bMc @ exp_twist([0.003, -0.0025, 0.001, 0.0, 0.0, 0.005])
    view = named(LENS, bMc, bMc_model, sony_xc55())
    error = np.linalg.norm(BOARD.predict_px(LENS, bMc, view.lattice_ij) - view.corners_px, axis=1)
    assert np.max(error) < 0.3  # a misnamed corner would be a whole square (27 px) off


def test_a_model_a_square_off_gets_the_view_refused_not_misnamed():
    bMc = tool_down(-0.45, 0.0)
    with pytest.raises(BoardNotFound, match="too far off"):
        named(sony_xc55(), bMc, bMc @ exp_twist([0.009, 0.0, 0.0, 0.0, 0.0, 0.0]), sony_xc55())


def test_an_image_without_a_board_is_refused():
    with pytest.raises(BoardNotFound, match="no checkerboard"):
        find_corners(np.full((480, 640), 128, dtype=np.uint8))


def test_back_projection_inverts_the_projection():
    bMc = tool_down(-0.45, 0.02, tilt=(0.05, -0.04, 0.3))
    ij = np.array([[-45, 0], [-44, 3], [-47, -2]], dtype=float)
    pixels = BOARD.predict_px(LENS, bMc, ij)
    assert np.allclose(BOARD.back_project(LENS, bMc, pixels), ij * 0.010, atol=1e-9)
