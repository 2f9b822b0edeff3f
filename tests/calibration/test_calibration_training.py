"""Levenberg-Marquardt, the MLP and its file: known minima, autograd against finite
differences, save/load round trips, and refused files."""

import numpy as np
import pytest
import torch

from vservo.core.calibration.dataset import CalibrationDataset, DatasetError
from vservo.core.calibration.levenberg_marquardt import LMSettings, levenberg_marquardt
from vservo.core.calibration.mlp import (
    ModelFileError,
    NNCalibration,
    Normalisation,
    forward,
    nguyen_widrow,
    parameter_count,
    train_nn,
)
from vservo.core.calibration.storage import write_archive
from vservo.core.geometry.spatial import rot_x, transform


def rosenbrock(x):
    return torch.stack((10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]))


def rosenbrock_jacobian(x):
    return torch.tensor([[-20.0 * float(x[0]), 10.0], [-1.0, 0.0]], dtype=torch.float64)


def test_lm_finds_the_minimum_of_rosenbrocks_valley():
    result = levenberg_marquardt(
        rosenbrock, rosenbrock_jacobian, torch.tensor([-1.2, 1.0], dtype=torch.float64), LMSettings(goal=1e-24, epochs=200)
    )
    assert result.stop == "goal"
    assert np.allclose(result.x.numpy(), [1.0, 1.0], atol=1e-10)
    # Step (iv): only steps that lower the sum of squares are taken.
    assert all(b < a for a, b in zip(result.history, result.history[1:]))


def test_lm_solves_linear_least_squares_as_numpy_does():
    rng = np.random.default_rng(3)
    A, b = rng.normal(size=(40, 5)), rng.normal(size=40)
    At, bt = torch.from_numpy(A), torch.from_numpy(b)
    result = levenberg_marquardt(
        lambda x: At @ x - bt,
        lambda x: At,
        torch.zeros(5, dtype=torch.float64),
        LMSettings(goal=0.0, epochs=50, min_gradient=1e-13),
    )
    assert result.stop in ("gradient", "mu")
    assert np.allclose(result.x.numpy(), np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-9)


def test_lm_stops_on_the_epoch_limit_and_on_a_rising_validation_error():
    x0 = torch.tensor([-1.2, 1.0], dtype=torch.float64)
    assert levenberg_marquardt(rosenbrock, rosenbrock_jacobian, x0, LMSettings(goal=0.0, epochs=3)).epochs == 3
    # A validation problem whose minimum lies elsewhere: its error rises once the fit closes in on (1, 1).
    away = levenberg_marquardt(
        rosenbrock,
        rosenbrock_jacobian,
        x0,
        LMSettings(goal=0.0, epochs=200, max_fail=2),
        validation=lambda x: x - torch.tensor([-1.2, 1.0], dtype=torch.float64),
    )
    assert away.stop == "validation"


def test_the_residual_jacobian_by_autograd_matches_finite_differences():
    from vservo.core.calibration.mlp import TrainingData, residual_functions

    rng = np.random.default_rng(0)
    data = TrainingData(torch.from_numpy(rng.uniform(-1, 1, (7, 4))), torch.from_numpy(rng.uniform(-1, 1, (7, 2))))
    residuals, jacobian = residual_functions(data, 4, 5)
    params = torch.from_numpy(nguyen_widrow(4, 5, rng))
    J = jacobian(params).numpy()
    h = 1e-6
    numeric = np.column_stack(
        [
            (residuals(params + h * e) - residuals(params - h * e)).numpy() / (2 * h)
            for e in torch.eye(params.numel(), dtype=torch.float64)
        ]
    )
    assert J.shape == (14, parameter_count(4, 5))
    assert np.allclose(J, numeric, atol=1e-8)


def planar_dataset(n_views=12, seed=0):
    """A synthetic planar dataset: pixels of a pinhole camera looking down from tool-down poses."""
    rng = np.random.default_rng(seed)
    f, height = 810.8, 0.3
    poses, pixels, world, view = [], [], [], []
    for k in range(n_views):
        T = np.array([-0.45 + rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.125])
        poses.append(transform(rot_x(np.pi), T))
        uv = rng.uniform([0, 0], [640, 480], (40, 2))
        # Tool down: camera x along base x, camera y along -base y.
        world.append(np.column_stack((T[0] + (uv[:, 0] - 320) * height / f, T[1] - (uv[:, 1] - 240) * height / f)))
        pixels.append(uv)
        view.append(np.full(40, k))
    return CalibrationDataset(
        np.concatenate(pixels), np.concatenate(world), np.concatenate(view), np.array(poses), {"truth": "synthetic"}
    )


def test_a_trained_network_maps_pixels_to_world_and_survives_a_save_load_round_trip(tmp_path):
    data = planar_dataset()
    model = train_nn(
        data.subset(np.arange(400)),
        validation=data.subset(np.arange(400, 480)),
        settings=LMSettings(goal=1e-12, epochs=60),
        seed=4,
    )
    assert model.trained and model.training["mse"] < 1e-6
    test = planar_dataset(seed=1)
    error = model.world_of(test.pixels_px, test.bMe[test.view]) - test.world_m
    assert np.max(np.abs(error)) < 1e-3  # 1 mm at worst over a 180 x 240 mm view: the map is learned
    loaded = NNCalibration.load(model.save(tmp_path / "nn.npz"), "planar")
    assert np.array_equal(
        loaded.world_of(test.pixels_px, test.bMe[test.view]), model.world_of(test.pixels_px, test.bMe[test.view])
    )
    assert loaded.training["epochs"] == model.training["epochs"]


def test_training_is_reproducible_from_its_seed():
    data = planar_dataset().subset(np.arange(300))
    a, b = (train_nn(data, settings=LMSettings(epochs=5), seed=9) for _ in range(2))
    assert np.array_equal(a.params, b.params)


def untrained(inputs=4, hidden=20):
    params = nguyen_widrow(inputs, hidden, np.random.default_rng(0))
    normalisation = Normalisation(np.zeros(inputs), np.ones(inputs), np.ones(2))
    return NNCalibration("planar" if inputs == 4 else "height", hidden, params, normalisation)


def test_an_untrained_network_file_is_refused(tmp_path):
    path = untrained().save(tmp_path / "nn.npz")
    with pytest.raises(ModelFileError, match="never trained"):
        NNCalibration.load(path)


def test_a_network_file_whose_arrays_do_not_match_its_layers_is_refused(tmp_path):
    model = untrained()
    arrays = {"params": model.params[:-3], "input_min": np.zeros(4), "input_max": np.ones(4), "output_scale": np.ones(2)}
    meta = {"method": "nn", "input_set": "planar", "input_names": ["u", "v", "Tx", "Ty"], "hidden": 20, "trained": True}
    write_archive(tmp_path / "short.npz", "vservo NN hand-eye calibration", arrays, meta)
    with pytest.raises(ModelFileError, match="params has shape"):
        NNCalibration.load(tmp_path / "short.npz")


def test_a_network_is_refused_for_inputs_it_was_not_trained_on(tmp_path):
    from dataclasses import replace

    path = replace(untrained(5), trained=True).save(tmp_path / "nn.npz")
    assert NNCalibration.load(path, "height").inputs == 5
    with pytest.raises(ModelFileError, match="not the 'planar' inputs"):
        NNCalibration.load(path, "planar")


def test_a_dataset_is_not_taken_for_a_network(tmp_path):
    path = planar_dataset().save(tmp_path / "planar.npz")
    with pytest.raises(ModelFileError, match="not a 'vservo NN hand-eye calibration'"):
        NNCalibration.load(path)


def test_forward_is_the_two_layer_network_of_eqs_2_24_and_2_25():
    rng = np.random.default_rng(1)
    params, x = nguyen_widrow(3, 4, rng), rng.normal(size=(5, 3))
    W1, b1 = params[:12].reshape(4, 3), params[12:16]
    W2, b2 = params[16:24].reshape(2, 4), params[24:]
    expected = np.tanh(x @ W1.T + b1) @ W2.T + b2
    assert np.allclose(forward(torch.from_numpy(params), torch.from_numpy(x), 3, 4).numpy(), expected)


# -- datasets ---------------------------------------------------------------------------


def write_dataset(path, **changes):
    data = planar_dataset()
    arrays = {"pixels_px": data.pixels_px, "world_m": data.world_m, "view": data.view, "bMe": data.bMe, **changes}
    write_archive(path, "vservo calibration dataset", arrays, {"truth": "synthetic"})
    return path


def test_a_dataset_round_trips_with_its_metadata(tmp_path):
    data = planar_dataset()
    loaded = CalibrationDataset.load(data.save(tmp_path / "d.npz"))
    assert np.array_equal(loaded.pixels_px, data.pixels_px) and np.array_equal(loaded.bMe, data.bMe)
    assert loaded.metadata == {"truth": "synthetic"}


def test_a_dataset_with_nan_is_refused_naming_the_array(tmp_path):
    pixels = planar_dataset().pixels_px.copy()
    pixels[17, 1] = np.nan
    with pytest.raises(DatasetError, match=r"pixels_px holds 1 NaN or infinite values \(first at index \[17, 1\]\)"):
        CalibrationDataset.load(write_dataset(tmp_path / "nan.npz", pixels_px=pixels))


def test_a_dataset_with_too_few_corners_is_refused(tmp_path):
    data = planar_dataset()
    path = write_dataset(tmp_path / "few.npz", pixels_px=data.pixels_px[:40], world_m=data.world_m[:40], view=data.view[:40])
    with pytest.raises(DatasetError, match="40 corners, too few"):
        CalibrationDataset.load(path)


def test_a_dataset_with_a_wrong_shape_is_refused(tmp_path):
    data = planar_dataset()
    with pytest.raises(DatasetError, match=r"world_m has shape \(480, 3\), expected \(480, 2\)"):
        CalibrationDataset.load(write_dataset(tmp_path / "shape.npz", world_m=np.zeros((480, 3))))
    with pytest.raises(DatasetError, match="view indices run to 11 but there are 3 poses"):
        CalibrationDataset.load(write_dataset(tmp_path / "views.npz", bMe=data.bMe[:3]))


def test_a_file_that_is_not_a_dataset_is_refused(tmp_path):
    path = tmp_path / "junk.npz"
    path.write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="not a vservo calibration file"):
        CalibrationDataset.load(path)
    with pytest.raises(DatasetError, match="no such file"):
        CalibrationDataset.load(tmp_path / "missing.npz")


def test_the_6dof_inputs_are_height_and_the_rotation_away_from_tool_down():
    from vservo.core.calibration.dataset import network_inputs
    from vservo.core.geometry.spatial import exp_twist

    tool_down = transform(rot_x(np.pi), (-0.45, 0.01, 0.125))
    tilted = tool_down @ exp_twist([0, 0, 0, 0.03, -0.02, 0.1])
    inputs = network_inputs("pose", np.array([[320.0, 240.0], [10.0, 20.0]]), np.array([tool_down, tilted]))
    assert np.allclose(inputs[:, :5], [[320, 240, -450, 10, 125], [10, 20, -450, 10, 125]])
    assert np.allclose(inputs[0, 5:], 0.0, atol=1e-12)
    assert np.allclose(inputs[1, 5:], [0.03, -0.02, 0.1])
    assert network_inputs("planar", inputs[:, :2], np.array([tool_down, tilted])).shape == (2, 4)


def test_a_network_with_a_zero_output_scale_is_refused_at_load(tmp_path):
    from dataclasses import replace

    model = replace(untrained(), trained=True, normalisation=Normalisation(np.zeros(4), np.ones(4), np.array([0.2, 0.0])))
    path = model.save(tmp_path / "flat.npz")
    with pytest.raises(ModelFileError, match=r"flat.npz: output_scale = \[0.2, 0.0\]: both scales must be positive"):
        NNCalibration.load(path)


def test_a_dataset_of_all_zero_poses_is_refused_at_load_and_at_training(tmp_path):
    data = planar_dataset()
    zero = np.zeros_like(data.bMe)
    with pytest.raises(DatasetError, match=r"zero.npz: bMe\[0\] = \[\[0.0, .*is not a rigid transform"):
        CalibrationDataset.load(write_dataset(tmp_path / "zero.npz", bMe=zero))
    with pytest.raises(DatasetError, match=r"bMe\[0\] = .* is not a rigid transform"):
        train_nn(CalibrationDataset(data.pixels_px, data.world_m, data.view, zero), settings=LMSettings(epochs=2))
