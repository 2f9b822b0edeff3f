"""The calibration workflow end to end on a small patch of the simulated cell, and the
command line's one-line errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from vservo.core.calibration.collection import Workspace
from vservo.core.calibration.dataset import CalibrationDataset
from vservo.core.calibration.levenberg_marquardt import LMSettings
from vservo.core.calibration.tracking import TrackingSettings, sinusoid_points
from vservo.core.calibration.workflow import CollectPlan, collect, evaluate, track, train
from vservo.core.cell.config import load_cell

PATCH = Workspace(x_range_m=(-0.47, -0.43), y_range_m=(-0.02, 0.02), step_m=0.02)


@pytest.fixture(scope="module")
def ideal_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ideal")
    config = load_cell()
    summary = collect(config, folder, "ideal", None, seed=1, plan=CollectPlan(PATCH, test_views=3, rotated_views=8))
    train(config, folder, "planar", samples=3000, validation=500, settings=LMSettings(goal=1e-10, epochs=40), seed=0)
    return folder, summary


@pytest.mark.slow
def test_collection_records_every_reachable_viewpoint_with_the_reported_pose(ideal_folder):
    folder, summary = ideal_folder
    assert summary["grid"] == {"viewpoints": 9, "reachable": 9}
    planar = CalibrationDataset.load(folder / "planar.npz")
    assert planar.views == 9 and planar.size > 9 * 300
    assert planar.metadata["truth"] == "ideal" and planar.metadata["pixel_noise_px"] == 0.0
    # The reported poses are where the camera was sent: tool down, 300 mm over the table.
    assert np.allclose(planar.bMe[:, 2, 3], -0.175 + 0.3, atol=1e-6)
    assert CalibrationDataset.load(folder / "rotated.npz").views >= 6


@pytest.mark.slow
def test_every_method_predicts_held_out_corners_of_the_ideal_cell(ideal_folder):
    folder, _ = ideal_folder
    result = evaluate(folder)
    assert set(result["methods"]) == {"nn", "free_hand_eye", "axxb", "planar_homography"}
    for name, errors in result["methods"].items():
        assert errors["xy_mm"] < 0.05, name


@pytest.mark.slow
def test_pbvs_brings_the_end_effector_over_random_targets(ideal_folder):
    folder, _ = ideal_folder
    result = track(load_cell(), folder, "random", points=2, settings=TrackingSettings(), methods=("nn", "planar_homography"))
    for name, errors in result["methods"].items():
        assert errors["lost"] == 0 and errors["xy_mm"] < 0.05, name
        assert errors["true"]["xy_mm"] == pytest.approx(errors["xy_mm"], abs=1e-6)  # a perfect arm


def test_the_sinusoid_has_41_points_one_period_over_200_mm():
    points = sinusoid_points(0.04)
    assert len(points) == 41
    assert np.allclose(np.diff(points[:, 1]), 0.005)
    assert np.allclose(points[[0, 10, 20, 30, 40], 0] + 0.45, [0.0, 0.04, 0.0, -0.04, 0.0], atol=1e-12)


def run(*args):
    return subprocess.run([sys.executable, "-m", "vservo.app.cli", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.slow
def test_evaluating_an_empty_folder_is_a_one_line_error(tmp_path):
    result = run("calibrate", "evaluate", "--dir", str(tmp_path), "--json")
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.strip().count("\n") == 0
    assert "test.npz: no such file; run vservo calibrate collect first" in result.stderr


@pytest.mark.slow
def test_training_on_a_dataset_with_nan_is_a_one_line_error(tmp_path, ideal_folder):
    data = CalibrationDataset.load(ideal_folder[0] / "planar.npz")
    pixels = data.pixels_px.copy()
    pixels[5, 0] = np.nan
    from vservo.core.calibration.storage import write_archive

    write_archive(
        tmp_path / "planar.npz",
        "vservo calibration dataset",
        {"pixels_px": pixels, "world_m": data.world_m, "view": data.view, "bMe": data.bMe},
        data.metadata,
    )
    result = run("calibrate", "train", "--dir", str(tmp_path))
    assert result.returncode == 2 and result.stderr.strip().count("\n") == 0
    assert "pixels_px holds 1 NaN" in result.stderr


@pytest.mark.slow
def test_evaluate_prints_one_json_object(ideal_folder):
    result = run("calibrate", "evaluate", "--dir", str(ideal_folder[0]), "--json")
    assert result.returncode == 0
    summary = json.loads(result.stdout)
    assert set(summary["methods"]["nn"]) == {"x_mm", "y_mm", "xy_mm", "max_xy_mm", "points"}
