"""The laser law robust to calibration error (core/servo/laws/robust_laser_ibvs.py) beside the
thesis's: which runs where, what it changes, and the scenes and readings the thesis's law fails.

The failing runs of the thesis's law are asserted too: they are why the robust law exists, and
a change that made the thesis's law pass them would change the study's reproduction."""

import json
from dataclasses import replace

import numpy as np
import pytest

from tests.app.test_cli import run
from tests.servo_fixtures import CAMERA, DESIRED_cMo, desired_image, features, project
from vservo.core.cell.config import ConfigError, load_cell
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import exp_twist, inverse, matrix_from_pose, transform
from vservo.core.perception.features import laser_depth, polygon_moments
from vservo.core.production.jobs import JobError, job_from_dict, read_job_file
from vservo.core.production.storage import DEMO_JOB, shipped_job_path
from vservo.core.servo.laws.base import ControlOutput, Failure, Stage
from vservo.core.servo.laws.laser_ibvs import LaserIbvs
from vservo.core.servo.laws.robust_laser_ibvs import RobustLaserIbvs, view_spread_rad
from vservo.core.servo.loop import LoopLimits, RetreatTest
from vservo.core.servo.methods import LaserLaw, LawSettings, build_law
from vservo.core.sim import Arm
from vservo.core.study.montecarlo import run_sample
from vservo.core.study.replay import replay
from vservo.core.study.run import RunSettings
from vservo.core.study.simulate import simulate, study_cell
from vservo.core.study.tasks import Table53Reading

LASER = LaserPointer.in_plane(0.030, np.radians(80.0))
TABLE_5_5 = "static/truths/table-5-5.toml"


def test_the_study_runs_the_thesis_law_and_a_job_the_robust_one():
    model = load_cell().nominal
    assert type(build_law(model, LawSettings())) is LaserIbvs  # the study's reproduction
    assert RunSettings().laser_law is LaserLaw.THESIS
    assert type(build_law(model, LawSettings(laser_law=LaserLaw.ROBUST))) is RobustLaserIbvs
    demo = read_job_file(shipped_job_path(DEMO_JOB))
    assert demo.laser_law is LaserLaw.ROBUST  # a job file without the key: the product's default
    data = json.loads(json.dumps(demo.as_dict()))
    assert job_from_dict(data, "job.json").laser_law is LaserLaw.ROBUST
    data["laser_law"] = "thesis"
    assert job_from_dict(data, "job.json").laser_law is LaserLaw.THESIS
    data["laser_law"] = "fast"
    with pytest.raises(JobError, match="laser_law"):
        job_from_dict(data, "job.json")


def test_a_spot_the_wrong_model_cannot_triangulate_still_turns_stage_1():
    """Far along the beam the spot's viewing ray, through a model camera whose principal
    point is off, passes outside the model's beam: no depth. The thesis's law takes the spot
    for unseen and aims at the model's beam; the robust law turns by the spot's pixel (1.A)."""
    spot = np.array([143.0, 240.0])  # the beam's far end seen by Table 5-5's true camera
    assert np.isnan(laser_depth(LASER, CAMERA, spot))
    cMo = matrix_from_pose([0.015, -0.005, 0.3, np.pi - 0.3, 0.1, -np.pi + 0.1])
    seen = replace(features(project(cMo), spot_px=spot), laser_depth_m=laser_depth(LASER, CAMERA, spot))
    assert seen.spot_seen and not seen.laser_visible
    thesis = LaserIbvs(CAMERA, cTe=np.zeros(3), laser=LASER).step(seen, desired_image(), None)
    robust = RobustLaserIbvs(CAMERA, cTe=np.zeros(3), laser=LASER).step(seen, desired_image(), None)
    assert thesis.stage is Stage.CENTRE_1B and "not seen" in thesis.note
    assert robust.stage is Stage.ALIGN_1A and not robust.note


def test_the_view_spread_stays_when_the_camera_turns_in_place_where_the_area_does_not():
    corners = project(DESIRED_cMo)
    turned_cMo = inverse(exp_twist([0.0, 0.0, 0.0, 0.0, 0.35, 0.0])) @ DESIRED_cMo  # 20 deg about y
    turned = project(turned_cMo)
    assert polygon_moments(turned)[0] > 1.15 * polygon_moments(corners)[0]  # near the edge: 20 % larger
    assert view_spread_rad(CAMERA, turned) == pytest.approx(view_spread_rad(CAMERA, corners), rel=1e-9)
    law = RobustLaserIbvs(CAMERA, cTe=np.zeros(3), laser=LASER)
    away = transform(t=[0.0, 0.0, 0.1]) @ DESIRED_cMo  # 0.1 m further along the optical axis
    distance = law.distance_m(features(project(away)), desired_image())
    assert distance == pytest.approx(np.linalg.norm((away @ [0.01, 0.01, 0.0, 1.0])[:3]), rel=0.02)


def test_the_retreat_test_reads_the_laws_distance_when_it_gives_one():
    square = np.array([[300.0, 200.0], [400.0, 200.0], [400.0, 300.0], [300.0, 300.0]])
    test = RetreatTest(LoopLimits(), desired_area_px2=10000.0, desired_depth_m=0.162)

    def at(distance_m: float, corners=square) -> str | None:
        return test(features(corners), ControlOutput(np.zeros(6), Stage.FINISH_3, 1.0, 1.0, distance_m=distance_m))

    assert at(0.10) is None  # the first distance
    assert at(0.24) is None  # within 1.5 times the larger of the first and Z* (0.243 m)
    assert at(0.24, square * 0.5 + 150.0) is None  # a quarter of the area: no matter, the distance says
    assert "distance 244 mm, first 100 mm" in at(0.244)
    by_area = RetreatTest(LoopLimits(), desired_area_px2=10000.0, desired_depth_m=0.162)
    law_without = ControlOutput(np.zeros(6), Stage.IBVS, 1.0, 1.0)
    assert by_area(features(square), law_without) is None
    assert "corner area 2500" in by_area(features(square * 0.5 + 150.0), law_without)


def test_from_a_close_start_tilted_56_deg_with_one_corner_seen_the_robust_law_converges():
    """The thesis's law retreats there by the image area (the first area, of a face seen
    close and tilted, is far larger than the desired one); the robust law reads distance."""
    pose = np.array([0.0469, 0.0414, 0.0946, -1.7615, 0.106, 1.9016])  # 0.115 m from the face, 56 deg off its normal
    camera = load_cell().simulation.truth.camera
    assert camera.in_view(project(matrix_from_pose(pose), camera=camera)).sum() == 1
    thesis = simulate(initial=pose, arm=Arm.NONE)
    robust = simulate(initial=pose, arm=Arm.NONE, laser_law=LaserLaw.ROBUST)
    assert thesis.outcome.failure is Failure.CAMERA_RETREAT
    assert robust.outcome.converged, robust.outcome.reason
    assert robust.final_translation_m < 0.005


@pytest.mark.parametrize("reading", list(Table53Reading))
def test_task_2_converges_under_both_readings_of_table_5_3_with_the_robust_law(reading):
    robust = simulate(task_number=2, robust=reading, laser_law=LaserLaw.ROBUST)
    assert robust.outcome.converged, robust.outcome.reason
    assert robust.final_translation_m < 0.002 and robust.final_rotation_rad < np.radians(0.5)
    thesis = simulate(task_number=2, robust=reading)
    # The thesis's law: the reproduction's reading converges (Table 5-3), the other diverges in stage 3.
    assert thesis.outcome.converged == (reading is Table53Reading.REPRODUCTION)


def test_random_scenes_under_table_5_5s_errors_converge_with_the_robust_law():
    """Samples of the free camera's Monte Carlo (seed 0) the thesis's law loses under Table
    5-5's errors: the spot it cannot triangulate (0, 7) and stage 3 diverging (12)."""
    config = study_cell(None, None, TABLE_5_5)
    for index in (0, 7, 12):
        thesis = run_sample(config, RunSettings(arm=Arm.NONE), 0, index)
        robust = run_sample(config, RunSettings(arm=Arm.NONE, laser_law=LaserLaw.ROBUST), 0, index)
        assert not thesis.converged and robust.converged, (index, thesis, robust)


def test_a_study_cell_takes_a_truth_file_or_table_5_3_but_not_both():
    config = study_cell(None, None, TABLE_5_5)
    assert config.simulation.truth.camera.intrinsics.fx == pytest.approx(5.0 / 0.0074)
    assert config.nominal.camera.intrinsics.fx == pytest.approx(6.0 / 0.0074)  # the model is the cell file's
    other = study_cell(None, Table53Reading.OTHER, None)
    assert other.nominal.camera.intrinsics.u0 == 384.0 and other.simulation.truth.camera.intrinsics.u0 == 320.0
    with pytest.raises(ConfigError, match="not both"):
        study_cell(None, Table53Reading.OTHER, TABLE_5_5)
    result = run("montecarlo", "--n", "1", "--robust", "--truth", TABLE_5_5)
    assert result.returncode != 0 and len(result.stderr.strip().splitlines()) == 1 and "not both" in result.stderr


def test_a_recorded_run_of_the_robust_law_replays_with_it(tmp_path):
    recorded = simulate(task_number=2, arm=Arm.NONE, laser_law=LaserLaw.ROBUST, record_to=str(tmp_path / "run"))
    assert recorded.outcome.converged and Stage.APPROACH_2 not in recorded.trace.stages
    again = replay(tmp_path / "run")
    assert again["cycles"] == recorded.outcome.iterations
    assert again["stage_mismatches"] == 0 and again["twist_difference_max"] == 0.0
