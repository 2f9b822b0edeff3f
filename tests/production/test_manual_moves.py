"""Moving the arm by hand on the simulated cell: Home and Survey from where a run left the arm,
manual mode, and moves refused by kind with the words of the catalogue
(core/production/manual_moves.py, core/production/protocol/catalogue.py)."""

from __future__ import annotations

import numpy as np
import pytest

from vservo.app.teach_panel import parse_pose_mm_deg
from vservo.core.geometry.spatial import pose_error
from vservo.core.production.cell_controller import CommandRefused
from vservo.core.production.protocol import Outcome, Phase
from vservo.core.production.protocol.catalogue import Refusal


@pytest.fixture
def after_a_run(controller):
    """The demo job placed: the arm stands over the metal part, the phase done."""
    controller.present_part()
    controller.start("demo")
    controller.wait()
    assert controller.last_outcome.outcome is Outcome.PLACED
    return controller


def test_home_and_survey_bring_the_arm_back_from_the_pocket_and_the_survey_sees_new_parts(after_a_run):
    controller = after_a_run
    robot = controller.rig.robot
    controller.go_home()
    translation, rotation = pose_error(robot.read_pose(), robot.arm.fk(controller.rig.config.home_q))
    assert translation < 1e-3 and rotation < 1e-3
    controller.go_survey()
    assert "survey" in controller.state.detail
    controller.begin_teach()
    for centre_mm in ((-390.0, -40.0), (-420.0, 20.0), (-360.0, -40.0)):  # around where parts are presented
        controller.present_part(centre_mm, 15.0)
        _, features = controller.look(fresh=True)
        assert features.all_corners_visible, centre_mm


def test_jogs_and_typed_moves_only_while_teaching_or_in_manual_mode(after_a_run):
    controller = after_a_run
    for move in (lambda: controller.jog([0.0, 0.0, 0.005]), lambda: controller.move_to(controller.state.bMe)):
        with pytest.raises(CommandRefused) as refused:
            move()
        assert refused.value.kind is Refusal.NOT_MANUAL
    controller.enter_manual()
    assert controller.state.phase is Phase.MANUAL
    controller.jog([0.0, 0.0, 0.005])
    with pytest.raises(CommandRefused) as refused:
        controller.start("demo")  # no run from manual mode
    assert refused.value.kind is Refusal.NOT_NOW
    controller.leave_manual()
    assert controller.state.phase is Phase.IDLE


def test_a_target_is_refused_saying_whether_a_joint_path_reaches_it_or_which_joint_stops_it(controller):
    controller.go_survey()
    controller.enter_manual()
    with pytest.raises(CommandRefused) as refused:
        controller.move_to(parse_pose_mm_deg("-200 0 0 180 0 180"))  # near the base, low: the elbow folds
    assert refused.value.kind is Refusal.UNREACHABLE
    assert refused.value.advice == "joint_3 stops at its upper limit: move the target toward -X."
    target = parse_pose_mm_deg("-350 200 300 180 0 180")
    before = controller.rig.robot.read_pose()
    with pytest.raises(CommandRefused) as refused:
        controller.move_to(target)  # the straight line from the survey passes a joint limit
    assert refused.value.kind is Refusal.LINE_BLOCKED
    assert np.array_equal(controller.rig.robot.read_pose(), before)  # a refusal moves nothing
    controller.move_joint(target)
    translation, rotation = pose_error(controller.rig.robot.read_pose(), target)
    assert translation < 1e-3 and rotation < 1e-3


def test_a_part_presented_after_a_run_clears_its_verdict(after_a_run):
    controller = after_a_run
    assert controller.state.phase is Phase.DONE
    controller.present_part()
    assert controller.state.phase is Phase.IDLE and controller.state.last_outcome is not None
