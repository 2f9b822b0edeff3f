"""The cell file for a Universal Robots cell: [ur], the cup on a UR's digital I/O, the
streamed servo's [motion] keys, and the arm from example-robot-data or any URDF."""

from xml.etree import ElementTree

import numpy as np
import pytest

from vservo.core.cell.config import ConfigError, parse_cell, read_cell_data
from vservo.core.servo.step_policy import StreamedVelocity, step_policy_from_config
from vservo.robot_models.loader import _example_robot_data_share, joint_limits


def ur_tables(**robot):
    tables, _ = read_cell_data()
    tables["robot"] = {**tables["robot"], "backend": "ur", **robot}
    tables["ur"] = {"host": "192.168.1.10", "acceleration_mm_s2": 2000.0}
    tables["vacuum"] = {**tables["vacuum"], "device": "ur_io", "io": "tool", "suction_output": 1, "grip_input": 0}
    tables["motion"] = {**tables["motion"], "mode": "streaming", "stream_gain": 5.0, "stream_max_speed_mm_s": 80.0}
    return tables


def test_a_ur_cell_reads_its_controller_its_cup_and_its_streamed_servo():
    config = parse_cell(ur_tables())
    assert config.robot_backend == "ur" and config.ur.host == "192.168.1.10"
    assert config.ur.acceleration_m_s2 == pytest.approx(2.0) and config.ur.script_port == 30002
    vacuum = config.vacuum_device
    assert (vacuum.device, vacuum.io, vacuum.suction_output, vacuum.grip_input) == ("ur_io", "tool", 1, 0)
    policy = step_policy_from_config(config.motion)
    assert isinstance(policy, StreamedVelocity)
    assert (policy.gain, policy.max_speed_m_s, policy.hold_s) == (5.0, pytest.approx(0.08), 0.1)


@pytest.mark.parametrize(
    "change, words",
    [
        (lambda t: t["vacuum"].update(suction_output=2), "vacuum.suction_output = 2: must be a tool digital signal, 0..1"),
        (lambda t: t["vacuum"].update(io="flange"), "vacuum.io = 'flange'"),
        (lambda t: t["robot"].update(backend="jrc"), "needs robot.backend = \"ur\", not 'jrc'"),
        (lambda t: t["ur"].update(script_port=0), "ur.script_port = 0: a TCP port"),
        (lambda t: t["ur"].update(acceleration_mm_s2=-1.0), "ur.acceleration_mm_s2 = -1.0"),
        (lambda t: t["motion"].update(stream_max_speed_mm_s=900.0), 'exceeds [safety] max_speed_mm_s = 250 (mode = "streaming")'),
        (lambda t: t["motion"].update(stream_hold_s=3.0), "motion.stream_hold_s = 3.0: must be more than 0 and at most 1 s"),
    ],
)
def test_a_wrong_ur_setting_is_refused_naming_the_key(change, words):
    tables = ur_tables()
    change(tables)
    with pytest.raises(ConfigError, match=words.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[").replace("]", r"\]")):
        parse_cell(tables)


def urdf_limits(path) -> tuple[list[float], list[float]]:
    """The revolute joints' limits, read from the URDF's XML."""
    joints = [j for j in ElementTree.parse(path).getroot().iter("joint") if j.get("type") == "revolute"]
    return [float(j.find("limit").get("lower")) for j in joints], [float(j.find("limit").get("upper")) for j in joints]


URDFS = _example_robot_data_share() / "example-robot-data/robots/ur_description/urdf"


@pytest.mark.parametrize("arm, urdf", [("ur5", "ur5_robot.urdf"), ("ur10", "ur10_robot.urdf")])
def test_example_robot_datas_ur_arms_come_with_their_urdfs_joint_limits(arm, urdf):
    config = parse_cell(ur_tables(arm=arm, home_joints_deg=[0.0, -90.0, 90.0, -90.0, -90.0, 0.0]))
    lower, upper = joint_limits(config.arm)
    assert np.allclose((lower, upper), urdf_limits(URDFS / urdf))


def test_any_urdf_is_an_arm_with_its_flange_frame_named_and_its_limits_read_from_it(tmp_path):
    urdf = URDFS / "ur5_joint_limited_robot.urdf"
    config = parse_cell(ur_tables(arm=f"{urdf}#tool0", home_joints_deg=[0.0, -90.0, 90.0, -90.0, -90.0, 0.0]))
    lower, upper = joint_limits(config.arm)
    assert np.allclose((lower, upper), urdf_limits(urdf)) and np.allclose(upper, np.pi)  # the joint-limited UR5: +-180 deg
    with pytest.raises(ConfigError, match="home_joints_deg.*beyond"):
        parse_cell(ur_tables(arm=f"{urdf}#tool0", home_joints_deg=[200.0, -90.0, 90.0, -90.0, -90.0, 0.0]))
    with pytest.raises(ConfigError, match="has no frame 'flange'"):
        parse_cell(ur_tables(arm=f"{urdf}#flange"))
