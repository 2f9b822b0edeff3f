"""The safety layer on both backends: the simulator, and the JRC link to an emulator over a pty.

Each refusal names its reason and leaves the robot where it was; the e-stop and the
watchdog hold the robot and refuse every move until they are reset.
"""

import re
import time
from contextlib import contextmanager
from dataclasses import replace

import numpy as np
import pytest

from tests.jrc_fixtures import jrc_link, short_timer_cell
from vservo.core.geometry.spatial import pose_error, rot_z, transform
from vservo.core.robot.backend import JointMotionBackend
from vservo.core.robot.safety import (
    BeyondJointLimits,
    OutsideWorkspace,
    SafetyLayer,
    SafetyRefusal,
    SafetyStopActive,
    StepTooLarge,
    TooFast,
)
from vservo.core.servo.laws.base import ControlOutput, Failure
from vservo.core.servo.loop import LoopLimits, run_servo
from vservo.core.servo.step_policy import DividedPositionStep
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.plant import SimulatedCell
from vservo.core.study.run import teach
from vservo.core.study.tasks import TASKS

pytestmark = pytest.mark.usefixtures("no_leaked_threads")

SPEED = 0.05


@contextmanager
def guarded(backend_name, config):
    """A SafetyLayer around a connected robot with servo power on, and the cell it moves."""
    cell = SimulatedCell(config)
    if backend_name == "sim":
        yield SafetyLayer.from_config(SimulatedBackend.enabled(cell), config), cell
        return
    with jrc_link(cell, config) as (robot, _):
        robot.servo(True)
        safe = SafetyLayer.from_config(robot, config)
        try:
            yield safe, cell
        finally:
            safe.watchdog.disarm()


@pytest.fixture(params=["sim", "jrc"])
def backend_name(request):
    return request.param


@pytest.fixture
def safe(backend_name):
    with guarded(backend_name, short_timer_cell()) as safe:
        yield safe


def arm_pose(cell):
    return cell.jrc_arm.fk(cell.state.q)


def test_a_target_outside_the_workspace_is_refused_and_nothing_moves(safe):
    robot, cell = safe
    before = arm_pose(cell)
    below_the_table = transform(t=(0.0, 0.0, -0.6)) @ before
    with pytest.raises(OutsideWorkspace, match=r"the flange would be at .* mm, outside the workspace box on z"):
        robot.move_to(below_the_table, SPEED)
    # The flange stays in the box, the vacuum cup 60 mm below it does not.
    with pytest.raises(OutsideWorkspace, match=r"the vacuum cup would be at .* outside the workspace box on z"):
        robot.move_to(transform(t=(0.0, 0.0, -0.45)) @ before, SPEED)
    with pytest.raises(OutsideWorkspace, match="not a finite"):
        robot.move_to(np.full((4, 4), np.nan), SPEED)
    assert np.array_equal(arm_pose(cell), before)


def test_a_step_too_large_or_too_fast_is_refused(safe):
    robot, cell = safe
    before = arm_pose(cell)
    with pytest.raises(StepTooLarge, match="a step of 60.0 mm exceeds the maximum 50.0 mm"):
        robot.move_by(transform(t=(0.06, 0.0, 0.0)), SPEED)
    with pytest.raises(StepTooLarge, match="a step of 20.00 deg exceeds the maximum 15.00 deg"):
        robot.move_to(before @ transform(rot_z(np.radians(20.0))), SPEED)
    with pytest.raises(TooFast, match="speed 300.0 mm/s exceeds the maximum 250.0 mm/s"):
        robot.move_by(transform(t=(0.01, 0.0, 0.0)), 0.3)
    assert np.array_equal(arm_pose(cell), before)
    # A step within every limit goes through.
    robot.move_by(transform(t=(0.01, 0.0, 0.0)), SPEED)
    assert robot.wait_motion()
    assert pose_error(arm_pose(cell), transform(t=(0.01, 0.0, 0.0)) @ before)[0] < 1e-6


def test_a_long_taught_move_is_checked_along_its_line_and_goes_out_as_one_move_without_a_reading(safe):
    """144 mm and 25 deg, beyond one step's limits: checked at points at most 45 mm and
    13.5 deg apart (linear_path), then one linear move; the next move starts from its
    target, which the robot reported reached, without reading the pose again."""
    robot, cell = safe
    before = arm_pose(cell)
    target = transform(t=(0.0, 0.12, -0.08)) @ before @ transform(rot_z(np.radians(25.0)))
    points = robot.linear_path(robot.read_pose(), target, SPEED)
    assert len(points) == 4 and np.allclose(points[-1], target)
    steps = [pose_error(a, b) for a, b in zip([before, *points], points)]
    assert max(t for t, _ in steps) <= 0.05 and max(r for _, r in steps) <= np.radians(15.0)
    sent, reads = [], []
    move_to, read_pose = robot.robot.move_to, robot.robot.read_pose
    robot.robot.move_to = lambda bMe, speed: (sent.append(bMe), move_to(bMe, speed))[1]
    robot.robot.read_pose = lambda: (reads.append(1), read_pose())[1]
    robot.move_linear(target, SPEED)
    assert pose_error(arm_pose(cell), target)[0] < 1e-4
    assert len(sent) == 1 and np.allclose(sent[0], target)
    robot.move_linear(before, SPEED)
    assert len(sent) == 2 and not reads  # known where it stood: no reading
    assert np.allclose(robot.pose(), before) and not reads
    robot.hold(False)  # a hold (or servo power, an alarm reset) forgets it: the next call reads
    robot.pose()
    assert len(reads) == 1


def test_a_long_move_refused_on_its_way_moves_nothing(safe):
    robot, cell = safe
    before = arm_pose(cell)
    robot.check_target(transform(t=(0.0, 0.04, 0.0)) @ before, SPEED)  # its first step alone would pass
    with pytest.raises(SafetyRefusal, match="move refused"):
        robot.move_linear(transform(t=(0.0, 0.45, 0.0)) @ before, SPEED)
    assert np.array_equal(arm_pose(cell), before)


@pytest.mark.parametrize("distance_m", [10.0, 1e9, 1e300])
def test_a_far_target_is_refused_at_once_naming_it_whatever_the_distance(safe, distance_m):
    """The target is checked against the workspace before a path is built: the refusal
    names the target itself (not the first step of a path of 10^10 steps to it), so the
    work is bounded whatever was asked; nothing moves."""
    robot, cell = safe
    before = arm_pose(cell)
    far = transform(t=(0.0, distance_m, 0.0)) @ before
    shown = re.escape(f"{np.round(far[:3, 3] * 1000, 1).tolist()}")
    for move in (robot.move_linear, robot.move_joint):
        with pytest.raises(OutsideWorkspace, match=f"the flange would be at {shown} mm"):
            move(far, SPEED)
    assert np.array_equal(arm_pose(cell), before)


def tool_down(x, y, z):
    bMe = transform(t=(x, y, z))
    bMe[:3, :3] = np.diag([1.0, -1.0, -1.0])
    return bMe


def test_a_transfer_whose_straight_line_leaves_the_arms_shell_goes_on_the_joint_space_line(safe):
    """Two tool-down poses 412 and 390 mm from the base axis at z = 50 mm: the straight line
    between them passes 361 mm from it, inside the hole of the UPJ's tool-down shell there."""
    robot, cell = safe
    here, there = tool_down(-0.36, -0.20, 0.05), tool_down(-0.36, 0.15, 0.05)
    robot.move_joint(here, SPEED)
    assert pose_error(arm_pose(cell), here)[0] < 1e-4
    with pytest.raises(BeyondJointLimits, match="no joints within the limits reach the target"):
        robot.move_linear(there, SPEED)
    assert pose_error(arm_pose(cell), here)[0] < 1e-4  # refused whole: nothing moved
    sent = []
    move_to = robot.robot.move_to
    robot.robot.move_to = lambda bMe, speed: (sent.append((arm_pose(cell), bMe)), move_to(bMe, speed))[1]
    assert not isinstance(robot.robot, JointMotionBackend)  # a look-and-move controller: the line in steps
    robot.move_joint(there, SPEED)
    assert pose_error(arm_pose(cell), there)[0] < 1e-4 and pose_error(arm_pose(cell), there)[1] < 1e-4
    assert len(sent) == 9  # 350 mm of chord, a longer arc, in steps of at most 45 mm
    steps = [pose_error(before, after) for before, after in sent]
    assert max(t for t, _ in steps) <= 0.05 and max(r for _, r in steps) <= np.radians(15.0)
    # On the way the flange swung out round the base axis, never in through the hole.
    radii = [np.linalg.norm(after[:2, 3]) for _, after in sent]
    assert min(radii) > 0.389


def test_a_taught_half_turn_goes_out_as_moves_the_controller_turns_the_way_the_model_does(safe):
    """A half turn of the flange is a toss-up for the short way round: sent whole, the
    controller may turn one way and the arm's model the other, a turn of joint 6 apart
    after it. It goes out as moves of at most 90 deg along the checked line instead."""
    robot, cell = safe
    start = tool_down(-0.36, -0.20, 0.05)
    robot.move_joint(start, SPEED)
    sent = []
    move_to = robot.robot.move_to
    robot.robot.move_to = lambda bMe, speed: (sent.append((arm_pose(cell), bMe)), move_to(bMe, speed))[1]
    for half_turns in (1, 2):  # a half turn, and back to the start's orientation the same way or not
        target = start @ transform(rot_z(np.pi * half_turns))
        robot.move_linear(target, SPEED)
        assert pose_error(arm_pose(cell), target)[0] < 1e-4 and pose_error(arm_pose(cell), target)[1] < 1e-4
        np.testing.assert_allclose(robot.model_joints(robot.pose()), cell.state.q, atol=1e-3)
    assert len(sent) == 4 and max(pose_error(before, after)[1] for before, after in sent) <= np.radians(90.0) + 1e-6


def test_a_wrist_wound_a_turn_is_unwound_by_the_joint_move_that_asks_it(backend_name):
    """Joint 6 a turn from the middle of its range (the UPJ's +-360 deg) leaves the servo
    no room to turn one way: move_joint(unwind=True) ends with it nearest the middle, the
    arm's model and the controller alike."""
    config = short_timer_cell()
    arm = SafetyLayer.from_config(SimulatedBackend.enabled(SimulatedCell(config)), config).arm
    q = np.array(config.home_q, dtype=float)
    wound = q.copy()
    wound[5] = q[5] - 2 * np.pi if q[5] > 0 else q[5] + 2 * np.pi
    np.testing.assert_allclose(arm.unwound(wound), q)
    np.testing.assert_allclose(arm.unwound(q), q)  # only the multi-turn joints, and only by whole turns
    with guarded(backend_name, replace(config, home_q=wound)) as (robot, cell):
        cell.state = replace(cell.state, q=wound)
        here = robot.read_pose()
        assert robot.wound(here)
        robot.move_joint(here, SPEED, unwind=True)
        np.testing.assert_allclose(cell.state.q, q, atol=1e-3)
        np.testing.assert_allclose(robot.model_joints(robot.pose()), q, atol=1e-3)
        assert not robot.wound(here) and pose_error(arm_pose(cell), here)[0] < 1e-4


def test_a_joint_move_to_a_pose_out_of_reach_is_refused_and_nothing_moves(safe):
    robot, cell = safe
    before = arm_pose(cell)
    with pytest.raises(BeyondJointLimits, match="no joints within the limits reach the path's ends"):
        robot.move_joint(tool_down(-0.60, 0.0, 0.05), SPEED)  # beyond the arm's reach tool-down
    assert np.array_equal(arm_pose(cell), before)


def test_joints_too_close_to_their_limits_are_refused(backend_name):
    """Home has joint 3 at 150 deg, 25 deg from its limit: a 30 deg margin refuses any move there."""
    with guarded(backend_name, short_timer_cell(safety={"joint_margin_deg": 30.0})) as (robot, cell):
        with pytest.raises(BeyondJointLimits, match="joint_3 would be 2[45].* deg from its limit, closer than the margin"):
            robot.move_by(transform(t=(0.0, 0.0, -0.001)), SPEED)


def test_after_an_e_stop_the_robot_is_held_and_every_move_is_refused(safe):
    robot, cell = safe
    robot.emergency_stop("operator pressed the button")
    assert robot.robot.status().held
    status = robot.status()
    assert "e-stop: operator pressed the button" in status.detail
    step = transform(t=(0.005, 0.0, 0.0))
    with pytest.raises(SafetyStopActive, match="move refused: e-stop: operator pressed the button"):
        robot.move_by(step, SPEED)
    with pytest.raises(SafetyStopActive, match="hold release refused"):
        robot.hold(False)
    with pytest.raises(SafetyStopActive, match="servo power on refused"):
        robot.servo(True)
    robot.reset_emergency_stop()
    robot.hold(False)
    robot.move_by(step, SPEED)
    assert robot.wait_motion()


def test_the_watchdog_holds_the_robot_when_the_camera_goes_quiet(backend_name):
    with guarded(backend_name, short_timer_cell(safety={"watchdog_s": 0.3})) as (robot, cell):
        robot.watchdog.arm()
        deadline = time.monotonic() + 10.0
        while robot.stop_reason is None and time.monotonic() < deadline:
            robot.read_pose()  # the link keeps talking; only the camera is quiet
            time.sleep(0.02)
        assert robot.stop_reason is not None and "watchdog: the camera has been quiet" in robot.stop_reason
        assert robot.robot.status().held and not robot.watchdog.armed
        with pytest.raises(SafetyStopActive, match="watchdog"):
            robot.move_by(transform(t=(0.001, 0.0, 0.0)), SPEED)


def test_a_fed_watchdog_stays_quiet(backend_name):
    with guarded(backend_name, short_timer_cell(safety={"watchdog_s": 5.0})) as (robot, cell):
        robot.watchdog.arm()
        for _ in range(20):
            robot.watchdog.feed("camera")
            robot.read_pose()
            time.sleep(0.01)
        robot.watchdog.disarm()
        assert robot.stop_reason is None and not robot.robot.status().held


class Approach:
    """A control law that asks for 10 mm/s along the optical axis, forever."""

    name = "approach"

    def step(self, features, desired, stage):
        return ControlOutput(np.array([0.0, 0.0, 0.01, 0.0, 0.0, 0.0]), "approach", 50.0, 50.0)


def test_the_loop_stops_with_the_safety_layers_reason(backend_name):
    """A servo whose steps exceed max_step stops at once, names the limit, and moves nothing."""
    config = short_timer_cell(safety={"max_step_mm": 0.1}, motion={"policy": "thesis"})
    with guarded(backend_name, config) as (robot, cell):
        scene = config.simulation.scene
        cell.place_cube(TASKS[2].placement.bMo(scene.table_height_m, scene.cube.side_m))
        desired = teach(cell, TASKS[2].desired_cMo, config.nominal)
        before = arm_pose(cell)
        policy = DividedPositionStep(divide_factor=1.0, sampling_period_s=0.01, speed_m_s=SPEED)
        outcome = run_servo(cell, Approach(), desired, config.nominal, policy, LoopLimits(max_iterations=5), robot=robot)
        assert outcome.failure is Failure.ROBOT_STOPPED and "exceeds the maximum 0.1 mm" in outcome.reason
        assert outcome.iterations == 1 and np.array_equal(arm_pose(cell), before)
        assert not robot.watchdog.armed  # the loop armed it for the run only
