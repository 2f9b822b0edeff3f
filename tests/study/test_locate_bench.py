"""The locate bench: alike failures count together, whatever their figures; a place counts
as servable only where the arm reaches the run's own goal."""

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from vservo.core.cell.config import load_cell
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.spatial import inverse, rot_z, transform
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.retarget import desired_view_for_part, retarget
from vservo.core.production.storage import Store
from vservo.core.robot.safety import SafetyRefusal
from vservo.core.study.locate_bench import _servable, failure_kind


def test_failures_count_together_by_their_words_and_the_joint_at_its_limit():
    servo = (
        "servo failed: robot_stopped (move refused: no joints within the limits reach the target (IK of 'flange' "
        "did not converge from 21 seeds: remaining error {} mm / 0.0 deg, joint_3 at its upper limit))"
    )
    assert (
        failure_kind(servo.format("0.1"))
        == failure_kind(servo.format("0.4"))
        == ("servo failed: robot_stopped, joint_3 at its upper limit")
    )
    assert failure_kind(servo.replace("joint_3", "joint_2").format("0.1")) != failure_kind(servo.format("0.1"))
    assert failure_kind("servo failed: features_lost (corners lost in stage 3)") == "servo failed: features_lost"


def test_a_place_whose_desired_view_through_the_cells_hand_eye_is_out_of_reach_is_not_servable(tmp_path):
    """A cell commissioned on static/truths/table-5-3.toml's truth measures eMc about 20 mm
    and 5 deg per axis off the taught one. The demo job at (-359.6, -36.2) mm, turned 86.1
    deg (seed 1's draw that the servo left 29 px short with joint 3 at its upper limit):
    through the taught eMc its desired view is reachable, but the run servoes to the view
    through the cell's eMc, which no branch of the arm reaches (joint 3 past its limit)."""
    text = (Path(__file__).parents[2] / "static" / "cell.toml").read_text()
    taught_eMc = re.search(r"^eMc = .*$", text, re.MULTILINE).group(0)
    cell_file = tmp_path / "cell.toml"
    cell_file.write_text(text.replace(taught_eMc, "eMc = [-20.0, 20.0, 19.9, 5.0, 5.0, 5.0]"))
    config = load_cell(cell_file)
    rig = build_rig(config, seed=1)
    try:
        job = Store(tmp_path / "data").load_job("demo")
        yaw = np.radians(86.1)
        centre_to_O = 0.5 * job.part_side_m * np.array([np.cos(yaw) - np.sin(yaw), np.sin(yaw) + np.cos(yaw)])
        x, y = np.array([-0.3596, -0.0362]) - centre_to_O
        bMo = transform(rot_z(yaw)[:3, :3], (x, y, config.simulation.scene.table_height_m + job.part_side_m))
        view_taught = bMo @ inverse(job.taught_model.eMc @ job.desired.cdMo)
        view_run = bMo @ inverse(config.nominal.eMc @ job.desired.cdMo)
        rig.robot.arm.ik(view_taught, config.home_q)  # reachable: the check of the taught view passed
        with pytest.raises(UnreachableTarget, match="joint_3 at its upper limit"):
            rig.robot.arm.ik(view_run, config.home_q, restarts=100)
        assert not _servable(rig, replace(job, survey_bMe=job.start_bMe), bMo)
        # The goal a locating run checks as soon as it has found the part (run_assembly),
        # and refuses at once instead of servoing until a joint is stuck at its limit.
        run_job = retarget(job, config.nominal)
        goal_bMe = desired_view_for_part(run_job, run_job.taught_model, bMo)
        assert np.allclose(goal_bMe, view_run, atol=1e-6)
        with pytest.raises(SafetyRefusal, match="joint_3 at its upper limit"):
            rig.robot.check_target(goal_bMe, 0.05, bMe_now=goal_bMe)
    finally:
        rig.close()
