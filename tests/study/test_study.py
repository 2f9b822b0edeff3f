"""The simulation study on the simulated cell: the pattern of Table 5-4, the failure
monitor, the command line, the Monte Carlo sampling and the report."""

import hashlib
import importlib.util
import json
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from vservo.core.cell.config import read_cell_data
from vservo.core.geometry.spatial import inverse, pose_error
from vservo.core.servo.laws.base import ControlOutput, Failure
from vservo.core.servo.loop import LoopLimits, run_servo
from vservo.core.servo.step_policy import IntegratedVelocity
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.plant import SimulatedCell, visible_region
from vservo.core.study import provenance
from vservo.core.study.montecarlo import DEPTH_RANGE_M, MAX_ROTATION_RAD, MAX_TRANSLATION_M, draw_initial_cMo, run_montecarlo
from vservo.core.study.report import report_markdown, reproduce, run_study, study_cells
from vservo.core.study.run import RunSettings, run_task, teach
from vservo.core.study.simulate import simulate
from vservo.core.study.tasks import ROBUSTNESS_TASK, TASKS, THESIS_PATH_LENGTH_M, Table53Reading

ROOT = Path(__file__).resolve().parents[2]
SHIPPED_CELL = ROOT / "static" / "cell.toml"
SNAPSHOT = ROOT / "static" / "study"  # made by `vservo reproduce --out static/study`


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


@pytest.mark.slow
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


@pytest.mark.slow
def test_stages_run_in_the_order_of_section_4_4(runs):
    assert [s["stage"] for s in runs[2, "laser"].outcome.stages] == ["1A", "2", "3"]
    assert [s["stage"] for s in runs[4, "laser"].outcome.stages] == ["1B", "1A", "2", "3"]


@pytest.mark.slow
def test_classic_ibvs_retreats_on_task_1_and_fails_tasks_3_and_4(runs):
    assert runs[1, "ibvs"].outcome.failure is Failure.CAMERA_RETREAT
    assert runs[2, "ibvs"].outcome.converged
    assert not runs[3, "ibvs"].outcome.converged
    assert runs[4, "ibvs"].outcome.failure is Failure.FEATURES_LOST


@pytest.mark.slow
def test_2_5d_succeeds_on_tasks_1_to_3_and_fails_task_4(runs):
    for task in (1, 2, 3):
        assert runs[task, "2.5d"].outcome.converged, task
    assert runs[4, "2.5d"].outcome.failure is Failure.FEATURES_LOST


@pytest.mark.slow
def test_pbvs_moves_the_camera_along_a_straight_line(runs):
    result = runs[2, "pbvs"]
    assert result.outcome.converged
    assert result.path_length_m == pytest.approx(result.straight_line_m, rel=0.01)
    assert runs[4, "pbvs"].outcome.failure is Failure.FEATURES_LOST


@dataclass(frozen=True)
class Stalled:
    """A control law that asks for nothing: its error never falls."""

    name: str = "stalled"

    def step(self, features, desired, stage):
        return ControlOutput(np.zeros(6), "stalled", 50.0, 50.0)


def test_the_loop_names_no_progress_and_the_iteration_limit(cell_config):
    cell = SimulatedCell(cell_config)
    scene = cell_config.simulation.scene
    cell.place_cube(TASKS[2].placement.bMo(scene.table_height_m, scene.cube.side_m))
    desired = teach(cell, TASKS[2].desired_cMo, cell_config.nominal)
    policy = IntegratedVelocity(0.1)
    stuck = run_servo(
        cell,
        Stalled(),
        desired,
        cell_config.nominal,
        policy,
        LoopLimits(progress_window=20),
        robot=SimulatedBackend.enabled(cell),
    )
    assert stuck.failure is Failure.NO_PROGRESS and stuck.iterations == 21
    short = run_task(cell_config, TASKS[2], RunSettings(method="laser", max_iterations=5))
    assert short.outcome.failure is Failure.ITERATION_LIMIT and short.outcome.iterations == 5


@dataclass(frozen=True)
class Broken:
    """A control law that breaks down: it returns NaN."""

    name: str = "broken"

    def step(self, features, desired, stage):
        return ControlOutput(np.full(6, np.nan), "broken", 50.0, 50.0)


def test_a_non_finite_twist_never_reaches_the_robot(cell_config):
    cell = SimulatedCell(cell_config)
    scene = cell_config.simulation.scene
    cell.place_cube(TASKS[2].placement.bMo(scene.table_height_m, scene.cube.side_m))
    desired = teach(cell, TASKS[2].desired_cMo, cell_config.nominal)
    q_before = cell.state.q.copy()
    outcome = run_servo(
        cell, Broken(), desired, cell_config.nominal, IntegratedVelocity(0.1), robot=SimulatedBackend.enabled(cell)
    )
    assert outcome.failure is Failure.SINGULAR_JACOBIAN and "non-finite" in outcome.reason
    assert np.array_equal(cell.state.q, q_before)


def test_the_arm_that_cannot_follow_is_named(cell_config):
    """A scene the UPJ can start but not finish: IBVS on task 3 asks for a pose out of reach."""
    result = run_task(cell_config, TASKS[3], RunSettings(method="ibvs"))
    assert result.outcome.failure is Failure.UNREACHABLE
    assert "IK" in result.outcome.reason


@pytest.mark.slow
def test_a_short_occlusion_of_the_spot_does_not_stop_the_run(runs):
    """On task 2 the spot hides behind the cube's edge as it climbs onto it; the run goes on."""
    spots = runs[2, "laser"].trace.laser_px
    assert runs[2, "laser"].outcome.converged and not np.isnan(spots).any()


@pytest.mark.slow
def test_the_robustness_test_converges_with_the_spot_off_its_row(runs):
    """Table 5-3: task 2 converges with the miscalibrated model, on a longer path (section
    5.2.2), and the laser spot leaves its image row as the thesis sees in Fig. 5-5 (a)."""
    robust = simulate(task_number=2, method="laser", robust=Table53Reading.REPRODUCTION)
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
    return subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "simulate", *args], capture_output=True, text=True, timeout=300
    )


def test_simulate_prints_one_json_object_with_every_field():
    result = simulate_cli("--task", "1", "--method", "laser", "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert set(summary) >= {
        "task",
        "method",
        "converged",
        "failure",
        "iterations",
        "final_error_px",
        "path_length_m",
        "straight_line_m",
        "final_pose_error",
        "stages",
    }
    assert set(summary["final_pose_error"]) == {"translation_m", "rotation_rad"}
    assert summary["converged"] and summary["failure"] is None
    assert all(set(stage) == {"stage", "iterations"} for stage in summary["stages"])


@pytest.mark.slow
def test_simulate_runs_a_scene_given_by_its_poses():
    result = simulate_cli("--initial=0.011,-0.01,0.18,3.0,0.0,-3.1416", "--desired=0.011,-0.01,0.162,3.1416,0,-3.1416", "--json")
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


@pytest.mark.slow
def test_montecarlo_is_reproducible_and_counts_every_sample(cell_config):
    settings = RunSettings(method="laser")
    first = run_montecarlo(cell_config, settings, n=4, seed=11, processes=2)
    again = run_montecarlo(cell_config, settings, n=4, seed=11, processes=1)
    assert first == again
    converged = round(first["success_rate"] * 4)
    assert converged + sum(first["failures"].values()) == 4


@pytest.fixture(scope="module")
def reproduced(tmp_path_factory):
    """``vservo reproduce`` without the Monte Carlo: its folder and what it returned."""
    out = tmp_path_factory.mktemp("study")
    return out, reproduce(out, montecarlo_n=0)


@pytest.mark.slow
def test_reproduce_writes_the_report_figures_and_results(reproduced):
    tmp_path, summaries = reproduced
    report = (tmp_path / "report.md").read_text()
    assert "Table 5-4 analogue" in report and "Robustness test" in report and "Where the results differ" in report
    results = json.loads((tmp_path / "results.json").read_text())
    assert results == summaries and report == report_markdown(results)
    assert results["runs"]["2/laser"]["converged"] is True
    made = results["provenance"]
    assert made["command"] == f"vservo reproduce --out {tmp_path} --montecarlo 0 --seed 0"
    assert made["cell"] == "static/cell.toml" and made["cell_sha256"] == hashlib.sha256(SHIPPED_CELL.read_bytes()).hexdigest()
    assert re.fullmatch(r"[0-9a-f]{40}(-dirty)?|unknown", made["commit"])
    assert f"from commit `{made['commit']}` on {made['date']}" in report
    assert len(summaries["figures"]) == 8
    for name in summaries["figures"]:
        image = cv2.imread(str(tmp_path / name))
        assert image is not None and image.shape[0] > 200 and image.std() > 5


@pytest.mark.slow
def test_the_report_says_what_its_own_results_say(reproduced):
    """The Table 5-4 analogue shows the run's paths beside Table 5-4's, and a path more than
    10 % from the thesis's gets its own line: exactly those paths, recomputed here."""
    out, results = reproduced
    runs, report = results["runs"], (out / "report.md").read_text()
    table = report.split("## Table 5-4 analogue")[1].split("## Every run")[0]
    rows = {
        cells[0]: cells[1:]
        for cells in (line.strip("| ").split(" | ") for line in table.splitlines() if re.match(r"\| \d \|", line))
    }
    methods = list(dict.fromkeys(key.split("/")[1] for key in runs))
    for task in TASKS:
        for column, method in enumerate(methods):
            s = runs[f"{task}/{method}"]
            shown = f"{s['path_length_m']:.3f}" if s["converged"] else f"failure ({s['failure']})"
            assert rows[str(task)][2 * column] == shown, (task, method)

    off = {
        (task, method)
        for task in TASKS
        for method, thesis in THESIS_PATH_LENGTH_M[task].items()
        if thesis
        and runs[f"{task}/{method}"]["converged"]
        and abs(runs[f"{task}/{method}"]["path_length_m"] - thesis) > 0.10 * thesis
    }
    flagged = {
        (int(task), method)
        for task, method in re.findall(r"^- Task (\d), (\S+): path [\d.]+ m against the thesis's", report, re.M)
    }
    assert flagged == off
    assert (2, "ibvs") in off  # 0.310 m against 0.404 m
    assert "- Task 2, ibvs: path 0.310 m against the thesis's 0.404 m, 23.2% shorter." in report
    robust = results["robustness"]
    assert f"after {robust['iterations']} iterations" in report and f"{robust['path_length_m']:.3f} m against" in report


def test_the_report_shows_task_2_under_both_readings_with_both_laws(reproduced):
    """The section beyond the reproduction: task 2 under each reading of Table 5-3 with the
    thesis's law and the robust one, as results.json has them (no Monte Carlo at n = 0)."""
    out, results = reproduced
    report = (out / "report.md").read_text()
    section = report.split("## Calibration errors beyond the reproduction")[1].split("## Where")[0]
    task_2 = results["calibration_errors"]["task 2"]
    assert task_2["reproduction"]["thesis"] == results["robustness"]  # the robustness test itself
    assert task_2["other"]["thesis"]["failure"] == "features_lost"  # the other reading: stage 3 diverges
    assert all(task_2[reading]["robust"]["converged"] for reading in ("reproduction", "other"))
    row = next(line for line in section.splitlines() if line.startswith("| task 2, Table 5-3 read the other way"))
    other = task_2["other"]["robust"]
    assert f"converged in {other['iterations']} iterations, path {other['path_length_m']:.3f} m" in row
    assert "the robust law converges on task 2 under both readings of Table 5-3." in section
    assert "Monte Carlo" not in section.split("|---|---|---|")[1]


def _assert_same(fresh, committed, where="results"):
    """The fresh run's values are the committed ones: exact for everything but floats, which
    the summaries round to 6 decimals (a last-digit flip is allowed, a real change is not)."""
    if isinstance(fresh, dict):
        assert fresh.keys() == committed.keys(), where
        for key in fresh:
            _assert_same(fresh[key], committed[key], f"{where}/{key}")
    elif isinstance(fresh, list):
        assert len(fresh) == len(committed), where
        for i, (a, b) in enumerate(zip(fresh, committed)):
            _assert_same(a, b, f"{where}[{i}]")
    elif isinstance(fresh, float) and not isinstance(committed, bool):
        assert committed == pytest.approx(fresh, rel=1e-6, abs=2e-6), where
    else:
        assert fresh == committed, where


@pytest.mark.slow
def test_the_committed_study_snapshot_is_what_the_code_makes():
    """static/study/ is re-made (the four tasks with every method and the robustness run,
    not the Monte Carlo) with its recorded settings; its numbers and report must be these."""
    committed = json.loads((SNAPSHOT / "results.json").read_text())
    made = committed["provenance"]
    assert shlex.split(made["command"])[:4] == ["vservo", "reproduce", "--out", "static/study"]
    assert "--cell" not in made["command"] and made["cell"] == "static/cell.toml"
    assert made["cell_sha256"] == hashlib.sha256(SHIPPED_CELL.read_bytes()).hexdigest(), "the cell changed: re-make it"
    assert re.fullmatch(r"[0-9a-f]{40}", made["commit"]), "a snapshot is made from a clean, committed tree"
    fresh = run_study(*study_cells(*read_cell_data()), committed["dt_s"]).summaries()
    for part in fresh:
        _assert_same(fresh[part], committed[part], part)
    assert (SNAPSHOT / "report.md").read_text() == report_markdown(committed)
    assert sorted(path.name for path in SNAPSHOT.glob("*.png")) == sorted(committed["figures"])


def test_an_installed_copy_records_an_unknown_commit(tmp_path, monkeypatch):
    """Outside a checkout of vservo (an installed copy) the commit is "unknown", not an error."""
    copy = tmp_path / "provenance.py"
    copy.write_text(Path(provenance.__file__).read_text())
    spec = importlib.util.spec_from_file_location("provenance_copy", copy)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # dataclasses look their module up there
    spec.loader.exec_module(module)
    assert module.source_commit() == "unknown"
    git = ["git", "-C", str(tmp_path), "-c", "user.name=study", "-c", "user.email=study@localhost"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "provenance.py"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "copy"], check=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], check=True, capture_output=True, text=True).stdout.strip()
    assert module.source_commit() == head
    copy.write_text(copy.read_text() + "# changed\n")
    assert module.source_commit() == f"{head}-dirty"


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
