"""Teaching against the cell file's metal part: the pocket pose offered, and the place
check said at the place step (how far off and how turned every run will set the part down),
on the simulated cell with the real camera pipeline."""

from __future__ import annotations

import numpy as np
import pytest

from vservo.app.scene3d import part_pose_from_corners
from vservo.app.teach_panel import above_pocket, cup_on_part, view_over_part
from vservo.core.cell.config import ConfigError, parse_cell, read_cell_data
from vservo.core.cell.scene import MetalPart
from vservo.core.geometry.spatial import Pose6, inverse, matrix_from_pose, rot_z, transform
from vservo.core.production.cell_controller import CellController
from vservo.core.production.pocket import flange_in_pocket, pocket_fit

SIDE_M = 0.020


def test_a_quarter_turned_part_fits_the_pocket_and_a_few_degrees_do_not():
    pocket = MetalPart(matrix_from_pose(Pose6(-0.4, 0.12, -0.165, np.deg2rad(30.0), 0.0, 0.0)))
    centred = pocket.bMp @ transform(t=(-SIDE_M / 2, -SIDE_M / 2, SIDE_M))
    about_centre = transform(t=(SIDE_M / 2, SIDE_M / 2, 0.0))
    for quarter in range(4):
        turned = centred @ about_centre @ transform(rot_z(quarter * np.pi / 2)) @ inverse(about_centre)
        fit = pocket_fit(turned, pocket, SIDE_M)
        assert abs(fit.turn_deg) < 1e-9 and fit.offset_mm < 1e-9 and abs(fit.height_mm) < 1e-9
    off = transform(t=(0.0005, 0.0, 0.002)) @ centred @ about_centre @ transform(rot_z(np.deg2rad(93.0))) @ inverse(about_centre)
    fit = pocket_fit(off, pocket, SIDE_M)
    assert fit.turn_deg == pytest.approx(3.0) and fit.offset_mm == pytest.approx(0.5) and fit.height_mm == pytest.approx(2.0)
    # The flange that sets a held part in the pocket does so in the quarter turn nearest the part's.
    eMo = transform(rot_z(0.3), (0.01, 0.0, -0.2))
    bMe = flange_in_pocket(eMo, pocket, SIDE_M, bMo_now=off)
    assert pocket_fit(bMe @ eMo, pocket, SIDE_M).offset_mm < 1e-9
    np.testing.assert_allclose((bMe @ eMo)[:3, :3], (pocket.bMp @ transform(rot_z(np.pi / 2)))[:3, :3], atol=1e-12)


def test_a_metal_part_whose_pocket_does_not_open_up_is_refused_by_name():
    data, _ = read_cell_data()
    data["metal_part"] = {"pose": [-400.0, 120.0, -165.0, 0.0, 10.0, 0.0]}
    with pytest.raises(ConfigError, match=r"metal_part\.pose = .*opens straight up"):
        parse_cell(data, "bent.toml")


def teach_up_to_the_pick(controller: CellController) -> None:
    """A new job: a part presented 40 mm from the demo's, viewed, picked and on the cup."""
    config = controller.rig.config
    eMc, camera = config.nominal.eMc, config.nominal.camera

    def part_seen():
        _, features = controller.look(fresh=True)
        return part_pose_from_corners(features.corners_px, controller.rig.robot.read_pose(), eMc, camera, SIDE_M)

    controller.begin_teach(None)
    controller.present_part([-390.0, -40.0], 0.0)
    controller.move_to(view_over_part(part_seen(), eMc))
    controller.capture_desired()
    controller.move_to(cup_on_part(part_seen()) @ inverse(config.nominal.eMv))
    controller.set_pick_pose()
    controller.suction(True)
    controller.jog([0.0, 0.0, 0.04])


def test_the_pocket_pose_offered_sets_the_part_in_the_pocket_and_the_place_step_says_so(controller):
    teach_up_to_the_pick(controller)
    assert controller.state.teaching.place_bMo is None
    pocket_bMe = controller.state.teaching.pocket_bMe
    controller.move_to(above_pocket(pocket_bMe))
    controller.move_to(pocket_bMe)
    controller.set_place_pose()
    detail = controller.state.detail
    assert "WARNING" not in detail and "the part sits 0.0 mm and +0.0 deg from the pocket's centre" in detail, detail
    controller.suction(False)
    placed = controller.rig.cell.ground_truth_placement()
    assert placed.inside and np.linalg.norm(placed.offset_m) < 2e-4, placed


def test_a_place_that_turns_the_part_from_the_pocket_is_warned_at_the_place_step(controller):
    teach_up_to_the_pick(controller)
    controller.move_to(controller.state.teaching.pocket_bMe)
    controller.jog([0.0, 0.0, 0.0], [0.0, 0.0, np.deg2rad(6.0)])  # the wrist turned 6 deg about the vertical
    controller.set_place_pose()
    detail = controller.state.detail
    assert "WARNING" in detail and "turned +6.0 deg from how it must sit in the pocket" in detail, detail
    assert controller.state.teaching.place_bMo is not None  # drawn as an outline over the pocket
