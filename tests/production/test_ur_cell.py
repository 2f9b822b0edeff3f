"""A Universal Robots cell, end to end: `vservo virtual-cell --robot-link ur` in its own
process (the UR controller emulator on its RTDE, dashboard and script ports, the camera
stream, the fixture), and the product driving it through the cell file it writes, with
ur-rtde's own clients, exactly as it would drive a real arm.

The virtual cell runs at a fifth of real time (--time-scale 0.2; its camera keeps the
controller's clock): the machine's two cores are shared, and a servo at the camera's rate
needs its host to keep up with every frame. Every figure here is on the controller's clock,
read from its log (the fixture's GET /robot-log).
"""

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from tests.production.test_real_cell import SIMULATOR_MODULES, loaded_modules
from tests.sim.test_virtual_cell import fixture_request
from tests.virtual_cell_process import ROOT, VirtualCellProcess
from vservo.core.cell.config import load_cell
from vservo.core.geometry.spatial import pose_error
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.protocol.state import Outcome
from vservo.core.production.storage import Store
from vservo.core.robot.backend import RobotNotReady
from vservo.core.robot.ur import UrBackend

TIME_SCALE = "0.2"


@pytest.fixture(scope="module")
def ur_cell():
    cell = VirtualCellProcess("--seed", "3", "--robot-link", "ur", "--time-scale", TIME_SCALE)
    try:
        yield cell
    finally:
        assert cell.stop() == 0


def robot_log(cell: VirtualCellProcess) -> dict:
    status, body = fixture_request(cell.addresses["fixture"] + "/robot-log")
    assert status == 200, body
    return body


def twists(log: dict) -> list[float]:
    return [entry["time_s"] for entry in log["log"] if entry["kind"] == "program" and entry["what"] == "speedl"]


def test_the_ur_backend_moves_reads_back_and_refuses_to_move_while_held(ur_cell):
    config = load_cell(ur_cell.addresses["cell_file"])
    assert config.robot_backend == "ur" and config.vacuum_device.device == "ur_io" and config.motion.mode == "streaming"
    ur = UrBackend(config.ur)
    ur.connect()
    try:
        ur.servo(True)
        assert ur.status().ready
        bMe = ur.read_pose()
        target = bMe.copy()
        target[:3, 3] += [0.01, 0.0, 0.01]
        ur.move_to(target, 0.1)
        assert ur.wait_motion(timeout_s=20.0)
        translation, rotation = pose_error(ur.read_pose(), target)
        assert translation < 1e-5 and rotation < 1e-5
        ur.hold(True)
        status = ur.status()
        assert status.held and "host hold" in status.detail
        with pytest.raises(RobotNotReady, match="held"):
            ur.move_to(bMe, 0.1)
        ur.hold(False)
        ur.move_to(bMe, 0.1)
        assert ur.wait_motion(timeout_s=20.0)
    finally:
        ur.close()


@pytest.fixture
def controller(ur_cell, tmp_path):
    from vservo.core.production.cell_controller import CellController

    config = load_cell(ur_cell.addresses["cell_file"])
    store = Store.for_controller(tmp_path / "data", config.recordings)
    controller = CellController(build_rig(config), store, seed=7)
    try:
        yield controller
    finally:
        controller.close()
        store.close()


def start_and_wait_for_the_stream(controller, ur_cell, twists_seen: int = 5) -> int:
    """Start the demo on a new part; return once the servo has streamed ``twists_seen`` twists."""
    before = len(twists(robot_log(ur_cell)))
    controller.present_part()
    controller.start("demo")
    deadline = time.monotonic() + 120.0
    while len(twists(robot_log(ur_cell))) < before + twists_seen:
        assert controller.running and time.monotonic() < deadline, controller.state.detail
        time.sleep(0.05)
    return before


def test_an_estop_during_the_streamed_servo_stops_the_arm_within_one_control_period(ur_cell, controller):
    start_and_wait_for_the_stream(controller, ur_cell)
    controller.estop("the test's e-stop")
    controller.wait(30.0)
    assert controller.last_outcome.outcome is Outcome.ESTOPPED
    time.sleep(0.5)
    log = robot_log(ur_cell)
    stops = [entry for entry in log["log"] if entry["kind"] == "stop"]
    assert stops and stops[-1]["time_s"] > twists(log)[-1]  # the dashboard's stop came after the last twist
    assert log["last_moved_s"] - stops[-1]["time_s"] <= log["period_s"]
    controller.reset()


def test_a_stalled_camera_stops_the_arm_within_the_watchdog(ur_cell, controller):
    url = ur_cell.addresses["fixture"]
    start_and_wait_for_the_stream(controller, ur_cell)
    assert fixture_request(url + "/camera", "POST", b'{"stalled": true}')[0] == 200
    try:
        config = load_cell(ur_cell.addresses["cell_file"])
        stalled_at = robot_log(ur_cell)["time_s"]
        log = robot_log(ur_cell)
        while log["last_moved_s"] >= log["time_s"] - log["period_s"]:  # until the arm stands
            assert log["time_s"] < stalled_at + config.safety.watchdog_s, "the arm still moves a watchdog after the stall"
            time.sleep(0.1)
            log = robot_log(ur_cell)
        last_twist = twists(log)[-1]
        # the controller stops the arm itself once the last twist's hold (stream_hold_s) has run
        # out: that, its deceleration from the streamed speed limit, and the period it lands in
        motion = config.motion
        stopping_s = motion.stream_hold_s + motion.stream_max_speed_m_s / config.ur.acceleration_m_s2 + 2 * log["period_s"]
        assert log["last_moved_s"] - last_twist <= stopping_s <= config.safety.watchdog_s
        stood_s = log["last_moved_s"] - last_twist
        print(f"the arm stood {stood_s:.3f} s after the last twist, {log['last_moved_s'] - stalled_at:.3f} s after the stall")
        controller.wait(60.0)
        assert controller.last_outcome.outcome is Outcome.FAULT
    finally:
        fixture_request(url + "/camera", "POST", b'{"stalled": false}')
    controller.reset()


@pytest.fixture
def fresh_ur_cell():
    # A tenth of real time: ten runs in a row on cores other test suites load too (a load
    # average of 20 to 30 on our two) must follow every frame of each.
    cell = VirtualCellProcess("--seed", "3", "--robot-link", "ur", "--time-scale", "0.1")
    try:
        yield cell
    finally:
        assert cell.stop() == 0


@pytest.mark.slow
def test_the_demo_is_placed_ten_of_ten_streaming_at_the_cameras_rate_and_loads_no_simulator_module(fresh_ur_cell, tmp_path):
    """The issue's acceptance on the UR: ten seeds placed within 0.3 mm by the virtual cell's
    gauge, each run within 6 s of the controller's clock, its servo streaming at least 25
    twists a second of it, and the run process importing no module of the simulator."""
    ur_cell, figures = fresh_ur_cell, []
    for seed in range(10):
        before = len(twists(robot_log(ur_cell)))
        run = subprocess.run(
            [sys.executable, "-X", "importtime", "-m", "vservo.app.cli", "run", "--job", "demo"]
            + ["--cell", ur_cell.addresses["cell_file"], "--json", "--data", str(tmp_path / "data"), "--seed", str(seed)],
            capture_output=True,
            text=True,
            timeout=600,
            cwd=ROOT,
        )
        assert run.returncode == 0, run.stdout + run.stderr[-3000:]
        summary = json.loads(run.stdout)
        released = ur_cell.next_event()
        streamed = twists(robot_log(ur_cell))[before:]
        rate = (len(streamed) - 1) / (streamed[-1] - streamed[0])
        figures.append(
            (seed, released["placement_error_mm"], summary["cell_time_s"], rate, summary["cell_time_by_phase_s"]["servo"])
        )
        print(seed, summary["cell_time_by_phase_s"], summary["stages"], f"{rate:.1f} twists/s", flush=True)
        assert summary["outcome"] == "placed" and released["inside"], (summary, released)
        assert released["placement_error_mm"] <= 0.3, released
        assert summary["cell_time_s"] <= 6.0, figures
        assert rate >= 25.0, figures
        assert not loaded_modules(run.stderr) & SIMULATOR_MODULES
    print("seed, gauge mm, cell time s, twists per s, servo s:", np.round(figures, 3).tolist())
