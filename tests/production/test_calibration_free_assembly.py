"""A cell whose truth is Table 5-5's errors away from its (nominal) cell file assembles a job
taught on it whatever the part's turn: the chain from the taught view to the release rests
on no calibration (core/production/grasp.py)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tests.controller_fixtures import simulated_controller
from vservo.core.cell.config import CellConfig, CommissioningRecord, load_cell, parse_cell, read_cell_data_with_truth
from vservo.core.geometry.spatial import inverse, rot_z, transform
from vservo.core.perception.features import ImageFeatures, pattern_scale
from vservo.core.production.assembly import Outcome, Phase
from vservo.core.production.cell_controller import CellController, CommandRefused
from vservo.core.production.cup_centring import CellMotions, CentringError, centre_cup
from vservo.core.production.demo_job import teach_demo_job
from vservo.core.production.part_view import ViewMotions, view_part
from vservo.core.production.placement_check import diagonals_crossing
from vservo.core.production.teaching_session import VIEW_SCALE

TABLE_5_5 = Path(__file__).resolve().parents[2] / "static" / "truths" / "table-5-5.toml"


@contextmanager
def viewing_the_guides_part(tmp_path: Path) -> Iterator[tuple[CellConfig, CellController]]:
    """A controller on the cell Table 5-5's errors from its file, teaching, the camera brought
    over the guide's part by View the part."""
    config = parse_cell(*read_cell_data_with_truth(None, TABLE_5_5))
    with simulated_controller(config, tmp_path / "data") as controller:
        controller.begin_teach()
        controller.present_part((-390.0, -40.0), 20.0)
        controller.view_part()
        yield config, controller


def cup_in_the_part_mm(config: CellConfig, controller: CellController) -> np.ndarray:
    """Where the cup truly is in the part's frame O (a top-face corner), mm: the test's gauge."""
    cell = controller.rig.cell
    return 1000.0 * (inverse(cell.state.scene.cube.bMo) @ cell.ground_truth_bMe() @ config.plant().truth.eMv)[:3, 3]


@pytest.mark.slow
def test_parts_turned_over_the_whole_circle_are_placed_within_a_few_tenths_of_a_millimetre(tmp_path):
    config = parse_cell(*read_cell_data_with_truth(None, TABLE_5_5))
    assert not np.allclose(config.plant().truth.eMc, config.nominal.eMc)  # the model is off
    job, image, check_image = teach_demo_job(config)  # taught on this cell, through its nominal model
    rng = np.random.default_rng(1)
    bMo = config.plant().scene.cube.bMo
    centre_mm = 1000.0 * (bMo @ np.array([0.01, 0.01, 0.0, 1.0]))[:2]
    yaw_deg = np.degrees(np.arctan2(bMo[1, 0], bMo[0, 0]))
    with simulated_controller(config, tmp_path / "data") as controller:
        controller.store.save_job(replace(job, name="turned"), image, check_image)
        outcomes = []
        for turn_deg in np.linspace(-180.0, 180.0, 8, endpoint=False) + rng.uniform(0.0, 45.0):
            offset_mm = rng.uniform(0.0, 30.0) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])
            if controller.state.phase == Phase.FAULT.value:
                controller.reset()
            controller.present_part(tuple(centre_mm + offset_mm), yaw_deg + turn_deg)
            controller.start("turned")
            controller.wait()
            outcomes.append((turn_deg, controller.last_outcome))
    placed = [outcome for _, outcome in outcomes if outcome.outcome is Outcome.PLACED]
    assert len(placed) >= 7, [(round(turn), outcome.reason) for turn, outcome in outcomes]
    for turn, outcome in outcomes:
        if outcome.outcome is Outcome.PLACED:
            assert outcome.gauge_inside and outcome.gauge_placement_error_mm < 0.3, (turn, outcome.reason)
        else:  # refused before the pick, saying what to do
            assert outcome.outcome is Outcome.FAULT and "refused before" in outcome.reason, (turn, outcome.reason)
            assert "present the part nearer its taught place" in outcome.reason


def test_the_demo_job_taught_on_the_shipped_cell_is_refused_before_moving_on_a_cell_never_commissioned(tmp_path):
    config = parse_cell(*read_cell_data_with_truth(None, TABLE_5_5))
    assert not config.model_measured and load_cell().model_measured
    with simulated_controller(config, tmp_path / "data") as controller:
        controller.present_part()
        before = controller.rig.robot.read_pose()
        with pytest.raises(CommandRefused, match="commission this cell .* or teach the job again on this cell"):
            controller.start("demo")
        np.testing.assert_array_equal(controller.rig.robot.read_pose(), before)
    commissioned = replace(config, commissioning=CommissioningRecord(None, {"date": "2026-11-28"}))
    assert commissioned.model_measured  # then the job is retargeted to the commissioned model instead


def test_present_part_brings_the_part_near_where_the_chosen_job_was_taught(controller):
    demo = controller.store.load_job("demo")
    # The demo job taught on a part 60 mm aside and turned 30 deg: every taught pose moved with it.
    part = controller.rig.cell.state.scene.cube
    centre = part.bMo @ transform(t=(0.01, 0.01, 0.0))
    moved = transform(rot_z(np.radians(30.0)), (-0.02, 0.057, 0.0))
    D = transform(t=centre[:3, 3] + moved[:3, 3]) @ transform(moved[:3, :3]) @ inverse(transform(t=centre[:3, 3]))
    aside = replace(demo, name="aside", taught_bMe=D @ demo.taught_bMe, start_bMe=D @ demo.start_bMe)
    controller.store.save_job(aside)
    taught_centre_mm = 1000.0 * (D @ centre)[:2, 3]
    for _ in range(5):
        controller.present_part(job="aside")
        bMo = controller.rig.cell.state.scene.cube.bMo
        offset_mm = 1000.0 * (bMo @ transform(t=(0.01, 0.01, 0.0)))[:2, 3] - taught_centre_mm
        assert np.all(np.abs(offset_mm) <= 15.0 + 1e-6), offset_mm  # the feeder's range about the job's part
        turn_deg = np.degrees(np.arctan2(bMo[1, 0], bMo[0, 0]) - np.arctan2(part.bMo[1, 0], part.bMo[0, 0])) - 30.0
        assert abs((turn_deg + 180.0) % 360.0 - 180.0) <= 20.0 + 0.1, turn_deg
    with pytest.raises(CommandRefused, match="nothing"):
        controller.present_part(job="nothing")


def test_view_the_part_and_centre_the_cup_rest_on_no_calibration(tmp_path):
    """On the cell Table 5-5's errors from its model: the camera brought over the part by the
    image alone, the spot on its centre; the cup put on the middle of its top face by the camera
    and the vacuum sensor, where the model's "Cup on it" would miss the part."""
    with viewing_the_guides_part(tmp_path) as (config, controller):
        cell = controller.rig.cell
        features = controller.look(fresh=True)[1]
        assert features.all_corners_visible and features.spot_seen
        crossing = diagonals_crossing(features.corners_px)
        assert np.linalg.norm(crossing - features.laser_spot_px) < 1.0  # the spot on the part's centre
        controller.capture_desired()
        controller.centre_cup()
        assert "cup centred on the part" in controller.state.detail
        cup_mm = cup_in_the_part_mm(config, controller)
        np.testing.assert_allclose(cup_mm[:2], [10.0, 10.0], atol=0.5)  # the top face's centre
        assert -6.0 < cup_mm[2] < 0.0  # pressed into the compensator, within its stroke
        assert not controller.state.holding_part and controller.test_pick()
        # The model's own cup pose for the part it sees is off the part.
        seen = controller.state.teaching
        assert seen is not None and not seen.model_measured
        bMo_model = controller._teaching.draft.seen_bMo
        model_cup = inverse(cell.state.scene.cube.bMo) @ bMo_model @ transform(t=(0.01, 0.01, 0.0))
        assert np.linalg.norm(model_cup[:2, 3] - [0.01, 0.01]) > 0.01
        controller.move_to(
            cell.ground_truth_bMe() @ transform(t=(0.0, 0.0, -0.03))
        )  # 30 mm up the tool's z: the part out of reach
        with pytest.raises(CommandRefused, match="four corners|felt no part"):
            controller.present_part((-300.0, 150.0), 0.0)
            controller.centre_cup()


@pytest.mark.slow
def test_centring_on_frames_that_lag_the_arm_refuses_and_says_so_with_the_arm_back_at_the_view(tmp_path):
    """A camera one look behind the arm (a busy host's late frames, docs/vision.md): the part
    seems not to move as the arm jogs, and centring must say so, not fail inside its
    arithmetic or drive the arm to a pose made from those frames."""
    with viewing_the_guides_part(tmp_path) as (config, controller):
        bMe_view = controller.rig.robot.read_pose()
        looks = []

        def one_look_behind() -> np.ndarray:
            looks.append(controller.look(fresh=True)[1].corners_px)
            return looks[-2] if len(looks) > 1 else looks[-1]

        motions = CellMotions(controller.move_to, controller.rig.robot.read_pose, one_look_behind, lambda: False)
        with pytest.raises(CentringError, match="frames lag the arm"):
            centre_cup(motions, config.nominal.eMv, config.nominal.eMc)
        np.testing.assert_allclose(controller.rig.robot.read_pose(), bMe_view, atol=1e-6)


def test_centring_looks_again_when_its_first_jog_was_seen_on_a_late_frame_and_puts_the_cup_on_the_part(tmp_path):
    """The look after the first jog hands over the frame from before it (a busy host's): the
    part seems not to move, and the measurement is made again from the view, not refused.
    Without a late frame it is made twice, and the two agree."""
    with viewing_the_guides_part(tmp_path) as (config, controller):
        looks = []

        def late_once() -> np.ndarray:
            looks.append(controller.look(fresh=True)[1].corners_px)
            return looks[0] if len(looks) == 2 else looks[-1]

        motions = CellMotions(controller.move_to, controller.rig.robot.read_pose, late_once, controller._teaching._grips)
        centre_cup(motions, config.nominal.eMv, config.nominal.eMc)
        # the first stopped after its jogs; two more agreed (each: the view, two jogs, two turns, a descent)
        assert len(looks) == 3 + 6 + 6
        np.testing.assert_allclose(cup_in_the_part_mm(config, controller)[:2], [10.0, 10.0], atol=0.5)  # the face's centre


@pytest.mark.parametrize("late", [1, 2, 3, 5])
def test_view_the_part_looks_again_at_a_frame_from_before_a_jog_and_brings_the_spot_onto_the_part(tmp_path, late):
    """One frame late (a busy host's, docs/vision.md): the look after a jog (the first, the
    second, the third, or after the first step) hands over the frame of the look before it.
    Before, the jog then seemed not to move the part and its Jacobian was singular (a
    LinAlgError from the page's View the part); now the aid looks again."""
    config = parse_cell(*read_cell_data_with_truth(None, TABLE_5_5))
    with simulated_controller(config, tmp_path / "data") as controller:
        controller.begin_teach()
        controller.present_part((-390.0, -40.0), 20.0)
        looks = []

        def once_late() -> ImageFeatures:
            looks.append(controller.look(fresh=True)[1])
            return looks[-2] if len(looks) == late + 1 else looks[-1]

        k = config.nominal.camera.intrinsics
        demo = controller.store.load_job("demo")
        motions = ViewMotions(controller.move_to, controller.rig.robot.read_pose, once_late)
        view_part(motions, VIEW_SCALE * pattern_scale(demo.desired.corners_px), np.array([k.u0, k.v0]))
        features = controller.look(fresh=True)[1]
        assert features.all_corners_visible and features.spot_seen
        assert np.linalg.norm(diagonals_crossing(features.corners_px) - features.laser_spot_px) < 1.0
