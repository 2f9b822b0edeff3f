"""A Universal Robots cell, end to end: `vservo virtual-cell --robot-link ur` in its own
process (the UR controller emulator on its RTDE, dashboard and script ports, the camera
stream, the fixture), and the product driving it through the cell file it writes, with
ur-rtde's own clients, exactly as it would drive a real arm.

The virtual cell runs slower than real time (--time-scale 0.2 here, the same for the ten-part
acceptance; its camera keeps the controller's clock): the machine's two cores are shared,
and a servo at the camera's rate needs its host to keep up with every frame. Every figure
here is on the controller's clock, read from its log (the fixture's GET /robot-log).
"""

import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.production.test_real_cell import SIMULATOR_MODULES, loaded_modules
from tests.sim.test_virtual_cell import fixture_request
from tests.virtual_cell_process import ROOT, VirtualCellProcess
from vservo.core.cell.config import load_cell
from vservo.core.geometry.spatial import pose_error, rot_z, transform
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.protocol import KEY_ENVIRONMENT, new_key
from vservo.core.production.protocol.client import ControllerClient
from vservo.core.production.protocol.commands import Start
from vservo.core.production.protocol.state import Outcome, RunOutcome
from vservo.core.production.storage import Store
from vservo.core.robot import ur_script
from vservo.core.robot.backend import RobotNotReady
from vservo.core.robot.safety import BeyondJointLimits, JointsDisagree, SafetyLayer
from vservo.core.robot.ur import UrBackend
from vservo.robot_models.loader import controller_base

TIME_SCALE = "0.2"
SPEED_M_S = 0.25


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
    ur = UrBackend(config.ur, controller_base(config.arm))
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


def programs(log: dict, since_s: float) -> list[str]:
    return [entry["what"] for entry in log["log"] if entry["kind"] == "program" and entry["time_s"] >= since_s]


def test_the_safety_layer_sends_a_checked_joint_path_to_the_ur_as_one_movej_within_the_speed(ur_cell):
    """move_joint checks the whole joint-space line, then sends the UR its end joints once
    (one movej program, none of the stepped movel's); the flange's speed on the way, read by
    ur-rtde's own client, stays within the move's. A refused move sends nothing."""
    import rtde_receive

    config = load_cell(ur_cell.addresses["cell_file"])
    robot = SafetyLayer.from_config(UrBackend(config.ur, controller_base(config.arm)), config)
    robot.connect()
    rtde = rtde_receive.RTDEReceiveInterface(config.ur.host, -1.0, ["timestamp", "actual_TCP_speed"])
    speeds: list[float] = []
    moving = threading.Event()

    def sample() -> None:
        while moving.is_set():
            speeds.append(float(np.linalg.norm(rtde.getActualTCPSpeed()[:3])))
            time.sleep(0.002)

    try:
        robot.servo(True)
        home = robot.read_pose()
        target = transform(t=(0.08, -0.10, 0.03)) @ home @ transform(rot_z(np.radians(30.0)))
        assert len(robot.joint_path(home, target, SPEED_M_S)) > 1  # the JRC would take it in steps
        since_s = robot_log(ur_cell)["time_s"]
        moving.set()
        sampler = threading.Thread(target=sample)
        sampler.start()
        try:
            robot.move_joint(target, SPEED_M_S)
        finally:
            moving.clear()
            sampler.join()
        assert programs(robot_log(ur_cell), since_s) == ["movej"]
        translation, rotation = pose_error(robot.read_pose(), target)
        assert translation < 1e-5 and rotation < 1e-5
        assert 0.5 * SPEED_M_S < max(speeds) <= 1.01 * SPEED_M_S
        since_s = robot_log(ur_cell)["time_s"]
        with pytest.raises(BeyondJointLimits, match="no joints within the limits reach the path's ends"):
            robot.move_joint(transform(t=(-0.60, 0.0, 0.05)) @ np.diag([1.0, -1.0, -1.0, 1.0]), SPEED_M_S)  # beyond the reach
        assert programs(robot_log(ur_cell), since_s) == []
        assert pose_error(robot.read_pose(), target)[0] < 1e-5
        robot.move_joint(home, SPEED_M_S)
        assert pose_error(robot.read_pose(), home)[0] < 1e-5
    finally:
        rtde.disconnect()
        robot.close()


def test_on_a_ur5_the_backend_speaks_the_urdfs_frame_and_the_controller_its_own_base():
    """A real UR5 reports its TCP in its Base, a half turn about z from example-robot-data's
    root base_link, vservo's base frame: RTDE's pose (read here with ur-rtde's own client)
    has x and y of the opposite sign of the backend's, and a move along +x of vservo's
    base frame moves RTDE's x the other way. A cell file naming the wrong arm is caught by
    the first joint move."""
    import rtde_receive

    cell = VirtualCellProcess("--seed", "3", "--robot-link", "ur", "--time-scale", TIME_SCALE, "--cell", "static/cell-ur5.toml")
    try:
        config = load_cell(cell.addresses["cell_file"])
        assert config.arm == "ur5"
        ur = UrBackend(config.ur, controller_base(config.arm))
        ur.connect()
        rtde = rtde_receive.RTDEReceiveInterface(config.ur.host, -1.0, ["timestamp", "actual_TCP_pose"])
        try:
            ur.servo(True)
            half_turn = np.diag([-1.0, -1.0, 1.0])

            def agree() -> None:
                bMe, uMe = ur.read_pose(), ur_script.pose_from_ur(rtde.getActualTCPPose())
                assert np.allclose(uMe[:3, 3], half_turn @ bMe[:3, 3], atol=1e-6)
                assert np.allclose(uMe[:3, :3], half_turn @ bMe[:3, :3], atol=1e-6)

            agree()
            x_before = rtde.getActualTCPPose()[0]
            target = ur.read_pose()
            target[:3, 3] += [0.01, 0.0, 0.0]
            ur.move_to(target, 0.1)
            assert ur.wait_motion(timeout_s=20.0)
            assert pose_error(ur.read_pose(), target)[0] < 1e-5
            assert rtde.getActualTCPPose()[0] == pytest.approx(x_before - 0.01, abs=1e-5)
            agree()
        finally:
            rtde.disconnect()
            ur.close()
        # The cell file naming the wrong arm (a UR10 where a UR5 stands): the model's joints for
        # the pose RTDE reports are not the controller's, so a joint move is refused unsent.
        wrong = replace(config, arm="ur10", home_q=load_cell(ROOT / "static" / "cell-ur10.toml").home_q)
        robot = SafetyLayer.from_config(UrBackend(config.ur, controller_base(wrong.arm)), wrong)
        robot.connect()
        try:
            since_s = robot_log(cell)["time_s"]
            with pytest.raises(JointsDisagree, match=r"the controller reports joint \w+ at .* from the arm model's"):
                robot.move_joint(transform(t=(0.03, -0.02, 0.02)) @ robot.read_pose(), 0.1)
            assert programs(robot_log(cell), since_s) == []
        finally:
            robot.close()
    finally:
        assert cell.stop() == 0


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


# The acceptance's pace: a quarter of real time. The demo's cell time is 4 to 6 s, so its ten
# runs take about 3 minutes; the servo must still follow every frame of the camera's 30 a
# second of the controller's clock (7.5 a second of the host's) while the suite's other
# worker loads the machine's two cores (at 0.5 of real time and a load average of 5 to 11 a
# run now and then fell to 20 to 24.7 twists a second; at 0.4, beside the other worker, one
# run of ten to 17.4).
ACCEPTANCE_TIME_SCALE = "0.2"
RUN_TIMEOUT_S = 120.0


class ControllerProcess:
    """`vservo controller` on the cell file, under ``python -X importtime`` (its standard error,
    the import log and its own log, in a file), and the channel to it."""

    def __init__(self, cell_file: str, data: Path) -> None:
        self.key = new_key()
        self.stderr = tempfile.TemporaryFile("w+")
        self.process = subprocess.Popen(
            [sys.executable, "-X", "importtime", "-m", "vservo.app.cli", "--cell", cell_file, "controller"]
            + ["--data", str(data), "--seed", "0", "--cycle-period", "0"],
            stdout=subprocess.PIPE,
            stderr=self.stderr,
            text=True,
            cwd=ROOT,
            env={**os.environ, KEY_ENVIRONMENT: self.key.hex()},
        )
        line = self.process.stdout.readline()
        if not line:
            raise AssertionError(f"the controller did not start: {self.log()[-3000:]}")
        address = json.loads(line)["controller"]
        self.channel = ControllerClient((address["host"], address["port"]), self.key)

    def log(self) -> str:
        self.stderr.seek(0)
        return self.stderr.read()

    def assemble(self, job_name: str) -> RunOutcome:
        """Start ``job_name`` on the part on the table; how the run ended."""
        reply = self.channel.call(Start(job_name))
        assert reply.ok, reply.error
        deadline = time.monotonic() + RUN_TIMEOUT_S
        while (state := self.channel.state).run.run_id != reply.result or state.last_outcome is None:
            assert time.monotonic() < deadline, f"run {reply.result} has not ended: {state.phase} {state.detail}"
            time.sleep(0.05)
        return state.last_outcome

    def stop(self) -> int:
        self.channel.close()
        self.process.terminate()
        try:
            return self.process.wait(timeout=30)
        finally:
            self.process.stdout.close()
            self.stderr.close()


@pytest.fixture
def acceptance_cell(tmp_path):
    """A virtual UR cell at the acceptance's pace, and one controller process on its cell file."""
    cell = VirtualCellProcess("--seed", "3", "--robot-link", "ur", "--time-scale", ACCEPTANCE_TIME_SCALE)
    controller = None
    try:
        controller = ControllerProcess(cell.addresses["cell_file"], tmp_path / "data")
        yield cell, controller
    finally:
        if controller is not None:
            assert controller.stop() == 0
        assert cell.stop() == 0


@pytest.mark.slow
def test_the_demo_is_placed_ten_of_ten_streaming_at_the_cameras_rate_and_loads_no_simulator_module(acceptance_cell):
    """The issue's acceptance on the UR: ten parts (the fixture's seeds 0 to 9) placed within
    0.3 mm by the virtual cell's gauge, each run within 6 s of the controller's clock, its
    servo streaming at least 25 twists a second of it, and the controller process importing
    no module of the simulator. One controller process runs the ten, as on a line."""
    ur_cell, controller = acceptance_cell
    figures = []
    for seed in range(10):
        status, body = fixture_request(ur_cell.addresses["fixture"] + "/part", "POST", json.dumps({"seed": seed}).encode())
        assert status == 200, body
        before = len(twists(robot_log(ur_cell)))
        outcome = controller.assemble("demo")
        released = ur_cell.next_event()
        streamed = twists(robot_log(ur_cell))[before:]
        rate = (len(streamed) - 1) / (streamed[-1] - streamed[0])
        figures.append((seed, released["placement_error_mm"], outcome.cell_time_s, rate, len(streamed)))
        print(
            seed,
            outcome.outcome,
            f"{outcome.cell_time_s} s",
            f"{rate:.1f} twists/s",
            "gaps",
            np.round(sorted(np.diff(streamed))[-3:], 3),
            flush=True,
        )
        assert outcome.outcome is Outcome.PLACED and released["inside"], (outcome, released)
        assert released["placement_error_mm"] <= 0.3, released
        assert outcome.cell_time_s is not None and outcome.cell_time_s <= 6.0, figures
        assert rate >= 25.0, figures
        assert not loaded_modules(controller.log()) & SIMULATOR_MODULES, sorted(
            loaded_modules(controller.log()) & SIMULATOR_MODULES
        )
    print("seed, gauge mm, cell time s, twists per s, twists:", np.round(figures, 3).tolist())
