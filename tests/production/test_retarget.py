"""Jobs that survive a recalibration, and the start pose for a part found elsewhere.

The recalibrated cell: eMc off by 10 mm and 3 deg, the focal length 4 % longer, the
principal point 12 px aside in u and v, the laser re-mounted 5 mm and 1.5 deg off. The
cell file's model is that truth, as a perfect commissioning leaves it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vservo.core.cell.config import CellConfig, CellModel, load_cell
from vservo.core.cell.scene import Cube
from vservo.core.geometry.camera import CameraModel, Intrinsics
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import exp_twist, inverse, rot_z, rotation_angle, transform
from vservo.core.production.assembly import Outcome
from vservo.core.production.cell_controller import CellController
from vservo.core.production.jobs import Job, JobError
from vservo.core.production.retarget import NOT_RETARGETED, RETARGETED, retarget, retarget_note, start_pose_for_part
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import Store


def moved(aMb: np.ndarray, mm: float, deg: float, along: tuple, about: tuple) -> np.ndarray:
    """aMb moved in its own frame by ``mm`` along ``along`` and turned ``deg`` about ``about``."""
    t = np.asarray(along, float) / np.linalg.norm(along) * mm / 1000.0
    w = np.asarray(about, float) / np.linalg.norm(about) * np.deg2rad(deg)
    return aMb @ exp_twist(np.concatenate([t, w]))


@pytest.fixture(scope="module")
def shipped() -> CellConfig:
    return load_cell()


@pytest.fixture(scope="module")
def recalibrated(shipped) -> CellModel:
    nominal = shipped.nominal
    k = nominal.camera.intrinsics
    camera = CameraModel(
        Intrinsics(1.04 * k.fx, 1.04 * k.fy, k.u0 + 12.0, k.v0 + 12.0, k.width, k.height), nominal.camera.distortion
    )
    return replace(
        nominal,
        camera=camera,
        eMc=moved(nominal.eMc, 10.0, 3.0, (1, 1, 0), (1, -1, 1)),
        laser=LaserPointer(moved(nominal.laser.cMl, 5.0, 1.5, (1, 1, 0), (0, 1, 0))),
    )


@pytest.fixture(scope="module")
def recalibrated_cell(shipped, recalibrated) -> CellConfig:
    """The shipped cell whose truth is the recalibrated model, and whose file says so."""
    return replace(shipped, nominal=recalibrated, simulation=replace(shipped.simulation, truth=recalibrated))


def part_pose_taught(job: Job) -> np.ndarray:
    return job.taught_bMe @ job.taught_model.eMc @ job.desired.cdMo


def test_on_the_cell_it_was_taught_on_the_job_is_run_unchanged(demo, shipped):
    assert demo.taught_model is not None
    assert retarget(demo, shipped.nominal) is demo
    assert retarget_note(demo, shipped.nominal) is None


def test_a_job_without_a_taught_model_runs_as_taught_and_says_so(demo, recalibrated):
    old = replace(demo, taught_model=None)
    assert retarget(old, recalibrated) is old
    assert retarget_note(old, recalibrated) == NOT_RETARGETED


def test_the_retargeted_job_is_the_taught_part_seen_through_the_new_model(demo, recalibrated):
    job = retarget(demo, recalibrated)
    assert retarget_note(demo, recalibrated) == RETARGETED
    cdMo = demo.desired.cdMo
    corners_c = Cube(np.eye(4), demo.part_side_m).corners_o @ cdMo[:3, :3].T + cdMo[:3, 3]
    assert np.allclose(job.desired.corners_px, recalibrated.camera.project(corners_c), atol=1e-9)
    assert np.min(np.linalg.norm(job.desired.corners_px - demo.desired.corners_px, axis=1)) > 10.0
    # The desired spot is where the new beam meets the top face, Z* its depth there.
    spot = recalibrated.laser.triangulate(recalibrated.camera, job.desired.laser_spot_px)
    assert spot.depth_m == pytest.approx(job.desired.depth_m, abs=1e-9) and spot.ray_gap_m < 1e-9
    assert (inverse(cdMo) @ np.append(spot.point_c, 1.0))[2] == pytest.approx(0.0, abs=1e-9)
    assert np.linalg.norm(job.desired.laser_spot_px - demo.desired.laser_spot_px) > 10.0
    assert np.allclose(job.desired.corner_depths_m, demo.desired.corner_depths_m)
    # The pick stays where it was on the part, and the part where it was in the cell.
    eMo_taught, eMo = demo.taught_model.eMc @ cdMo, recalibrated.eMc @ cdMo
    assert np.allclose(inverse(eMo) @ job.eMe_pick, inverse(eMo_taught) @ demo.eMe_pick, atol=1e-12)
    assert np.allclose(part_pose_taught(job), part_pose_taught(demo), atol=1e-12)
    for name in ("start_bMe", "bMe_place"):
        assert np.array_equal(getattr(job, name), getattr(demo, name))
    assert np.array_equal(job.check.check_bMe, demo.check.check_bMe)
    assert job.taught_model.matches(recalibrated)
    assert retarget(job, recalibrated) is job  # once is enough


def test_the_retargeted_views_are_what_the_recalibrated_cell_sees(demo, shipped, recalibrated_cell):
    """On the cell whose truth is the new model: the desired view from the retargeted
    taught pose, and the check view over the placed part, as its camera sees them."""
    job = retarget(demo, recalibrated_cell.nominal)
    rig = simulated_rig(recalibrated_cell, seed=5)
    try:
        rig.robot.connect()
        rig.robot.servo(True)
        rig.robot.move_linear(job.taught_bMe, 0.05)
        seen, _ = rig.extractor.extract(rig.camera.read_after(rig.robot.clock_s()).image)
        assert np.max(np.linalg.norm(seen.corners_px - job.desired.corners_px, axis=1)) < 1.0
        assert np.linalg.norm(seen.laser_spot_px - job.desired.laser_spot_px) < 1.0
        assert abs(seen.laser_depth_m - job.desired.depth_m) < 1e-3

        scene = shipped.simulation.scene
        side = scene.cube.side_m
        rig.cell.place_cube(scene.metal_part.bMp @ transform(t=(-side / 2, -side / 2, side)))  # as taught
        rig.robot.move_linear(job.check.check_bMe, 0.05)
        seen, _ = rig.extractor.extract(rig.camera.read_after(rig.robot.clock_s()).image)
        assert np.max(np.linalg.norm(seen.corners_px - job.check.corners_px, axis=1)) < 1.0
        assert np.max(np.linalg.norm(seen.corners_px - demo.check.corners_px, axis=1)) > 3.0
    finally:
        rig.close()


def run_once(config: CellConfig, job: Job, tmp_path, seed: int, bMo: np.ndarray | None = None):
    """One run of ``job`` on a new part: presented by the cell, or put at ``bMo`` by hand."""
    store = Store(tmp_path / f"data-{job.name}-{seed}")
    store.save_job(job)
    controller = CellController(simulated_rig(config, seed=seed), store, seed=seed)
    try:
        if bMo is None:
            controller.present_part()
        else:
            controller.rig.cell.place_cube(bMo)
        controller.start(job.name)
        controller.wait()
        return controller.last_outcome
    finally:
        controller.close()
        store.close()


def test_the_demo_job_taught_on_the_nominal_cell_is_placed_on_a_recalibrated_cell(demo, recalibrated_cell, tmp_path):
    outcome = run_once(recalibrated_cell, demo, tmp_path, seed=3)
    assert outcome.outcome is Outcome.PLACED, outcome.reason
    assert outcome.gauge_inside and outcome.gauge_placement_error_mm < 0.3
    assert outcome.placement_error_mm < 0.3
    assert outcome.summary()["notes"] == [RETARGETED]
    # The same job run as taught (a file without its model): the desired image the
    # recalibrated cell cannot reach.
    unretargeted = run_once(recalibrated_cell, replace(demo, name="as-taught", taught_model=None), tmp_path, seed=3)
    assert unretargeted.outcome is not Outcome.PLACED, unretargeted.reason
    assert unretargeted.summary()["notes"] == [NOT_RETARGETED]


def test_a_desired_view_the_new_laser_cannot_make_is_refused_naming_the_job(demo, recalibrated):
    away = replace(recalibrated, laser=LaserPointer(moved(recalibrated.laser.cMl, 30.0, 0.0, (1, 0, 0), (0, 0, 1))))
    with pytest.raises(JobError, match="'demo': this cell's laser beam misses the part's top face"):
        retarget(demo, away)


def test_the_start_pose_for_a_part_moves_with_the_part(demo):
    model = demo.taught_model
    bMo_taught = part_pose_taught(demo)
    assert np.allclose(start_pose_for_part(demo, model, bMo_taught), demo.start_bMe, atol=1e-12)
    centre = transform(t=(demo.part_side_m / 2, demo.part_side_m / 2, 0.0))
    for yaw_deg in (30.0, 100.0, -130.0, 180.0):
        bMo = transform(t=(0.04, -0.03, 0.0)) @ bMo_taught @ centre @ transform(rot_z(np.deg2rad(yaw_deg))) @ inverse(centre)
        bMe = start_pose_for_part(demo, model, bMo)
        # The start is the taught one turned with the part all the way (the mark numbers its corners).
        turned = bMo_taught @ centre @ transform(rot_z(np.deg2rad(yaw_deg))) @ inverse(centre)
        shift = transform(t=(0.04, -0.03, 0.0))
        assert np.allclose(bMe, shift @ turned @ inverse(bMo_taught) @ demo.start_bMe, atol=1e-12)
        assert np.degrees(rotation_angle(demo.start_bMe[:3, :3].T @ bMe[:3, :3])) == pytest.approx(abs(yaw_deg), abs=1e-9)


def test_a_part_found_far_from_its_taught_place_is_assembled_from_the_start_pose_moved_with_it(demo, shipped, tmp_path):
    """34 mm away and turned 100 deg (the part feeder's arrivals stay within 15 mm and 10 deg)."""
    centre = transform(t=(demo.part_side_m / 2, demo.part_side_m / 2, 0.0))
    bMo = (
        transform(t=(0.015, 0.03, 0.0))
        @ shipped.simulation.scene.cube.bMo
        @ centre
        @ transform(rot_z(np.deg2rad(100.0)))
        @ inverse(centre)
    )
    found = replace(demo, name="found", start_bMe=start_pose_for_part(demo, demo.taught_model, bMo))
    # This part is at the edge of the UPJ's reach: the servo ends where the taught grasp's
    # lifted pick is beyond it (joint 2 at its limit); one of its quarter-turned grasps is not.
    outcome = run_once(shipped, found, tmp_path, seed=4, bMo=bMo)
    assert outcome.outcome is Outcome.PLACED, outcome.reason
    assert outcome.gauge_inside and outcome.gauge_placement_error_mm < 0.5
    # The same part said to have no symmetry: the taught grasp alone, out of reach.
    taught_grasp_only = run_once(shipped, replace(found, name="asymmetric", grasp_symmetry=1), tmp_path, seed=4, bMo=bMo)
    assert taught_grasp_only.outcome is Outcome.FAULT
    assert "limit" in taught_grasp_only.reason


def test_from_the_start_pose_for_a_part_turned_a_quarter_the_camera_sees_what_it_saw_from_the_taught_start(demo, shipped):
    centre = transform(t=(demo.part_side_m / 2, demo.part_side_m / 2, 0.0))
    bMo_table = shipped.simulation.scene.cube.bMo
    bMo = transform(t=(-0.03, 0.02, 0.0)) @ bMo_table @ centre @ transform(rot_z(np.pi / 2)) @ inverse(centre)
    rig = simulated_rig(shipped, seed=6)
    try:
        rig.robot.connect()
        rig.robot.servo(True)
        views = []
        for part, start in ((bMo_table, demo.start_bMe), (bMo, start_pose_for_part(demo, demo.taught_model, bMo))):
            rig.cell.place_cube(part)
            rig.robot.move_linear(start, 0.05)
            seen, _ = rig.extractor.extract(rig.camera.read_after(rig.robot.clock_s()).image)
            views.append(seen)
    finally:
        rig.close()
    taught, found = views
    # The same four corners with the same numbers (the orientation mark turned with the
    # part and the camera) and the same spot: the servo has nothing to turn.
    assert np.all(np.linalg.norm(taught.corners_px - found.corners_px, axis=1) < 1.0)
    assert np.linalg.norm(taught.laser_spot_px - found.laser_spot_px) < 1.0
