"""The virtual cell's fixture lays the checkerboard and puts parts at a given place.

`vservo virtual-cell --board` runs as a child process; the board is laid and taken away
over its fixture port and seen in the frames of its camera stream, as commissioning will
see it. The refusal while the cup holds the part is checked on a VirtualCell in this
process (its fixture on a real socket), where the test can put the cup on the part.
"""

import json

import cv2
import numpy as np
import pytest

from tests.sim.test_virtual_cell import fixture_request
from tests.virtual_cell_process import VirtualCellProcess
from vservo.core.cell.config import load_cell, read_cell_data, with_truth
from vservo.core.geometry.spatial import inverse, rot_x, transform
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.fixture import FixtureError
from vservo.core.production.rig import extractor_for
from vservo.core.sim.virtual_cell import ENDPOINTS, VirtualCell

SB_FLAGS = cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE


@pytest.fixture(scope="module")
def virtual_cell():
    cell = VirtualCellProcess("--seed", "5", "--board")
    yield cell
    assert cell.stop() == 0


@pytest.fixture
def table_clear(virtual_cell) -> str:
    """The fixture's URL, the board taken away (whatever a test before left)."""
    url = virtual_cell.addresses["fixture"]
    assert post(url + "/board", {"laid": False})[0] == 200
    return url


def post(url: str, body: dict | bytes) -> tuple[int, dict]:
    return fixture_request(url, "POST", body if isinstance(body, bytes) else json.dumps(body).encode())


def stream_frame(camera_url: str) -> np.ndarray:
    """A frame exposed after this call: a fresh connection, a few frames in."""
    capture = cv2.VideoCapture(camera_url)
    try:
        for _ in range(4):
            ok, image = capture.read()
            assert ok, "the camera stream gave no frame"
    finally:
        capture.release()
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def test_the_board_is_laid_at_start_seen_in_the_stream_and_taken_away_for_the_cube(virtual_cell):
    url, camera_url = virtual_cell.addresses["fixture"], virtual_cell.addresses["camera_url"]
    config = load_cell(virtual_cell.addresses["cell_file"])
    assert config.board is not None  # the controller's file keeps the nominal [board]
    assert fixture_request(url + "/board") == (200, {"board": {"laid": True}})
    found, _ = cv2.findChessboardCornersSB(stream_frame(camera_url), config.board.inner_corners, SB_FLAGS)
    assert found
    assert post(url + "/board", {"laid": False}) == (200, {"board": {"laid": False}})
    image = stream_frame(camera_url)
    assert not cv2.findChessboardCornersSB(image, config.board.inner_corners, SB_FLAGS)[0]
    features, _ = extractor_for(config).extract(image)
    assert np.isfinite(features.corners_px).all()  # the cube is back, all four corners seen
    assert post(url + "/board", {"laid": True}) == (200, {"board": {"laid": True}})
    assert cv2.findChessboardCornersSB(stream_frame(camera_url), config.board.inner_corners, SB_FLAGS)[0]
    status, body = post(url + "/part", {"seed": 3})
    assert status == 409 and "board is laid" in body["error"]
    assert post(url + "/board", {"laid": False})[0] == 200


def test_the_part_is_put_where_asked_and_get_part_reports_it(table_clear):
    url = table_clear
    status, body = post(url + "/part", {"x_mm": -470.0, "y_mm": 60.0, "yaw_deg": 15.0})
    assert status == 200
    assert fixture_request(url + "/part") == (200, body)
    assert body["part"] == {"x_mm": -470.0, "y_mm": 60.0, "z_mm": -155.0, "yaw_deg": 15.0}
    status, body = post(url + "/part", {"x_mm": -420, "y_mm": -30})  # yaw 0 when not given
    assert status == 200 and body["part"]["yaw_deg"] == 0.0


@pytest.mark.parametrize(
    "path, body, message",
    [
        ("/board", {"laid": "yes"}, '{"laid": true} or {"laid": false}'),
        ("/board", {}, '{"laid": true} or {"laid": false}'),
        ("/board", b"[1, 2]", "must be a JSON object"),
        ("/part", {"x_mm": "a", "y_mm": 0.0}, "x_mm = 'a' is not a finite number"),
        ("/part", {"x_mm": -450.0}, "keys ['x_mm']"),
        ("/part", {"seed": 1, "x_mm": -450.0, "y_mm": 0.0}, "keys ['seed', 'x_mm', 'y_mm']"),
        ("/part", {"x_mm": -400.0, "y_mm": 120.0}, "overlap the metal part"),
        ("/part", {"x_mm": 1200.0, "y_mm": 0.0}, "off the table"),
        ("/part", b"not json", "Expecting value"),
    ],
)
def test_bad_bodies_are_refused_with_a_message(table_clear, path, body, message):
    status, reply = post(table_clear + path, body)
    assert status == 400 and message in reply["error"], reply


def test_the_fixture_lists_its_endpoints(virtual_cell):
    status, body = fixture_request(virtual_cell.addresses["fixture"] + "/")
    assert status == 200 and body["endpoints"] == list(ENDPOINTS)
    assert {"POST /board", "GET /board", "POST /part"} <= set(ENDPOINTS)


def test_the_rig_lays_the_board_and_places_the_part_through_the_fixture(virtual_cell, table_clear):
    config = load_cell(virtual_cell.addresses["cell_file"])
    rig = build_rig(config)
    try:
        url = table_clear
        rig.place_part(-0.460, 0.040, np.radians(-10.0))
        assert fixture_request(url + "/part")[1]["part"] == {"x_mm": -460.0, "y_mm": 40.0, "z_mm": -155.0, "yaw_deg": -10.0}
        rig.lay_board(True)
        assert fixture_request(url + "/board")[1] == {"board": {"laid": True}}
        with pytest.raises(FixtureError, match=r"POST /part refused \(409\).*board is laid"):
            rig.place_part(-0.460, 0.040, 0.0)
        rig.lay_board(False)
        with pytest.raises(FixtureError, match=r"refused \(400\).*off the table"):
            rig.place_part(2.0, 0.0, 0.0)
    finally:
        rig.close()


def test_the_board_is_refused_while_the_cup_holds_the_part():
    tables, source = read_cell_data(None)
    with VirtualCell(with_truth(tables, None), source, seed=2) as virtual:
        cell = virtual.cell
        with virtual.emulator.lock:
            cube = cell.state.scene.cube
            bMv = cube.bMo @ transform(rot_x(np.pi), (cube.side_m / 2, cube.side_m / 2, 0.0))
            cell.set_joints(cell.truth.arm.ik(bMv @ inverse(cell.truth.model.eMv), cell.state.q).q)
            assert cell.vacuum(True)
        status, body = post(virtual.fixture.url + "/board", {"laid": True})
        assert status == 409 and "cup holds the part" in body["error"]
        assert fixture_request(virtual.fixture.url + "/board") == (200, {"board": {"laid": False}})


def test_a_cell_without_a_board_says_so():
    tables, source = read_cell_data(None)
    tables = with_truth(tables, None)
    del tables["board"]
    with VirtualCell(tables, source, seed=2) as virtual:
        status, body = post(virtual.fixture.url + "/board", {"laid": True})
        assert status == 409 and "no [board]" in body["error"]


def test_the_truth_file_says_where_the_board_truly_lies():
    tables, _ = read_cell_data(None)
    truth = {
        "simulation": {
            "truth": {"hand_eye": {"eMc": [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]}},
            "scene": {"board_pose": [-440.0, -20.0, -175.0, 4.0, 0.0, 0.0]},
        }
    }
    merged = with_truth(tables, truth)
    assert merged["simulation"]["scene"]["board_pose"] == [-440.0, -20.0, -175.0, 4.0, 0.0, 0.0]
    assert merged["simulation"]["scene"]["object_pose"] == tables["simulation"]["scene"]["object_pose"]
    assert "board_pose" not in tables["simulation"]["scene"]  # the cell's own tables are not changed
