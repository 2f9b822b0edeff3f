"""The loop on camera images: rendered frames, the vision pipeline, recording and replay."""

import json
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from vservo.core.cell.scene import Cube
from vservo.core.geometry.spatial import inverse
from vservo.core.perception.camera_source import Frame
from vservo.core.perception.features import ImageFeatures
from vservo.core.perception.vision.pipeline import ImageFeatureExtractor, front_winding, winding_of
from vservo.core.servo.laws.base import Failure
from vservo.core.servo.loop import LoopLimits
from vservo.core.sim.camera import SimulatedCamera
from vservo.core.sim.plant import SimulatedCell
from vservo.core.sim.render_settings import RenderSettings
from vservo.core.sim.sensor import FrameFault
from vservo.core.study.replay import replay
from vservo.core.study.run import RunSettings, run_task
from vservo.core.study.tasks import TASKS


def extractor(config):
    return ImageFeatureExtractor(config.nominal.camera, config.nominal.laser, front_winding(Cube(np.eye(4)).corners_o))


def test_front_winding_matches_a_projected_desired_view(cell_config):
    cell = SimulatedCell(cell_config)
    scene = cell_config.simulation.scene
    cell.place_cube(TASKS[1].placement.bMo(scene.table_height_m, scene.cube.side_m))
    cell.place_camera(TASKS[1].desired_cMo)
    assert winding_of(cell.measure().corners_px) == front_winding(cell.state.scene.cube.corners_o)


@pytest.mark.parametrize("task", [1, 2])
def test_features_from_a_rendered_frame_are_the_projected_ones(cell_config, task):
    cell = SimulatedCell(cell_config)
    scene = cell_config.simulation.scene
    cell.place_cube(TASKS[task].placement.bMo(scene.table_height_m, scene.cube.side_m))
    cell.place_camera(TASKS[task].desired_cMo)
    projected = cell.measure()
    features, report = extractor(cell_config).extract(SimulatedCamera(cell).read().image)
    assert report.corners.found and report.spot.found, (report.corners.reason, report.spot.reason)
    # The corners come in the model's order: the same order as the projections.
    assert np.abs(features.corners_px - projected.corners_px).max() < 0.3
    assert np.abs(features.laser_spot_px - projected.laser_spot_px).max() < 0.2
    assert features.laser_depth_m == pytest.approx(0.162, abs=5e-4)


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((480, 640), np.uint8),
        np.full((480, 640), 255, np.uint8),
        np.full((480, 640), 60, np.uint8),
        np.zeros((480, 640, 3), np.uint8),
        np.zeros((480, 640), np.float32),
        np.zeros((10, 10), np.uint8),
    ],
    ids=["black", "saturated", "table only", "colour", "float", "tiny"],
)
def test_bad_frames_give_unseen_features_never_an_exception(cell_config, image):
    features, report = extractor(cell_config).extract(image)
    assert isinstance(features, ImageFeatures)
    assert not features.all_corners_visible and not features.laser_visible
    assert report.corners.reason and report.spot.reason


def test_a_dropped_frame_stops_the_laser_method_with_features_lost(cell_config):
    cell = SimulatedCell(cell_config)
    scene = cell_config.simulation.scene
    cell.place_cube(TASKS[2].placement.bMo(scene.table_height_m, scene.cube.side_m))
    cell.place_camera(TASKS[2].initial_cMo)
    camera = SimulatedCamera(cell)
    features, _ = extractor(cell_config).extract(camera.read(fault=FrameFault.dropped()).image)
    assert not features.laser_visible and not features.region.seen


class DroppingCamera(SimulatedCamera):
    """The simulated camera, with the frames whose numbers are in ``dropped`` lost
    (black, as a camera link hands out a dropped frame): the detectors find nothing."""

    def __init__(self, cell: SimulatedCell, dropped: range) -> None:
        super().__init__(cell)
        self.dropped = dropped
        self.reads = 0

    def read(self, fault: FrameFault | None = None) -> Frame:
        drop = self.reads in self.dropped
        self.reads += 1
        return super().read(FrameFault.dropped() if drop else fault)


def servo_through_dropped_frames(config, dropped: range):
    """Task 2's laser servo on rendered frames, the frames numbered in ``dropped`` lost."""
    settings = RunSettings(method="laser", features="rendered")
    return run_task(config, TASKS[2], settings, camera=lambda cell: DroppingCamera(cell, dropped))


DROP_AT = 40  # a cycle of stage 2, where the corners are needed


def test_the_loop_holds_the_robot_through_two_lost_frames(cell_config):
    outcome = servo_through_dropped_frames(cell_config, range(DROP_AT, DROP_AT + 2)).outcome
    assert outcome.converged, outcome.reason
    held = outcome.cycles[DROP_AT : DROP_AT + 2]
    assert all(not cycle.features.all_corners_visible for cycle in held)
    assert all(cycle.output.note.startswith("holding") and not cycle.output.cVc.any() for cycle in held)
    # No command during the held cycles: the next cycle's readout is where the first held one was.
    for cycle in (*held[1:], outcome.cycles[DROP_AT + 2]):
        np.testing.assert_array_equal(cycle.measurement.q, held[0].measurement.q)
        assert cycle.measurement.time_s == held[0].measurement.time_s
    assert outcome.cycles[DROP_AT + 2].features.all_corners_visible


def test_the_loop_stops_with_features_lost_after_the_held_frames(cell_config):
    hold = LoopLimits().lost_hold_cycles
    result = servo_through_dropped_frames(cell_config, range(DROP_AT, DROP_AT + hold + 1))
    outcome = result.outcome
    assert outcome.failure is Failure.FEATURES_LOST and "corners" in outcome.reason
    assert outcome.iterations == DROP_AT + hold + 1
    lost = outcome.cycles[DROP_AT:]
    assert outcome.cycles[DROP_AT - 1].output.stage == lost[0].output.stage
    for cycle in lost:
        np.testing.assert_array_equal(cycle.measurement.q, lost[0].measurement.q)
        assert not cycle.output.cVc.any()
    # The true flange after the last cycle is where it was when the frames were lost.
    np.testing.assert_array_equal(result.trace.bMe_position_true[-1], result.trace.bMe_position_true[DROP_AT])


@pytest.fixture(scope="module")
def rendered_runs(cell_config):
    return {
        task: (
            run_task(cell_config, TASKS[task], RunSettings(method="laser")),
            run_task(cell_config, TASKS[task], RunSettings(method="laser", features="rendered")),
        )
        for task in TASKS
    }


@pytest.mark.slow
def test_every_task_converges_on_rendered_features_like_on_ideal_ones(rendered_runs):
    for task, (ideal, rendered) in rendered_runs.items():
        assert rendered.outcome.converged, (task, rendered.outcome.reason)
        assert abs(rendered.outcome.final_error_px - ideal.outcome.final_error_px) < 1.0
        assert rendered.path_length_m == pytest.approx(ideal.path_length_m, rel=0.1, abs=0.005)


def test_a_recorded_run_replays_to_the_same_decisions(cell_config, tmp_path):
    folder = tmp_path / "run"
    result = run_task(cell_config, TASKS[1], RunSettings(method="laser", features="rendered", record_to=str(folder)))
    report = replay(folder)
    assert report["cycles"] == result.outcome.iterations == report["frames"]
    assert report["stage_mismatches"] == 0
    assert report["twist_difference_max"] < 1e-9
    assert report["corner_difference_px_max"] < 1e-9
    assert report["outcome"]["converged"] is True


def test_detect_reads_an_image_file(cell_config, tmp_path):
    cell = SimulatedCell(cell_config)
    scene = cell_config.simulation.scene
    cell.place_cube(TASKS[2].placement.bMo(scene.table_height_m, scene.cube.side_m))
    cell.place_camera(TASKS[2].desired_cMo)
    path = tmp_path / "view.png"
    cv2.imwrite(str(path), cv2.cvtColor(SimulatedCamera(cell).read().image, cv2.COLOR_GRAY2BGR))
    result = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "detect", str(path), "--json"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    found = json.loads(result.stdout)
    bMc, _ = cell.ground_truth_view()
    cMb = inverse(bMc)
    truth = cell.truth.model.camera.project(cell.state.scene.cube.corners_b @ cMb[:3, :3].T + cMb[:3, 3])
    assert np.abs(np.array(found["corners"]["px"]) - truth).max() < 0.3
    assert found["laser_depth_mm"] == pytest.approx(162.0, abs=0.5)
    missing = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "detect", str(tmp_path / "none.png")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert missing.returncode == 2 and "cannot read image" in missing.stderr and "none.png" in missing.stderr


def test_a_simulated_camera_is_a_frame_source(cell_config):
    cell = SimulatedCell(cell_config)
    with SimulatedCamera(cell, RenderSettings(noise_sigma=2.0), seed=4) as camera:
        first, second = camera.read(), camera.read()
        assert isinstance(first, Frame) and (first.index, second.index) == (0, 1)
        assert first.image.shape == (480, 640) and camera.image_size == (640, 480)
        assert not np.array_equal(first.image, second.image)  # fresh noise every frame
        # The current view, whichever clock the robot's motion ended on (the host's for the JRC link).
        assert camera.read_after(time.monotonic()).index == 2


def test_detect_on_an_empty_file_says_so_in_one_line(tmp_path):
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    result = subprocess.run(
        [sys.executable, "-m", "vservo.app.cli", "detect", str(empty)], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 2
    assert result.stderr.splitlines() == [f"vservo detect: error: cannot decode image {str(empty)!r}: the file is empty"]
