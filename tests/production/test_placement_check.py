"""Placement checked by vision: the product's own measure of where a placed part lies,
against the simulated cell's gauge (its truth), on the real camera pipeline."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vservo.core.cell.config import load_cell
from vservo.core.cell.scene import Cube
from vservo.core.geometry.spatial import Pose6, inverse, matrix_from_pose, transform
from vservo.core.production.assembly import Outcome
from vservo.core.production.cell_controller import CellController, CommandRefused
from vservo.core.production.jobs import job_from_dict
from vservo.core.production.placement_check import CheckView, check_placement
from vservo.core.production.protocol import TeachStep
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import Store

SEEDS = range(8)
AGREEMENT_MM = 0.1


def controller_for(tmp_path, seed: int) -> CellController:
    return CellController(simulated_rig(load_cell(), seed=seed, backend="sim"), Store(tmp_path / f"data{seed}"), seed=seed)


def close(controller: CellController) -> None:
    controller.close()
    controller.store.close()


def run(controller: CellController, job: str = "demo", on_state=None):
    if on_state is not None:
        controller.state_subscribers.append(on_state)
    controller.present_part()
    controller.start(job)
    controller.wait()
    return controller.last_outcome


def placed_in_pocket(controller: CellController, offset_m=(0.0, 0.0)):
    """The part's pose with its bottom on the pocket floor, centred but for offset_m (pocket x, y)."""
    scene = controller.rig.cell.state.scene
    side = scene.cube.side_m
    return scene.metal_part.bMp @ transform(t=(offset_m[0] - side / 2, offset_m[1] - side / 2, side))


# -- the measure itself, on projected corners ---------------------------------------------------


def test_the_check_measures_a_shift_in_the_top_plane_exactly_under_perspective():
    """A camera tilted 12 deg off the face's normal: the homography keeps millimetres
    where a single mm-per-px scale would be off by the perspective."""
    camera = load_cell().nominal.camera
    side = 0.020
    corners_o = Cube(np.eye(4), side).corners_o
    cMo = matrix_from_pose(Pose6(-0.01, 0.005, 0.17, np.pi + np.deg2rad(12.0), np.deg2rad(5.0), 0.3))

    def seen(oMo_shifted):
        cP = (corners_o @ oMo_shifted[:3, :3].T + oMo_shifted[:3, 3]) @ cMo[:3, :3].T + cMo[:3, 3]
        return camera.project(cP)

    check = CheckView(np.eye(4), seen(np.eye(4)))
    assert check_placement(check, seen(np.eye(4)), camera, side).error_mm == pytest.approx(0.0, abs=1e-6)
    centre = transform(t=(side / 2, side / 2, 0.0))
    turned = centre @ matrix_from_pose(Pose6(0.0, 0.0, 0.0, 0.0, 0.0, 0.2)) @ inverse(centre)
    for shift_m in ((0.0007, 0.0), (0.0003, -0.0012)):
        result = check_placement(check, seen(transform(t=(*shift_m, 0.0)) @ turned), camera, side)
        assert result.found
        np.testing.assert_allclose(result.offset_mm, 1000.0 * np.array(shift_m), atol=1e-6)
    # The same corners in another cyclic order (another first corner, the other winding): same figure.
    shifted = seen(transform(t=(0.0007, 0.0003, 0.0)))
    reordered = CheckView(np.eye(4), check.corners_px[[2, 1, 0, 3]])
    assert check_placement(reordered, shifted, camera, side).error_mm == pytest.approx(np.hypot(0.7, 0.3), abs=1e-6)
    # Out of order round the face (corners 1 and 2 swapped, as a tracker may hand them over
    # after the part turned): still the diagonals' crossing, the same figure.
    assert check_placement(check, shifted[[0, 2, 1, 3]], camera, side).error_mm == pytest.approx(np.hypot(0.7, 0.3), abs=1e-6)
    unseen = shifted.copy()
    unseen[1] = np.nan
    assert not check_placement(check, unseen, camera, side).found


# -- on the simulated cell, against its gauge --------------------------------------------------


def test_the_vision_figure_agrees_with_the_gauge_within_a_tenth_of_a_millimetre(tmp_path):
    differences = []
    for seed in SEEDS:
        controller = controller_for(tmp_path, seed)
        try:
            outcome = run(controller)
        finally:
            close(controller)
        assert outcome.outcome is Outcome.PLACED, (seed, outcome.reason)
        assert outcome.gauge_inside and "seen" in outcome.reason
        differences.append(outcome.placement_error_mm - outcome.gauge_placement_error_mm)
    print(f"vision - gauge over seeds {list(SEEDS)}: {np.round(differences, 4).tolist()} mm")
    assert np.max(np.abs(differences)) < AGREEMENT_MM


def test_a_part_moved_after_the_release_is_measured_where_it_lies_and_missed_beyond_tolerance(tmp_path):
    """Between the release and the look from the check pose the part is pushed to 0.7 mm
    off the pocket's centre: still in the pocket (the gauge says inside), beyond a 0.5 mm
    tolerance, and the camera measures the 0.7 mm."""
    controller = controller_for(tmp_path, 1)
    try:
        demo = controller.store.load_job("demo")
        controller.store.save_job(replace(demo, name="tight", placement_tolerance_mm=0.5))
        bMo_pushed = placed_in_pocket(controller, (0.0007, 0.0))

        def push(state):
            if state.detail.startswith("looking at the placed part"):
                controller.rig.cell.place_cube(bMo_pushed)

        outcome = run(controller, "tight", push)
    finally:
        close(controller)
    assert outcome.outcome is Outcome.MISSED, outcome.reason
    assert "beyond the 0.5 mm tolerance" in outcome.reason
    assert outcome.gauge_inside and outcome.gauge_placement_error_mm == pytest.approx(0.7, abs=1e-6)
    assert outcome.placement_error_mm == pytest.approx(0.7, abs=AGREEMENT_MM)
    assert outcome.summary()["placement_error_mm"] == round(outcome.placement_error_mm, 4)


def test_a_part_gone_from_the_pocket_is_missed_as_not_found(tmp_path):
    controller = controller_for(tmp_path, 2)
    try:

        def knock_away(state):
            if state.detail.startswith("looking at the placed part"):
                controller.rig.cell.place_cube(controller.rig.config.simulation.scene.cube.bMo)  # back on the table

        outcome = run(controller, on_state=knock_away)
    finally:
        close(controller)
    assert outcome.outcome is Outcome.MISSED
    assert outcome.reason == "part not found at the check pose"
    assert outcome.summary()["placement_error_mm"] is None and outcome.gauge_inside is False


def test_a_version_1_job_still_runs_with_its_placement_unknown_to_vision(tmp_path):
    controller = controller_for(tmp_path, 4)
    try:
        data = controller.store.load_job("demo").as_dict()
        data.update(version=1, name="old")
        del data["check"], data["placement_tolerance_mm"]
        controller.store.save_job(job_from_dict(data, "old.json"))
        outcome = run(controller, "old")
    finally:
        close(controller)
    assert outcome.outcome is Outcome.PLACED, outcome.reason
    assert outcome.placement_error_mm is None
    assert outcome.gauge_inside and outcome.gauge_placement_error_mm < 1.0  # the gauge still decides here
    assert "(gauge)" in outcome.reason


# -- teaching ----------------------------------------------------------------------------------


def test_teaching_captures_the_check_view_over_the_placed_part(tmp_path):
    controller = controller_for(tmp_path, 5)
    try:
        demo = controller.store.load_job("demo")
        cell = controller.rig.cell
        controller.begin_teach("demo")
        assert controller.state.teaching.optional_missing == (TeachStep.CHECK_VIEW,)
        controller.move_to(demo.check.check_bMe)
        with pytest.raises(CommandRefused, match="four top-face corners"):
            controller.capture_check_view()  # the part is still on the table
        bMo_table = cell.state.scene.cube.bMo
        cell.place_cube(placed_in_pocket(controller))
        check = controller.capture_check_view()
        np.testing.assert_allclose(check.corners_px, demo.check.corners_px, atol=0.05)
        assert controller.state.teaching.optional_missing == ()
        cell.place_cube(bMo_table)
        controller.move_to(demo.taught_bMe)
        controller.capture_desired()
        controller.save_job("checked")
        saved = controller.store.load_job("checked")
        np.testing.assert_allclose(saved.check.check_bMe, demo.check.check_bMe, atol=1e-4)
        assert controller.store.job_image("checked", check=True).shape == (480, 640)
        outcome = run(controller, "checked")
    finally:
        close(controller)
    assert outcome.outcome is Outcome.PLACED, outcome.reason
    assert abs(outcome.placement_error_mm - outcome.gauge_placement_error_mm) < AGREEMENT_MM
