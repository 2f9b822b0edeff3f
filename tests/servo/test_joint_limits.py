"""The arm's joint limits inside the control law: a step into a limit is bent and keeps the
joint inside, a step far from the limits goes as the policy made it, bit for bit."""

import re
from dataclasses import dataclass
from itertools import product

import numpy as np
import pinocchio as pin
import pytest

from vservo.core.cell.kinematics import ArmKinematics, UnreachableTarget
from vservo.core.geometry.spatial import inverse
from vservo.core.robot.commands import PositionCommand, VelocityCommand
from vservo.core.servo.joint_limits import JointBound, JointLimitedSteps, JointLimitSettings, bounded_least_squares
from vservo.core.servo.laws.base import ControlOutput, Failure
from vservo.core.servo.loop import LoopLimits, run_servo
from vservo.core.servo.step_policy import IntegratedVelocity
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.plant import SimulatedCell
from vservo.core.study.montecarlo import run_sample
from vservo.core.study.run import RunSettings, teach
from vservo.core.study.tasks import TASKS
from vservo.robot_models.loader import load_arm

DT_S = 0.1


@pytest.fixture(scope="module")
def arm(cell_config):
    """The controller's model of the UPJ with the nominal tool mount."""
    return ArmKinematics(load_arm(cell_config.arm), cell_config.nominal.mount)


def near_elbow_limit(arm, cell_config, below_rad):
    """The home pose with joint 3 (the elbow) ``below_rad`` under its upper limit."""
    q = cell_config.home_q.copy()
    q[2] = arm.upper[2] - below_rad
    return q


def joint_step(arm, q, dq, policy="velocity"):
    """The command whose flange step is, to first order, the joint step dq (eq. 4-17)."""
    xi_e = arm.jacobian(q, "flange") @ dq
    bMe = arm.fk(q)
    if policy == "velocity":
        return VelocityCommand(xi_e / DT_S, DT_S), bMe
    return PositionCommand(VelocityCommand(xi_e, 1.0).target(bMe), 0.05, 2.0), bMe


def brute_force_bounded_least_squares(A, b, lower, upper):
    """The best of every assignment of each variable to free, its lower or its upper bound."""
    best, best_cost = None, np.inf
    for sides in product((None, "lower", "upper"), repeat=A.shape[1]):
        x = np.array([lower[i] if s == "lower" else upper[i] if s == "upper" else 0.0 for i, s in enumerate(sides)])
        free = np.array([s is None for s in sides])
        if free.any():
            x[free] = np.linalg.lstsq(A[:, free], b - A[:, ~free] @ x[~free], rcond=None)[0]
        if np.all((lower - 1e-12 <= x) & (x <= upper + 1e-12)):
            cost = float(np.sum((A @ x - b) ** 2))
            if cost < best_cost:
                best, best_cost = x, cost
    return best


@pytest.mark.parametrize("seed", range(8))
def test_the_bounded_least_squares_finds_the_best_point_in_the_box(seed):
    rng = np.random.default_rng(seed)
    A, b = rng.normal(size=(6, 5)), rng.normal(size=6) * 3.0
    lower, upper = -rng.uniform(0.0, 0.5, 5), rng.uniform(0.0, 0.5, 5)
    lower[0] = 0.0  # a variable that may not go down at all (a joint at its margin)
    x = bounded_least_squares(A, b, lower, upper)
    assert np.all((lower <= x) & (x <= upper))
    expected = brute_force_bounded_least_squares(A, b, lower, upper)
    assert np.sum((A @ x - b) ** 2) == pytest.approx(np.sum((A @ expected - b) ** 2), rel=1e-9, abs=1e-12)
    assert np.allclose(x, expected, atol=1e-9)


def test_far_from_the_limits_a_command_goes_unchanged_bit_for_bit(arm, cell_config):
    q = cell_config.home_q
    assert np.all(np.minimum(q - arm.lower, arm.upper - q) > JointLimitSettings().band_rad)
    limits = JointLimitedSteps(arm)
    for policy in ("velocity", "position"):
        command, bMe = joint_step(arm, q, np.radians([20.0, -15.0, 25.0, 40.0, -30.0, 90.0]), policy)
        step = limits.limit(command, bMe, q)
        assert step.command is command and step.held == ()


def test_near_a_limit_a_step_away_from_it_goes_unchanged(arm, cell_config):
    q = near_elbow_limit(arm, cell_config, np.radians(1.0))
    command, bMe = joint_step(arm, q, np.radians([0.0, 0.0, -5.0, 0.0, 0.0, 0.0]))
    step = JointLimitedSteps(arm).limit(command, bMe, q)
    assert step.command is command and step.held == ()


@pytest.mark.parametrize("policy", ["velocity", "position"])
def test_a_step_into_a_limit_is_bent_and_the_joint_stays_inside(arm, cell_config, policy):
    q = near_elbow_limit(arm, cell_config, np.radians(1.0))
    command, bMe = joint_step(arm, q, np.radians([3.0, 2.0, 5.0, 0.0, 4.0, 0.0]), policy)
    with pytest.raises(UnreachableTarget, match="joint_3 at its upper limit"):
        arm.ik(command.target(bMe), q, restarts=0)  # as commanded, the controller refuses it

    limits = JointLimitedSteps(arm)
    step = limits.limit(command, bMe, q)
    assert type(step.command) is type(command)
    assert step.held == (JointBound("joint_3", "upper"),)
    assert str(step.held[0]) == "joint_3 at its upper limit"
    q_next = arm.ik(step.command.target(bMe), q, restarts=0).q
    assert q_next[2] == pytest.approx(arm.upper[2] - limits.settings.margin_rad, abs=1e-6)
    assert arm.within_limits(q_next)
    # The other joints keep as much of the camera's motion as they can: it still goes the
    # commanded way, a long way.
    commanded = np.linalg.norm(command.target(bMe)[:3, 3] - bMe[:3, 3])
    bent = step.command.target(bMe)[:3, 3] - bMe[:3, 3]
    assert bent @ (command.target(bMe)[:3, 3] - bMe[:3, 3]) > 0.5 * commanded**2
    if policy == "position":
        assert (step.command.speed_m_s, step.command.period_s) == (command.speed_m_s, command.period_s)


def test_a_joint_inside_its_margin_may_leave_but_not_go_further_in(arm, cell_config):
    limits = JointLimitedSteps(arm)
    q = near_elbow_limit(arm, cell_config, limits.settings.margin_rad / 4)
    command, bMe = joint_step(arm, q, np.radians([0.0, 0.0, 0.5, 0.0, 1.0, 0.0]))
    step = limits.limit(command, bMe, q)
    q_next = arm.ik(step.command.target(bMe), q, restarts=0).q
    assert q_next[2] <= q[2] + 1e-7 and step.held == (JointBound("joint_3", "upper"),)


def test_settings_that_make_no_sense_are_refused():
    with pytest.raises(ValueError, match="margin_rad"):
        JointLimitSettings(band_rad=0.01, margin_rad=0.02)
    with pytest.raises(ValueError, match="rotation_weight_m"):
        JointLimitSettings(rotation_weight_m=0.0)


@dataclass(frozen=True)
class Homing:
    """A position-based law for the test: it steers the TRUE camera straight to bMc_goal
    (the plant's pose, which no real law may read), its error the distance left in mm."""

    cell: SimulatedCell
    bMc_goal: np.ndarray
    name: str = "homing"

    def step(self, features, desired, stage):
        cMc_goal = inverse(self.cell.ground_truth_bMe() @ self.cell.truth.model.eMc) @ self.bMc_goal
        cVc = pin.log6(pin.SE3(cMc_goal)).vector
        error_mm = 1000.0 * float(np.linalg.norm(cMc_goal[:3, 3]))
        return ControlOutput(cVc, "homing", error_mm, error_mm)


def test_a_goal_beyond_the_limits_still_ends_unreachable_naming_the_joint(arm, cell_config):
    """The goal: the camera where the elbow would put it 10 deg past its upper limit."""
    cell = SimulatedCell(cell_config)
    scene = cell_config.simulation.scene
    cell.place_cube(TASKS[2].placement.bMo(scene.table_height_m, scene.cube.side_m))
    desired = teach(cell, TASKS[2].desired_cMo, cell_config.nominal)
    cell.set_joints(near_elbow_limit(arm, cell_config, np.radians(5.0)))
    q_goal = near_elbow_limit(arm, cell_config, np.radians(-10.0))
    law = Homing(cell, cell.truth.arm.fk(q_goal, "camera"))
    outcome = run_servo(
        cell,
        law,
        desired,
        cell_config.nominal,
        IntegratedVelocity(DT_S),
        LoopLimits(progress_window=20),
        robot=SimulatedBackend.enabled(cell),
        joint_limits=JointLimitedSteps(arm),
    )
    # Bent around the limit as near to the goal as the arm goes, then stopped there, named.
    assert outcome.failure is Failure.UNREACHABLE, outcome.reason
    assert re.fullmatch(r"stage homing error [0-9.]+ after 20 cycles, joint_3 at its upper limit", outcome.reason)
    assert arm.within_limits(cell.state.q)


def test_a_monte_carlo_start_the_arm_stopped_on_now_converges(cell_config):
    """Seed 0's sample 1: without the limits in the law the elbow hit its upper limit at
    the 4th cycle ("unreachable"); bent around it the laser method converges."""
    outcome = run_sample(cell_config, RunSettings(method="laser"), seed=0, index=1)
    assert outcome.converged, outcome
