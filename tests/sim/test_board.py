"""The calibration checkerboard in the simulator: where it truly lies ([simulation.scene]
board_pose), laying it on a cleared table and taking it away, and how it is drawn.

The drawing is checked as commissioning will read it: OpenCV's findChessboardCornersSB
must find the pattern in frames of the TRUE camera (with lens distortion) from the heights
and tilts a calibration uses, and its corners must agree with the exact projection of the
true corners (CameraModel.project), which does not go through the renderer.
"""

from __future__ import annotations

import copy

import cv2
import numpy as np
import pytest

from vservo.core.cell.config import ConfigError, parse_cell, read_cell_data
from vservo.core.geometry.spatial import inverse, rot_x, rot_y, rot_z, transform
from vservo.core.sim.part_feeder import place_part, present_part
from vservo.core.sim.plant import CellStateError, SimulatedCell
from vservo.core.sim.render import SceneRenderer
from vservo.core.sim.render_settings import RenderSettings

SB_FLAGS = cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE
DISTORTION = [-0.2, 0.1, 0.001, -0.001, 0.0]


def shipped_tables() -> dict:
    return copy.deepcopy(read_cell_data(None)[0])


def cell_from(tables: dict) -> SimulatedCell:
    return SimulatedCell(parse_cell(tables, "test"))


def truth_with_distortion() -> dict:
    tables = shipped_tables()
    tables["simulation"]["truth"] = {"camera": {"distortion": DISTORTION, "principal_point_px": [331.0, 236.0]}}
    return tables


# -- where the board lies ---------------------------------------------------------------


def test_the_true_board_lies_where_the_board_table_says_unless_board_pose_says_otherwise():
    tables = shipped_tables()
    config = parse_cell(tables, "test")
    assert np.allclose(config.simulation.board.bMboard, config.board.bMboard)
    tables["simulation"]["scene"]["board_pose"] = [-440.0, -25.0, -175.0, 3.0, 0.0, 0.0]
    board = parse_cell(tables, "test").simulation.board
    assert np.allclose(board.bMboard[:3, 3], [-0.440, -0.025, -0.175])
    assert np.isclose(np.degrees(np.arctan2(board.bMboard[1, 0], board.bMboard[0, 0])), 3.0)
    assert board.square_m == 0.010 and board.inner_corners == (8, 5)
    # The inner corner (0, 0) is the board frame's origin, corner (1, 0) one square along its x.
    assert np.allclose(board.corners_b[0], board.bMboard[:3, 3])
    assert np.allclose(board.corners_b[1] - board.corners_b[0], 0.010 * board.bMboard[:3, 0])


def test_board_pose_without_a_board_table_is_refused_naming_the_key():
    tables = shipped_tables()
    del tables["board"]
    assert parse_cell(tables, "test").simulation.board is None
    tables["simulation"]["scene"]["board_pose"] = [-440.0, -25.0, -175.0, 0.0, 0.0, 0.0]
    with pytest.raises(ConfigError, match=r"simulation\.scene\.board_pose.*needs a \[board\] table"):
        parse_cell(tables, "test")


@pytest.mark.parametrize("pose", [[-440.0, -25.0, -170.0, 0.0, 0.0, 0.0], [-440.0, -25.0, -175.0, 0.0, 2.0, 0.0]])
def test_a_board_off_the_table_or_tilted_is_refused(pose):
    tables = shipped_tables()
    tables["simulation"]["scene"]["board_pose"] = pose
    with pytest.raises(ConfigError, match=r"simulation\.scene\.board_pose.*sheet lying on the table"):
        parse_cell(tables, "test")


# -- laying it ------------------------------------------------------------------------


def test_laying_the_board_clears_the_table_and_taking_it_away_puts_the_parts_back():
    cell = cell_from(shipped_tables())
    before = cell.state.scene
    assert cell.measure().corners_visible.all()
    cell.lay_board(True)
    scene = cell.state.scene
    assert cell.board_laid and not scene.parts_on_table
    assert [box.name for box in scene.boxes] == ["table"]
    seen = cell.measure()
    assert np.isnan(seen.corners_px).all() and np.isnan(seen.reference_px).all() and not seen.region.seen
    # The beam lands on the sheet, which is the table's surface.
    bMc, spot_b = cell.ground_truth_view()
    assert spot_b is not None and np.isclose(spot_b[2], scene.table_height_m)
    with pytest.raises(CellStateError, match="board is laid"):
        present_part(cell, before.cube.bMo, np.random.default_rng(0))
    cell.lay_board(False)
    assert cell.state.scene.parts_on_table
    assert np.array_equal(cell.state.scene.cube.bMo, before.cube.bMo)
    assert np.array_equal(cell.state.scene.metal_part.bMp, before.metal_part.bMp)
    assert cell.measure().corners_visible.all()


def hold_the_part(cell: SimulatedCell) -> None:
    """Put the true cup on the cube's top face (the truth's own IK) and switch the vacuum on."""
    cube = cell.state.scene.cube
    bMv = cube.bMo @ transform(rot_x(np.pi), (cube.side_m / 2, cube.side_m / 2, 0.0))
    bMe = bMv @ inverse(cell.truth.model.eMv)
    cell.set_joints(cell.truth.arm.ik(bMe, cell.state.q).q)
    assert cell.vacuum(True)


def test_the_board_is_not_laid_while_the_cup_holds_the_part_nor_on_a_cell_without_one():
    cell = cell_from(shipped_tables())
    hold_the_part(cell)
    with pytest.raises(CellStateError, match="cup holds the part"):
        cell.lay_board(True)
    assert cell.state.scene.parts_on_table
    tables = shipped_tables()
    del tables["board"]
    with pytest.raises(ConfigError, match=r"no \[board\]"):
        cell_from(tables).lay_board(True)


def test_nothing_is_gripped_while_the_board_is_laid():
    cell = cell_from(shipped_tables())
    hold_the_part(cell)
    cell.vacuum(False)
    cell.lay_board(True)
    assert not cell.vacuum(True)


# -- placing the part -----------------------------------------------------------------


def test_the_part_is_put_where_asked_and_refused_off_the_table_or_on_the_metal_part():
    cell = cell_from(shipped_tables())
    bMo = place_part(cell, -0.480, 0.050, np.radians(30.0))
    scene = cell.state.scene
    assert np.array_equal(scene.cube.bMo, bMo)
    assert np.allclose(bMo[:3, 3], [-0.480, 0.050, scene.table_height_m + scene.cube.side_m])
    assert np.isclose(np.degrees(np.arctan2(bMo[1, 0], bMo[0, 0])), 30.0)
    part = scene.metal_part.bMp[:3, 3]
    with pytest.raises(ValueError, match="overlap the metal part"):
        place_part(cell, part[0] + 0.020, part[1], 0.0)  # its corner O on a wall (the part spans +-26 mm)
    place_part(cell, part[0] + 0.027, part[1], 0.0)  # just clear of it
    with pytest.raises(ValueError, match="off the table"):
        place_part(cell, 0.995, 0.0, 0.0)
    with pytest.raises(ValueError, match="x must be a finite number"):
        place_part(cell, float("nan"), 0.0, 0.0)
    assert np.allclose(cell.state.scene.cube.bMo[:2, 3], part[:2] + [0.027, 0.0])


# -- drawing it -----------------------------------------------------------------------


def views_of(centre_b: np.ndarray):
    """Camera poses looking at ``centre_b`` from 150 to 400 mm, tilted up to 30 deg, from all sides."""
    for height in (0.15, 0.25, 0.40):
        for tilt_deg in (0.0, 15.0, 30.0):
            for azimuth_deg in (0.0, 100.0, 220.0):
                R = rot_z(np.radians(azimuth_deg)) @ rot_x(np.pi) @ rot_y(np.radians(tilt_deg))
                yield (height, tilt_deg, azimuth_deg), transform(R, centre_b - height * R[:, 2])


def test_opencv_finds_the_rendered_board_where_the_true_corners_project():
    cell = cell_from(truth_with_distortion())
    cell.lay_board(True)
    board, camera = cell.board, cell.truth.model.camera
    assert not camera.distortion.is_zero
    renderer = SceneRenderer(camera, RenderSettings())
    rng = np.random.default_rng(4)
    centre_b = board.bMboard[:3, :3] @ np.array([0.035, 0.020, 0.0]) + board.bMboard[:3, 3]
    medians = []
    for view, bMc in views_of(centre_b):
        image = renderer.render(cell.state.scene, bMc, None, rng)
        found, corners = cv2.findChessboardCornersSB(image, board.inner_corners, SB_FLAGS)
        assert found, f"no board found in the view {view} (height m, tilt deg, azimuth deg)"
        true_px = renderer.project_b(bMc, board.corners_b)
        # OpenCV orders the corners from whichever end it starts: match each to the nearest
        # true corner (a square is 25 px or more, the errors hundredths of a pixel).
        distance = np.linalg.norm(corners.reshape(-1, 1, 2) - true_px[None], axis=2)
        assert len(set(distance.argmin(axis=1))) == len(true_px)
        errors = distance.min(axis=1)
        assert np.median(errors) < 0.1 and errors.max() < 0.5, (view, np.median(errors), errors.max())
        medians.append(np.median(errors))
    assert np.median(medians) < 0.06


def test_the_square_at_the_origin_is_black_and_its_neighbours_white():
    cell = cell_from(shipped_tables())
    cell.lay_board(True)
    board = cell.board
    renderer = SceneRenderer(cell.truth.model.camera)
    bMc = transform(rot_x(np.pi), board.bMboard[:3, 3] + [0.0, 0.0, 0.25])
    image = renderer.render(cell.state.scene, bMc, None, np.random.default_rng(0))
    s = board.square_m

    def grey_at(x: float, y: float) -> int:
        u, v = np.round(renderer.project_b(bMc, board.bMboard[:3, :3] @ [x, y, 0.0] + board.bMboard[:3, 3])[0])
        return int(image[int(v), int(u)])

    settings = RenderSettings()
    assert grey_at(s / 2, s / 2) == round(settings.board_black_grey)
    assert grey_at(-s / 2, -s / 2) == round(settings.board_black_grey)
    assert grey_at(3 * s / 2, s / 2) == round(settings.board_white_grey)
    assert grey_at(s / 2, 3 * s / 2) == round(settings.board_white_grey)
    assert grey_at(-1.5 * s, s / 2) == round(settings.board_white_grey)  # the sheet's margin
    assert grey_at(-2.5 * s, s / 2) == round(settings.table_grey)  # beyond the sheet
