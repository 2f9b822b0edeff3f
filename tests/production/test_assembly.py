"""One-click assembly on the simulated cell, through the controller's state machine."""

from __future__ import annotations

import json
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.controller_fixtures import simulated_controller
from tests.jrc_fixtures import with_the_thesis_policy
from vservo.app.cli import main
from vservo.core.cell.config import CellConfig, load_cell
from vservo.core.production.assembly import AssemblyOutcome, FlangeReadout, Outcome, Phase, joint_limited_steps, run_assembly
from vservo.core.production.cell_controller import CellController, CommandRefused
from vservo.core.production.demo_job import teach_demo_job
from vservo.core.production.protocol import TeachStep
from vservo.core.production.protocol.catalogue import Refusal, RunEnd
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import Store
from vservo.core.robot.safety import SafetyLayer


@pytest.fixture
def thesis_controller(tmp_path):
    """The conftest's controller with the thesis's step policy: hundreds of servo cycles, one per 2 s."""
    with simulated_controller(with_the_thesis_policy(load_cell()), tmp_path / "data") as controller:
        yield controller


def test_demo_job_places_the_part(controller):
    controller.present_part()
    run_id = controller.start("demo")
    controller.wait()
    outcome = controller.last_outcome
    assert outcome.outcome is Outcome.PLACED, outcome.reason
    assert outcome.final_error_px < 3.0
    assert outcome.placement_error_mm < 1.0  # the pocket leaves 1 mm each side
    assert not controller.rig.gripper.holding()
    record = controller.store.run(run_id)
    assert record.outcome is Outcome.PLACED and record.stages == outcome.stages
    assert controller.state.phase == Phase.DONE.value


def assemble_through_the_jrc_link(config: CellConfig, tmp_path: Path) -> tuple[AssemblyOutcome, list[str]]:
    """The demo job once on the simulated cell, every move a BSC exchange over a pty with
    the emulated JRC; its outcome and the motion commands the JRC executed."""
    store = Store(tmp_path / "data")
    rig = simulated_rig(config, seed=3, backend="jrc", jrc_time_scale=1000.0)
    controller = CellController(rig, store, seed=3)
    try:
        controller.present_part()
        controller.start("demo")
        controller.wait()
        return controller.last_outcome, rig.emulator.executed
    finally:
        controller.close()
        store.close()


@pytest.mark.slow
def test_the_demo_job_places_the_part_through_the_jrc_link_in_fewer_steps_than_the_thesis_policy(tmp_path):
    fast, fast_moves = assemble_through_the_jrc_link(load_cell(), tmp_path / "fast")
    assert fast.outcome is Outcome.PLACED, fast.reason
    assert fast.placement_error_mm < 1.0
    assert len(fast_moves) > fast.iterations and all(m.startswith("MOVL") for m in fast_moves)
    thesis, _ = assemble_through_the_jrc_link(with_the_thesis_policy(load_cell()), tmp_path / "thesis")
    assert thesis.outcome is Outcome.PLACED, thesis.reason
    # The cell clock is the emulated JRC's (its speed-up undone, the link at 9600 baud):
    # the thesis policy's 2 s a step against the fast one's few large steps.
    assert fast.iterations < thesis.iterations / 5
    assert fast.cell_time_s < thesis.cell_time_s / 5
    # Split by phase, the servo is where the two differ.
    for run in (fast, thesis):
        assert list(run.cell_time_by_phase_s) == ["start", "servo", "pick", "place", "check"]
        assert sum(run.cell_time_by_phase_s.values()) == pytest.approx(run.cell_time_s)
    assert thesis.cell_time_by_phase_s["servo"] > 0.9 * thesis.cell_time_s


def test_a_part_out_of_reach_of_the_cup_is_a_fault_with_the_robot_held(controller):
    job = controller.store.load_job("demo")
    # A pick transform that stops 30 mm short of the part: the vacuum sensor must say so.
    short = job.eMe_pick.copy()
    short[2, 3] -= 0.03
    controller.store.save_job(replace(job, name="short", eMe_pick=short))
    controller.present_part()
    controller.start("short")
    controller.wait()
    assert controller.last_outcome.outcome is Outcome.FAULT
    assert "vacuum" in controller.last_outcome.reason
    assert controller.rig.robot.status().held
    with pytest.raises(CommandRefused) as refused:
        controller.jog([0.0, 0.0, 0.01])  # no hand moves outside teaching and manual mode
    assert refused.value.kind is Refusal.NOT_MANUAL
    with pytest.raises(CommandRefused) as refused:
        controller.enter_manual()  # nor manual mode with the robot held after the fault
    assert refused.value.kind is Refusal.NOT_NOW
    controller.reset()
    controller.enter_manual()
    controller.jog([0.0, 0.0, 0.01])


def test_estop_stops_the_arm_within_one_cycle_and_refuses_moves_until_reset(thesis_controller):
    controller = thesis_controller  # a servo long enough to press the e-stop in
    cell = controller.rig.cell
    period = controller.rig.config.motion.sampling_period_s
    servoing = threading.Event()

    def watch(state):
        if state.phase == Phase.SERVOING.value and state.run.iteration >= 20:
            servoing.set()

    controller.state_subscribers.append(watch)
    controller.present_part()
    run_id = controller.start("demo")
    assert servoing.wait(60.0)
    controller.estop()
    time_at_estop = cell.state.time_s
    controller.wait()
    # Each servo step is one move of one sampling period: at most the step under way ends.
    assert cell.state.time_s - time_at_estop <= period + 1e-9
    assert controller.last_outcome.outcome is Outcome.ESTOPPED
    assert controller.state.phase == Phase.ESTOPPED.value
    assert controller.store.run(run_id).outcome is Outcome.ESTOPPED
    q = cell.state.q.copy()
    for command in (lambda: controller.jog([0.01, 0.0, 0.0]), lambda: controller.start("demo")):
        with pytest.raises(CommandRefused, match="e-stop"):
            command()
    assert np.array_equal(cell.state.q, q)
    controller.reset()
    assert controller.state.phase == Phase.IDLE.value
    controller.enter_manual()
    controller.jog([0.0, 0.0, 0.005])
    assert not np.array_equal(cell.state.q, q)


def test_teach_a_job_then_assemble_it(controller):
    demo = controller.store.load_job("demo")
    controller.present_part()
    assert controller.state.job is None  # nothing was run yet
    controller.start("demo")
    controller.wait()
    controller.begin_teach()
    assert controller.state.job is None  # a new job is not the last one run
    controller.present_part((-390.0, 0.0), 0.0)  # where the demo job's part was taught
    with pytest.raises(CommandRefused, match="desired image"):
        controller.set_pick_pose()
    controller.move_to(demo.taught_bMe)
    desired = controller.capture_desired()
    np.testing.assert_allclose(desired.corners_px, demo.desired.corners_px, atol=0.05)
    controller.move_to(demo.taught_bMe @ demo.eMe_pick)
    controller.set_pick_pose()
    assert controller.test_pick()
    assert "grip good" in controller.state.detail and not controller.state.holding_part
    controller.move_to(demo.bMe_place)
    with pytest.raises(CommandRefused, match="reports none"):
        controller.set_place_pose()  # the part was left at the pick
    controller.move_to(demo.taught_bMe @ demo.eMe_pick)
    assert controller.suction(True) and controller.state.holding_part
    controller.move_to(demo.bMe_place)
    controller.set_place_pose()
    assert not controller.suction(False)
    controller.move_to(demo.check.check_bMe)
    controller.capture_check_view()
    assert "from where the taught pick and place put it" in controller.state.detail
    assert "WARNING" not in controller.state.detail, controller.state.detail
    with pytest.raises(CommandRefused, match="start pose"):
        controller.save_job("bolt")
    controller.move_to(demo.start_bMe)
    controller.set_start_pose()
    saved = controller.save_job("bolt")
    assert saved.taught_model.matches(controller.rig.config.nominal)  # what the pixels were seen through
    assert controller.store.load_job("bolt").taught_model.matches(controller.rig.config.nominal)
    assert "bolt" in [entry.name for entry in controller.store.list_jobs()]
    assert controller.store.job_image("bolt").shape == (480, 640)
    controller.present_part()
    controller.start("bolt")
    controller.wait()
    assert controller.last_outcome.outcome is Outcome.PLACED, controller.last_outcome.reason


def test_teaching_presents_a_part_where_asked_and_a_test_pick_off_the_part_says_no_grip(controller):
    cell = controller.rig.cell
    controller.begin_teach()
    controller.present_part((-360.0, -20.0), 30.0)  # 40 mm from the demo's part, turned
    bMo = cell.state.scene.cube.bMo
    centre = bMo @ np.array([0.01, 0.01, 0.0, 1.0])
    np.testing.assert_allclose(centre[:2], [-0.360, -0.020], atol=1e-9)
    assert np.degrees(np.arctan2(bMo[1, 0], bMo[0, 0])) == pytest.approx(30.0)
    assert controller.state.phase == Phase.TEACHING.value
    with pytest.raises(CommandRefused, match="no grip") as refused:
        controller.test_pick()  # the cup is nowhere near it
    assert refused.value.kind is Refusal.NO_GRIP
    assert "no grip" in controller.state.detail
    assert controller.state.teaching.test_pick_held is False  # the Teach tab offers the test pick again
    with pytest.raises(CommandRefused, match="X, Y"):
        controller.present_part((float("nan"), 0.0))


def test_a_part_turned_between_the_desired_image_and_the_pick_is_warned_of_at_the_check_view(controller):
    demo = controller.store.load_job("demo")
    controller.begin_teach("demo")
    controller.move_to(demo.taught_bMe)
    controller.capture_desired()
    controller.present_part((-390.0, 0.0), 10.0)  # the same place, turned: the desired image no longer says how
    controller.move_to(demo.taught_bMe @ demo.eMe_pick)
    controller.set_pick_pose()
    assert controller.suction(True)
    controller.move_to(demo.bMe_place)
    controller.set_place_pose()
    controller.suction(False)
    controller.move_to(demo.check.check_bMe)
    controller.capture_check_view()
    detail = controller.state.detail
    assert "WARNING" in detail and "+10." in detail, detail


def test_capture_without_the_part_in_view_is_refused(controller):
    controller.begin_teach()
    controller.jog([0.0, 0.15, 0.0])  # look at the bare table
    with pytest.raises(CommandRefused, match="four corners"):
        controller.capture_desired()
    assert controller.state.teaching.missing[0] is TeachStep.DESIRED_IMAGE


def test_vservo_run_prints_one_json_object(tmp_path, capsys):
    code = main(["run", "--job", "demo", "--data", str(tmp_path), "--seed", "5", "--json"])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0
    assert summary["outcome"] == "placed"
    assert set(summary) >= {"outcome", "final_error_px", "placement_error_mm", "duration_s", "stages"}
    assert main(["run", "--job", "no-such-job", "--data", str(tmp_path)]) == 2
    assert "no job named 'no-such-job'" in capsys.readouterr().err


def test_the_servos_readout_gives_the_arm_models_joints_and_the_bending_keeps_the_safety_margin():
    """The JRC reports the flange alone: the joints the law's limit handling needs are the
    safety layer's model's, and the steps it bends stop outside [safety] joint_margin_deg."""
    config = load_cell()
    rig = simulated_rig(config, seed=3)
    try:
        rig.robot.connect()
        measurement = FlangeReadout(rig.robot).measure()
        assert np.all(np.isfinite(measurement.q))
        assert np.allclose(rig.robot.arm.fk(measurement.q), measurement.bMe, atol=1e-6)
    finally:
        rig.close()
    margin = replace(config.safety, joint_margin_rad=np.deg2rad(2.0))
    steps = joint_limited_steps(SafetyLayer(rig.robot.robot, margin, rig.robot.arm, config.home_q))
    assert steps.settings.margin_rad > margin.joint_margin_rad
    assert np.allclose(steps.upper, rig.robot.arm.upper - steps.settings.margin_rad)


def test_an_estop_pressed_as_the_start_pose_is_seen_ends_the_run_estopped_not_as_a_fault():
    """The hold refuses the servo goal's reach check that follows the frame: the run still
    ends by the e-stop, as the operator pressed it, not as a goal out of reach."""
    config = load_cell()
    job, _, _ = teach_demo_job(config)
    rig = simulated_rig(config, seed=0)
    rig.robot.connect()
    rig.robot.servo(True)
    pressed = threading.Event()
    camera = rig.perception()

    class EStopAtTheFirstFrame:
        def perceive(self, measurement, motion_ended_s):
            if not pressed.is_set():
                pressed.set()
                rig.robot.emergency_stop("pressed by the operator")
            return camera.perceive(measurement, motion_ended_s)

    outcome = run_assembly(
        job, rig.robot, rig.gripper, EStopAtTheFirstFrame(), config.nominal, rig.policy, estopped=pressed.is_set
    )
    assert pressed.is_set()
    assert outcome.outcome is Outcome.ESTOPPED and outcome.end is RunEnd.ESTOPPED
    assert rig.robot.status().held
