"""The simulated cell: measurements come from the truth, readouts from the nominal model."""

import tomllib
from dataclasses import replace
from importlib import resources

import cv2
import numpy as np
import pytest

from vservo.core.cell.config import StepPolicyKind, load_cell, parse_cell
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.spatial import Pose6, exp_twist, inverse, matrix_from_pose, pose_error, transform, twist_transform
from vservo.core.robot.commands import PositionCommand, VelocityCommand
from vservo.core.servo.step_policy import DividedPositionStep, IntegratedVelocity, LargestSafeStep, step_policy_from_config
from vservo.core.sim.plant import IK_TOLERANCE_M, SimulatedCell

# Task 1 of Table 5-1: cube 162 mm in front of the camera, centred near the laser spot.
TEACH_cMo = matrix_from_pose(Pose6(0.011, -0.01, 0.162, np.pi, 0.0, -np.pi))


def cell_data(**simulation) -> dict:
    data = tomllib.loads(resources.files("vservo.static").joinpath("cell.toml").read_text())
    data["simulation"].update(simulation)
    return data


def at_teach_pose(data: dict, seed: int | None = None) -> SimulatedCell:
    config = parse_cell(data)
    cell = SimulatedCell(config, seed)
    bMc = config.simulation.scene.cube.bMo @ inverse(TEACH_cMo)
    cell.execute(PositionCommand(bMc @ inverse(config.nominal.eMc), 0.05, 0.0))
    return cell


def project_with_opencv(camera, cMb, points_b):
    """An independent projection of base-frame points through a camera at cMb."""
    rvec, _ = cv2.Rodrigues(cMb[:3, :3])
    uv, _ = cv2.projectPoints(points_b, rvec, cMb[:3, 3], camera.intrinsics.K, camera.distortion.as_opencv())
    return uv.reshape(-1, 2)


def test_corners_are_seen_through_the_true_camera_not_the_nominal_one():
    data = cell_data(
        truth={
            "camera": {"principal_point_px": [326.0, 228.0], "distortion": [-0.2, 0.05, 0.001, -0.001, 0.0]},
            "hand_eye": {"eMc": [2.0, -1.0, 3.0, 0.5, -0.4, 1.0]},
        }
    )
    cell = at_teach_pose(data)
    seen = cell.measure()
    truth = cell.truth
    bMc_true = cell.ground_truth_bMe() @ truth.model.eMc
    expected = project_with_opencv(truth.model.camera, inverse(bMc_true), cell.state.scene.cube.corners_b)
    assert np.allclose(seen.corners_px, expected, atol=1e-9)
    # What the nominal model would predict differs by pixels: the control law cannot read the truth.
    config = parse_cell(data)
    bMc_nominal = seen.bMe @ config.nominal.eMc
    nominal = project_with_opencv(config.nominal.camera, inverse(bMc_nominal), cell.state.scene.cube.corners_b)
    assert np.abs(nominal - seen.corners_px).max() > 3.0


def test_the_robot_reports_its_nominal_pose_while_the_true_arm_is_elsewhere():
    data = cell_data(joint_placement_error_mm=0.5, joint_placement_error_deg=0.05)
    cell = at_teach_pose(data)
    seen = cell.measure()
    assert np.allclose(seen.bMe, cell.jrc_arm.fk(seen.q), atol=1e-12)
    translation, rotation = pose_error(seen.bMe, cell.ground_truth_bMe())
    assert 1e-4 < translation < 0.02 and rotation > 1e-5


def test_laser_spot_is_where_the_true_beam_meets_the_cube():
    cell = at_teach_pose(cell_data())
    seen = cell.measure()
    bMc = cell.ground_truth_bMe() @ cell.truth.model.eMc
    beam = cell.truth.model.laser.beam(bMc)
    top = cell.state.scene.cube.bMo
    # The top face is the plane z = 0 of O: intersect the beam with it directly.
    distance = beam.intersect_plane(top[:3, 2], float(top[:3, 2] @ top[:3, 3]))
    expected = project_with_opencv(cell.truth.model.camera, inverse(bMc), beam.point_at(distance)[None, :])[0]
    assert np.allclose(seen.laser_spot_px, expected, atol=1e-9)
    assert np.allclose(seen.laser_spot_px, [327.2, 240.0], atol=0.1)  # docs/thesis-notes.md section 4


def test_nominal_triangulation_is_exact_only_when_the_laser_is_calibrated():
    exact = at_teach_pose(cell_data())
    config = parse_cell(cell_data())
    depth = config.nominal.laser.triangulate(config.nominal.camera, exact.measure().laser_spot_px)
    assert depth.depth_m == pytest.approx(exact.ground_truth_cMo()[2, 3], abs=1e-8)

    miscalibrated = at_teach_pose(cell_data(truth={"laser": {"cMl": [30.0, 0.0, 0.0, 0.0, -12.0, 0.0]}}))
    depth = config.nominal.laser.triangulate(config.nominal.camera, miscalibrated.measure().laser_spot_px)
    assert abs(depth.depth_m - miscalibrated.ground_truth_cMo()[2, 3]) > 0.005


def test_velocity_command_integrates_the_twist_exactly():
    cell = at_teach_pose(cell_data())
    before = cell.measure()
    eVe = np.array([0.01, -0.02, 0.005, 0.05, -0.1, 0.2])
    report = cell.execute(IntegratedVelocity(0.1).command(before.bMe, eVe))
    after = cell.measure()
    assert np.allclose(after.bMe, before.bMe @ exp_twist(eVe * 0.1), atol=IK_TOLERANCE_M)
    assert after.time_s - before.time_s == pytest.approx(0.1) == report.duration_s


def test_jrc_style_steps_move_a_divided_step_per_sampling_period():
    cell = at_teach_pose(cell_data())
    policy = DividedPositionStep(divide_factor=50.0, sampling_period_s=2.0, speed_m_s=0.05)
    cVc = np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.2])
    eVe = twist_transform(np.eye(4)) @ cVc
    before = cell.measure()
    command = policy.command(before.bMe, eVe)
    assert np.allclose(command.bMe_target, before.bMe @ exp_twist(eVe / 50.0))
    cell.execute(command)
    after = cell.measure()
    assert np.allclose(after.bMe, command.bMe_target, atol=IK_TOLERANCE_M)
    assert np.linalg.norm(after.bMe[:3, 3] - before.bMe[:3, 3]) == pytest.approx(0.001, rel=1e-3)
    # A 1 mm step takes 20 ms at 50 mm/s: the sampling period sets the pace.
    assert after.time_s - before.time_s == pytest.approx(2.0)
    # A long move outlasts the period.
    far = PositionCommand(after.bMe @ transform(t=(0.0, 0.0, -0.15)), 0.05, 2.0)
    assert cell.execute(far).duration_s == pytest.approx(3.0)


def test_fast_steps_move_the_whole_correction_within_the_step_limits_with_no_sampling_wait():
    cell = at_teach_pose(cell_data())
    policy = LargestSafeStep(max_step_m=0.04, max_step_rad=np.radians(10.0), speed_m_s=0.1)
    before = cell.measure()
    # Near the goal the whole correction, unscaled: the fine steps of the end.
    small = np.array([0.002, -0.001, 0.003, 0.01, 0.0, -0.02])
    command = policy.command(before.bMe, small)
    assert np.allclose(command.bMe_target, before.bMe @ exp_twist(small))
    assert command.period_s == 0.0 and command.speed_m_s == 0.1
    # Far from it, scaled as a whole (its direction kept) to the limit it reaches first.
    for far, limited_by in (
        (np.array([0.0, 0.08, 0.06, 0.0, 0.0, 0.05]), "translation"),
        (np.array([0.0, 0.0, 0.01, 0.0, 0.0, np.radians(40.0)]), "rotation"),
    ):
        command = policy.command(before.bMe, far)
        scale = 0.04 / 0.1 if limited_by == "translation" else 0.25
        assert np.allclose(command.bMe_target, before.bMe @ exp_twist(scale * far)), limited_by
        translation, rotation = pose_error(before.bMe, command.bMe_target)
        assert translation <= 0.04 + 1e-12 and rotation <= np.radians(10.0) + 1e-12
    # A zero twist stays put.
    assert np.allclose(policy.command(before.bMe, np.zeros(6)).bMe_target, before.bMe)
    # The move takes its own time at its speed, not a sampling period.
    report = cell.execute(policy.command(before.bMe, np.array([0.03, 0.0, 0.0, 0.0, 0.0, 0.0])))
    assert report.duration_s == pytest.approx(0.3)


def test_the_cell_file_chooses_the_step_policy():
    motion = load_cell().motion
    assert step_policy_from_config(motion) == LargestSafeStep(0.04, np.radians(10.0), 0.1)
    assert step_policy_from_config(replace(motion, policy=StepPolicyKind.THESIS)) == DividedPositionStep(50.0, 2.0, 0.05)
    assert step_policy_from_config(replace(motion, mode="velocity")) == IntegratedVelocity(0.05)


def test_an_unreachable_target_leaves_the_arm_where_it_was():
    cell = at_teach_pose(cell_data())
    before = cell.measure()
    with pytest.raises(UnreachableTarget):
        cell.execute(PositionCommand(before.bMe @ transform(t=(0.0, 0.0, -1.5)), 0.05, 2.0))
    after = cell.measure()
    assert np.array_equal(after.q, before.q) and after.time_s == before.time_s


def test_noise_is_seeded_and_has_the_configured_spread():
    data = cell_data(pixel_noise_px=0.5)
    first = at_teach_pose(data, seed=7)
    again = at_teach_pose(data, seed=7)
    other = at_teach_pose(data, seed=8)
    a, b, c = first.measure(), again.measure(), other.measure()
    assert np.array_equal(a.corners_px, b.corners_px) and np.array_equal(a.laser_spot_px, b.laser_spot_px)
    assert not np.array_equal(a.corners_px, c.corners_px)

    clean = at_teach_pose(cell_data()).measure().corners_px
    errors = np.concatenate([first.measure().corners_px - clean for _ in range(300)])
    assert np.std(errors) == pytest.approx(0.5, rel=0.1)
    assert abs(np.mean(errors)) < 0.05


def test_repeatability_moves_the_true_flange_but_not_the_readout():
    cell = at_teach_pose(cell_data(repeatability_mm=0.02, repeatability_deg=0.001))
    offsets = []
    for _ in range(50):
        seen = cell.measure()
        cell.execute(VelocityCommand(np.zeros(6), 0.1))
        offsets.append(pose_error(seen.bMe, cell.ground_truth_bMe())[0])
        assert np.allclose(cell.measure().bMe, seen.bMe, atol=1e-12)
    # Three axes of 0.02 mm sigma: about 0.03 mm on average.
    assert 1e-5 < np.mean(offsets) < 6e-5


def test_corners_outside_the_image_are_not_measured():
    cell = at_teach_pose(cell_data())
    # Slide the camera 150 mm along base Y (the half field of view is 64 mm here): the cube leaves the view.
    bMe = cell.measure().bMe
    cell.execute(PositionCommand(transform(t=(0.0, 0.15, 0.0)) @ bMe, 0.05, 0.0))
    seen = cell.measure()
    assert not seen.corners_visible.any()
    assert np.isnan(seen.corners_px).all()
    # The laser still hits the table and is seen.
    assert seen.laser_visible
