"""The shipped cell with a UR arm in place of the UPJ (static/cell-ur5.toml, cell-ur10.toml):
only [robot] differs, and from its home the demo job's taught poses pass the safety layer's
checks, tool down, on the arm's own model. No virtual cell: the kinematic simulator is the
robot the safety layer wraps (tests/production/test_ur_cell.py drives the UR controller)."""

from pathlib import Path

import numpy as np
import pytest

from vservo.core.cell.config import load_cell, parse_cell, read_cell_data
from vservo.core.geometry.spatial import pose_error
from vservo.core.production.jobs import read_job_file
from vservo.core.robot.safety import OutsideWorkspace, SafetyLayer
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.plant import SimulatedCell

STATIC = Path(__file__).resolve().parents[2] / "static"
ARMS = ("ur5", "ur10")


def safety_on_the_simulator(config) -> SafetyLayer:
    return SafetyLayer.from_config(SimulatedBackend.enabled(SimulatedCell(config)), config)


@pytest.mark.parametrize("arm", ARMS)
def test_the_ur_cell_is_the_shipped_cell_with_only_its_robot_changed(arm):
    tables, _ = read_cell_data(STATIC / f"cell-{arm}.toml")
    shipped, _ = read_cell_data()
    assert tables["robot"]["arm"] == arm and load_cell(STATIC / f"cell-{arm}.toml").arm == arm
    assert {k: v for k, v in tables.items() if k != "robot"} == {k: v for k, v in shipped.items() if k != "robot"}


@pytest.mark.parametrize("arm", ARMS)
def test_from_the_ur_cells_home_the_demos_poses_pass_the_safety_checks_tool_down(arm):
    config = load_cell(STATIC / f"cell-{arm}.toml")
    demo = read_job_file(STATIC / "jobs" / "demo.json")
    safety = safety_on_the_simulator(config)
    bMe_home = safety.read_pose()
    assert np.allclose(bMe_home[:3, 2], [0.0, 0.0, -1.0], atol=1e-9)  # tool down
    bMe_pick = demo.taught_bMe @ demo.eMe_pick
    for bMe in (demo.start_bMe, demo.taught_bMe, bMe_pick, demo.bMe_place, demo.check.check_bMe):
        assert safety.joint_path(bMe_home, bMe, config.motion.move_speed_m_s)
        assert safety.linear_path(bMe_home, bMe, config.motion.move_speed_m_s)
    # The run's first move, as assembly makes it from home (not wound: a straight line), executed.
    assert not safety.wound(demo.start_bMe)
    safety.move_linear(demo.start_bMe, config.motion.move_speed_m_s)
    translation, rotation = pose_error(safety.read_pose(), demo.start_bMe)
    assert translation < 1e-6 and rotation < 1e-6


def test_the_upjs_home_joints_put_a_ur5s_tool_outside_the_shipped_workspace():
    """Why a UR cell needs its own home: the UPJ's joints on a UR5 are no tool-down pose over the table."""
    tables, _ = read_cell_data()
    tables["robot"] = {**tables["robot"], "arm": "ur5"}
    config = parse_cell(tables)
    safety = safety_on_the_simulator(config)
    with pytest.raises(OutsideWorkspace):
        safety.check_target(safety.read_pose(), config.motion.move_speed_m_s, bMe_now=safety.read_pose())
