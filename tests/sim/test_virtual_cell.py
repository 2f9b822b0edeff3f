"""The virtual cell: `vservo virtual-cell` runs the simulated cell as its own process, and
the product drives it through the cell file it writes, exactly as it drives a real cell.

Everything here crosses process boundaries as on a real cell: the JRC emulator answers on
a pseudo-terminal (or, with --robot-link ethernet, as a later controller's Ethernet server
on a TCP port: every test runs on both), the camera is an MJPEG stream OpenCV opens by URL,
and the fixture is an HTTP port. The test reads the virtual cell's released lines (its gauge) to check what the
controller process, which has no gauge, reports by vision.
"""

import json
import os
import socket
import subprocess
import sys
import tomllib
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.production.test_real_cell import SIMULATOR_MODULES, loaded_modules
from tests.virtual_cell_process import ROOT, VirtualCellProcess
from vservo.core.cell.cell_file import dumps_cell
from vservo.core.cell.config import SERIAL_ONLY_KEYS, ConfigError, HostTransport, load_cell, read_cell_data, with_truth
from vservo.core.robot.jrc import JrcBackend


def fixture_request(url: str, method: str = "GET", body: bytes | None = None) -> tuple[int, dict]:
    request = urllib.request.Request(url, data=body, method=method)
    try:
        with urllib.request.urlopen(request, timeout=5) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


@pytest.fixture(scope="module", params=list(HostTransport))
def virtual_cell(request):
    cell = VirtualCellProcess("--seed", "3", "--robot-link", request.param)
    cell.robot_link = request.param
    yield cell
    assert cell.stop() == 0


def test_it_prints_its_devices_and_writes_a_real_cell_file_with_no_truth_in_it(virtual_cell):
    addresses = virtual_cell.addresses
    assert set(addresses) == {"cell_file", "jrc_port", "camera_url", "fixture"}
    config = load_cell(addresses["cell_file"])
    assert config.real and config.robot_backend == "jrc" and config.jrc.address == addresses["jrc_port"]
    assert config.jrc.transport is virtual_cell.robot_link
    assert config.camera_source.kind == "capture" and config.camera_source.device == addresses["camera_url"]
    assert config.vacuum_device.device == "jrc_io" and config.fixture_url == addresses["fixture"]
    assert config.simulation is None  # the plant's layout and truth stay in the virtual cell
    tables = tomllib.loads(Path(addresses["cell_file"]).read_text())
    assert "simulation" not in tables
    if config.jrc.transport is HostTransport.ETHERNET:
        assert not set(tables["jrc"]) & set(SERIAL_ONLY_KEYS)  # no serial line's keys on a TCP link
        socket.create_connection((config.jrc.host, config.jrc.tcp_port), timeout=5).close()
    else:
        assert os.path.exists(addresses["jrc_port"])


def test_its_camera_is_a_stream_opencv_opens_by_url(virtual_cell):
    capture = cv2.VideoCapture(virtual_cell.addresses["camera_url"])
    try:
        assert capture.isOpened()
        ok, image = capture.read()
    finally:
        capture.release()
    assert ok and image.shape[:2] == (480, 640)


def test_its_fixture_presents_a_part_where_the_seed_says_and_refuses_nonsense(virtual_cell):
    url = virtual_cell.addresses["fixture"]
    status, first = fixture_request(url + "/part", "POST", b'{"seed": 11}')
    assert status == 200
    assert fixture_request(url + "/part")[1] == first
    fixture_request(url + "/part", "POST", b'{"seed": 12}')
    assert fixture_request(url + "/part", "POST", b'{"seed": 11}')[1] == first  # the same seed, the same place
    assert fixture_request(url + "/part", "POST", b'{"seed": "x"}')[0] == 400
    assert fixture_request(url + "/part", "POST", b"not json")[0] == 400
    status, body = fixture_request(url + "/nothing")
    assert status == 404 and "GET /nothing" in body["error"]


def test_a_run_on_the_virtual_cell_places_the_part_by_vision_and_loads_no_simulator_module(virtual_cell, tmp_path):
    """The issue's acceptance: the part is placed, the virtual cell's gauge says inside within
    0.3 mm, the run's own (vision) figure agrees with the gauge within 0.1 mm, and the run
    process imported no module of the simulator."""
    run = subprocess.run(
        [
            sys.executable,
            "-X",
            "importtime",
            "-m",
            "vservo.app.cli",
            "run",
            "--job",
            "demo",
            "--cell",
            virtual_cell.addresses["cell_file"],
            "--json",
            "--data",
            str(tmp_path / "data"),
            "--seed",
            "5",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    summary = json.loads(run.stdout)
    released = virtual_cell.next_event()
    assert summary["outcome"] == "placed", summary
    assert released["event"] == "released" and released["inside"], released
    assert released["placement_error_mm"] <= 0.3, released
    assert abs(summary["placement_error_mm"] - released["placement_error_mm"]) <= 0.1, (summary, released)
    assert not loaded_modules(run.stderr) & SIMULATOR_MODULES


def test_the_controllers_cell_file_round_trips_through_toml():
    tables, _ = read_cell_data()
    assert tomllib.loads(dumps_cell(tables, "a header")) == tables
    with pytest.raises(ValueError, match="motion.speed_mm_s"):
        dumps_cell({"motion": {"speed_mm_s": float("nan")}})


def test_a_truth_file_without_truth_is_refused(tmp_path):
    tables, _ = read_cell_data()
    with pytest.raises(ConfigError, match="no \\[simulation.truth"):
        with_truth(tables, {"robot": {}})
    truth = {"simulation": {"truth": {"hand_eye": {"eMc": [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]}}}}
    assert with_truth(tables, truth)["simulation"]["truth"] == truth["simulation"]["truth"]
    assert "truth" not in tables["simulation"]  # the cell's own tables are not changed


# A serial port is opened exclusively; over TCP a second session waits for the server instead.
@pytest.mark.parametrize("virtual_cell", [HostTransport.SERIAL], indirect=True)
def test_a_second_program_on_the_robots_port_is_refused_naming_the_holder_and_moves_nothing(virtual_cell, tmp_path):
    """While this test holds the virtual cell's JRC port (as a running controller does),
    `vservo run` on the same cell file is refused at once in one line naming the port and
    this process; the arm has not moved."""
    config = load_cell(virtual_cell.addresses["cell_file"])
    holder = JrcBackend(config.jrc)
    holder.connect()
    try:
        before = holder.read_pose()
        run = subprocess.run(
            [sys.executable, "-m", "vservo.app.cli", "run", "--job", "demo", "--cell", virtual_cell.addresses["cell_file"]]
            + ["--data", str(tmp_path / "data")],
            capture_output=True,
            text=True,
            timeout=120,
            cwd=ROOT,
        )
        assert run.returncode == 2, run.stdout + run.stderr
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1, run.stderr
        assert config.jrc.port in lines[0] and f"process {os.getpid()} " in lines[0], lines[0]
        assert np.array_equal(holder.read_pose(), before)
    finally:
        holder.close()


@pytest.mark.parametrize(
    "args, words",
    [
        (["--robot-link", "ethernet", "--jrc-link", "/tmp/jrc"], "--jrc-link names a pseudo-terminal"),
        (["--jrc-tcp-port", "10080"], "--jrc-tcp-port is the Ethernet server's port"),
    ],
)
def test_a_link_option_for_the_other_link_is_refused(args, words):
    run = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "virtual-cell", *args], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert run.returncode == 2 and words in run.stderr, run.stderr
