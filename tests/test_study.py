"""The simulation study on the simulated cell: the pattern of Table 5-4, the failure
monitor, the command line, the Monte Carlo sampling and the report."""

import json
import subprocess
import sys
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from vservo.core.cell.config import load_cell
from vservo.core.geometry.spatial import inverse, pose_error
from vservo.core.servo.laws.base import ControlOutput, Failure
from vservo.core.servo.loop import LoopLimits, run_servo
from vservo.core.servo.step_policy import IntegratedVelocity
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.plant import SimulatedCell, visible_region
from vservo.core.study.montecarlo import DEPTH_RANGE_M, MAX_ROTATION_RAD, MAX_TRANSLATION_M, draw_initial_cMo, run_montecarlo
from vservo.core.study.report import reproduce
from vservo.core.study.run import RunSettings, run_task, teach
from vservo.core.study.simulate import simulate
from vservo.core.study.tasks import ROBUSTNESS_TASK, TASKS, THESIS_PATH_LENGTH_M


@pytest.fixture(scope="module")
def cell_config():
    return load_cell()


@pytest.fixture(scope="module")
def runs(cell_config):
    """Every task with every method, run once for the module."""
    return {
        (task, method): run_task(cell_config, TASKS[task], RunSettings(method=method))
        for task in TASKS
        for method in ("laser", "ibvs", "2.5d", "pbvs")
    }


def test_tasks_have_the_relative_motions_of_the_thesis():
    translation, rotation = TASKS[1].camera_motion
    assert translation == pytest.approx(0.0, abs=1e-12) and rotation == pytest.approx(np.pi)
    assert TASKS[2].camera_motion == pytest.approx((0.30, 1.09), abs=0.02)
    assert TASKS[3].camera_motion == pytest.approx((0.32, 2.92), abs=0.02)


def test_the_laser_method_converges_on_every_task_with_the_thesis_path_lengths(runs):
    for task in TASKS:
        result = runs[task, "laser"]
        assert result.outcome.converged, (task, result.outcome.reason)
        assert result.outcome.final_error_px <= 1.0
        # 1 px on a 100 px face leaves about a degree of tilt: a few mm of camera position.
        assert result.final_translation_m < 5e-3 and result.final_rotation_rad < 0.03
    # Task 1 turns in place: no translation beyond 5 mm.
    assert runs[1, "laser"].path_length_m < 0.005
    for task in (2, 3, 4):
        assert runs[task, "laser"].path_length_m == pytest.approx(THESIS_PATH_LENGTH_M[task]["laser"], rel=0.25)


def test_stages_run_in_the_order_of_section_4_4(runs):
    assert [s["stage"] for s in runs[2, "laser"].outcome.stages] == ["1A", "2", "3"]
    assert [s["stage"] for s in runs[4, "laser"].outcome.stages] == ["1B", "1A", "2", "3"]


def test_classic_ibvs_retreats_on_task_1_and_fails_tasks_3_and_4(runs):
    assert runs[1, "ibvs"].outcome.failure is Failure.CAMERA_RETREAT
    assert runs[2, "ibvs"].outcome.converged
    assert not runs[3, "ibvs"].outcome.converged
    assert runs[4, "ibvs"].outcome.failure is Failure.FEATURES_LOST


def test_2_5d_succeeds_on_tasks_1_to_3_and_fails_task_4(runs):
    for task in (1, 2, 3):
        assert runs[task, "2.5d"].outcome.converged, task
    assert runs[4, "2.5d"].outcome.failure is Failure.FEATURES_LOST


def test_pbvs_moves_the_camera_along_a_straight_line(runs):
    result = runs[2, "pbvs"]
    assert result.outcome.converged
    assert result.path_length_m == pytest.approx(result.straight_line_m, rel=0.01)
    assert runs[4, "pbvs"].outcome.failure is Failure.FEATURES_LOST


@dataclass(frozen=True)
class Stalled:
    """A controller that asks for nothing: its error never falls."""

    name: str = "stalled"

    def step(self, features, desired, stage):
        return ControlOutput(np.zeros(6), "stalled", 50.0, 50.0)


def test_the_loop_names_no_progress_and_the_iteration_limit(cell_config):
    cell = SimulatedCell(cell_config)
    scene = cell_config.simulation.scene
    cell.place_cube(TASKS[2].placement.bMo(scene.table_height_m, scene.cube.side_m))
    desired = teach(cell, TASKS[2].desired_cMo, cell_config.nominal)
    policy = IntegratedVelocity(0.1)
    stuck = run_servo(cell, Stalled(), desired, cell_config.nominal, policy, LoopLimits(progress_window=20),
                      robot=SimulatedBackend.enabled(cell))
    assert stuck.failure is Failure.NO_PROGRESS and stuck.iterations == 21
    short = run_task(cell_config, TASKS[2], RunSettings(method="laser", max_iterations=5))
    assert short.outcome.failure is Failure.ITERATION_LIMIT and short.outcome.iterations == 5


@dataclass(frozen=True)
class Broken:
    """A controller whose law breaks down: it returns NaN."""

    name: str = "broken"

    def step(self, features, desired, stage):
        return ControlOutput(np.full(6, np.nan), "broken", 50.0, 50.0)


def test_a_non_finite_twist_never_reaches_the_robot(cell_config):
    cell = SimulatedCell(cell_config)
    scene = cell_config.simulation.scene
    cell.place_cube(TASKS[2].placement.bMo(scene.table_height_m, scene.cube.side_m))
    desired = teach(cell, TASKS[2].desired_cMo, cell_config.nominal)
    q_before = cell.state.q.copy()
    outcome = run_servo(cell, Broken(), desired, cell_config.nominal, IntegratedVelocity(0.1),
                        robot=SimulatedBackend.enabled(cell))
    assert outcome.failure is Failure.SINGULAR_JACOBIAN and "non-finite" in outcome.reason
    assert np.array_equal(cell.state.q, q_before)


def test_the_arm_that_cannot_follow_is_named(cell_config):
    """A scene the UPJ can start but not finish: IBVS on task 3 asks for a pose out of reach."""
    result = run_task(cell_config, TASKS[3], RunSettings(method="ibvs"))
    assert result.outcome.failure is Failure.UNREACHABLE
    assert "IK" in result.outcome.reason


def test_a_short_occlusion_of_the_spot_does_not_stop_the_run(runs):
    """On task 2 the spot hides behind the cube's edge as it climbs onto it; the run goes on."""
    spots = runs[2, "laser"].trace.laser_px
    assert runs[2, "laser"].outcome.converged and not np.isnan(spots).any()


def test_the_robustness_test_converges_with_the_spot_off_its_row(runs):
    """Table 5-3: task 2 converges with the miscalibrated controller, on a longer path (section
    5.2.2), and the laser spot leaves its image row as the thesis sees in Fig. 5-5 (a)."""
    robust = simulate(task_number=2, method="laser", robust=True)
    ideal = runs[2, "laser"]
    assert robust.outcome.converged, robust.outcome.reason
    assert robust.outcome.final_error_px <= 1.0
    assert robust.final_translation_m < 5e-3 and robust.final_rotation_rad < 0.03
    assert [s["stage"] for s in robust.outcome.stages] == ["1A", "2", "3"]
    assert ideal.path_length_m < robust.path_length_m < 1.25 * ideal.path_length_m
    assert np.ptp(ideal.trace.laser_px[:, 1]) < 0.5
    assert np.ptp(robust.trace.laser_px[:, 1]) > 20.0
    # The same relative motion as task 2; only the cube's place on the table differs.
    assert np.array_equal(ROBUSTNESS_TASK.initial_cMo, TASKS[2].initial_cMo)
    assert np.array_equal(ROBUSTNESS_TASK.desired_cMo, TASKS[2].desired_cMo)


def simulate_cli(*args):
    return subprocess.run([sys.executable, "-m", "vservo.app.cli", "simulate", *args], capture_output=True, text=True,
                          timeout=300)


def test_simulate_prints_one_json_object_with_every_field():
    result = simulate_cli("--task", "1", "--method", "laser", "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert set(summary) >= {"task", "method", "converged", "failure", "iterations", "final_error_px", "path_length_m",
                            "straight_line_m", "final_pose_error", "stages"}
    assert set(summary["final_pose_error"]) == {"translation_m", "rotation_rad"}
    assert summary["converged"] and summary["failure"] is None
    assert all(set(stage) == {"stage", "iterations"} for stage in summary["stages"])


def test_simulate_runs_a_scene_given_by_its_poses():
    result = simulate_cli("--initial=0.011,-0.01,0.18,3.0,0.0,-3.1416", "--desired=0.011,-0.01,0.162,3.1416,0,-3.1416",
                          "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["task"] == "scene" and summary["converged"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--task", "7"], "--task: invalid choice: 7"),
        (["--method", "magic"], "--method: invalid choice: 'magic'"),
        (["--initial=1,2,3"], "expected 6 comma-separated numbers"),
        (["--desired=0,0,nan,0,0,0"], "expected 6 comma-separated numbers"),
        (["--dt", "-1"], "expected a positive float"),
    ],
)
def test_bad_input_gets_one_line_and_a_non_zero_exit(args, message):
    result = simulate_cli(*args)
    assert result.returncode == 2 and result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr


def test_montecarlo_draws_within_the_documented_distribution(cell_config):
    rng = np.random.default_rng(3)
    desired_cMo = TASKS[2].desired_cMo
    camera = cell_config.simulation.truth.camera
    for _ in range(50):
        cMo = draw_initial_cMo(rng, desired_cMo, cell_config)
        translation, rotation = pose_error(inverse(cMo), inverse(desired_cMo))
        # The camera turned in place by at most pi, then moved by at most 0.4 m.
        assert rotation <= MAX_ROTATION_RAD + 1e-9
        assert translation <= MAX_TRANSLATION_M + 1e-9
        centre = cMo[:3, :3] @ [0.01, 0.01, 0.0] + cMo[:3, 3]
        assert DEPTH_RANGE_M[0] - 0.02 <= centre[2] <= DEPTH_RANGE_M[1] + 0.02
        assert inverse(cMo)[2, 3] > 0.0  # the camera above the face
        corners = camera.project(np.array([[0, 0, 0], [0.02, 0, 0], [0.02, 0.02, 0], [0, 0.02, 0]]) @ cMo[:3, :3].T + cMo[:3, 3])
        assert visible_region(corners, camera.image_size).seen  # at least part of the face in the image


def test_montecarlo_is_reproducible_and_counts_every_sample(cell_config):
    settings = RunSettings(method="laser")
    first = run_montecarlo(cell_config, settings, n=4, seed=11, processes=2)
    again = run_montecarlo(cell_config, settings, n=4, seed=11, processes=1)
    assert first == again
    converged = round(first["success_rate"] * 4)
    assert converged + sum(first["failures"].values()) == 4


def test_reproduce_writes_the_report_figures_and_results(tmp_path):
    summaries = reproduce(tmp_path, montecarlo_n=0)
    report = (tmp_path / "report.md").read_text()
    assert "Table 5-4 analogue" in report and "0.348" in report and "0.364" in report
    assert "Robustness test" in report and "Where and why" in report
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["runs"]["2/laser"]["converged"] == summaries["runs"]["2/laser"]["converged"] is True
    assert len(summaries["figures"]) == 8
    for name in summaries["figures"]:
        image = cv2.imread(str(tmp_path / name))
        assert image is not None and image.shape[0] > 200 and image.std() > 5


def test_teaching_sees_the_desired_features_of_table_5_2(cell_config):
    """The taught images at the desired poses are the corrected sets of Table 5-2 within 3 px."""
    from vservo.core.study.tasks import THESIS_DESIRED_FEATURES_PX, THESIS_DESIRED_LASER_PX, distance_to_thesis_set

    scene = cell_config.simulation.scene
    for task, feature_set in ((1, 2), (2, 1), (3, 2), (4, 1)):
        cell = SimulatedCell(cell_config)
        cell.place_cube(TASKS[task].placement.bMo(scene.table_height_m, scene.cube.side_m))
        desired = teach(cell, TASKS[task].desired_cMo, cell_config.nominal)
        assert distance_to_thesis_set(desired.corners_px, THESIS_DESIRED_FEATURES_PX[feature_set]) < 3.0
        assert np.abs(desired.laser_spot_px - THESIS_DESIRED_LASER_PX).max() < 0.5
        assert desired.depth_m == pytest.approx(0.162, abs=1e-6)
