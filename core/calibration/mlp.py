"""The NN hand-eye calibration (thesis section 2.3): an MLP from what the cell measures
to world coordinates, its normalisation, its training and its file.

The network (section 2.3.1, Fig. 2-3, Appendix B): inputs the corner's pixel (u, v) and
the end-effector position the JRC reports (T_x, T_y, and optionally T_z);
one hidden layer of 20 tanh units (eq. 2-24); two linear outputs (eq. 2-25), the world
(X_0, Y_0). No hand-eye transform is estimated: the mapping f of eq. 2-23 is learned.

Normalisation. Outputs are divided by the workspace limits max|X_0|, max|Y_0| (eq. 2-42,
``max(abs(.))`` as in Appendix B) and scaled back (eq. 2-43). Inputs are mapped to
[-1, 1] by their training minimum and maximum, as Matlab's ``newff(minmax(p), ...)``
does before the first layer; an input that never varies is passed through centred.

Input sets:
- ``planar``: (u, v, T_x, T_y), the thesis's network (Appendix B);
- ``height``: (u, v, T_x, T_y, T_z), the optional T_z of section 2.3.1;
- ``pose``: (u, v, T_x, T_y, T_z, r_x, r_y, r_z) with r the rotation vector of the end
  effector away from tool-down: the 6-DOF step the thesis left as future work (2.5, 6).

Training (section 2.3.2 step 2) is Levenberg-Marquardt on the sum of squared errors of
the normalised outputs (eqs. 2-26, 2-28), with the Jacobian of the residuals by reverse-
mode automatic differentiation (``residual_functions``), float64, seeded Nguyen-Widrow
initial weights as Matlab's initnw. A file holds the weights, the normalisation and the
training record; loading refuses an untrained network or one whose arrays do not match
its declared layers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vservo.core.calibration.dataset import INPUT_SETS, CalibrationDataset, network_inputs
from vservo.core.calibration.levenberg_marquardt import LMResult, LMSettings, levenberg_marquardt
from vservo.core.calibration.storage import CalibrationFileError, read_archive, write_archive
from vservo.core.geometry.spatial import Matrix

KIND = "vservo NN hand-eye calibration"
HIDDEN_UNITS = 20


class ModelFileError(CalibrationFileError):
    """A calibration model file that cannot be used; the message says why."""


def parameter_count(inputs: int, hidden: int) -> int:
    return hidden * inputs + hidden + 2 * hidden + 2


def forward(params: torch.Tensor, x: torch.Tensor, inputs: int, hidden: int) -> torch.Tensor:
    """Normalised outputs (N, 2) of normalised inputs x (N, k): W2 tanh(W1 x + b1) + b2
    (eqs. 2-24, 2-25). ``params`` is one parameter vector (P,) or one per sample (N, P)."""
    lead = params.shape[:-1]
    split = np.cumsum([hidden * inputs, hidden, 2 * hidden])
    W1 = params[..., : split[0]].reshape(*lead, hidden, inputs)
    b1 = params[..., split[0] : split[1]]
    W2 = params[..., split[1] : split[2]].reshape(*lead, 2, hidden)
    b2 = params[..., split[2] :]
    h = torch.tanh((W1 @ x[:, :, None])[..., 0] + b1)
    return (W2 @ h[:, :, None])[..., 0] + b2


def nguyen_widrow(inputs: int, hidden: int, rng: np.random.Generator) -> Matrix:
    """Initial weights for inputs in [-1, 1] (Nguyen and Widrow 1990; Matlab's initnw)."""
    beta = 0.7 * hidden ** (1.0 / inputs)
    W1 = rng.uniform(-1.0, 1.0, (hidden, inputs))
    W1 *= beta / np.linalg.norm(W1, axis=1, keepdims=True)
    b1 = rng.uniform(-beta, beta, hidden)
    W2 = rng.uniform(-1.0, 1.0, (2, hidden)) / np.sqrt(hidden)
    b2 = rng.uniform(-1.0, 1.0, 2) * 0.1
    return np.concatenate((W1.ravel(), b1, W2.ravel(), b2))


@dataclass(frozen=True)
class Normalisation:
    """Input min-max to [-1, 1] and output division by max|X_0|, max|Y_0| (eqs. 2-42, 2-43)."""

    input_min: Matrix
    input_max: Matrix
    output_scale: Matrix

    @classmethod
    def fit(cls, inputs: Matrix, world_m: Matrix) -> Normalisation:
        scale = np.max(np.abs(world_m), axis=0)
        if np.any(scale <= 0.0):
            raise ValueError("the world coordinates are all zero along an axis: nothing to normalise by")
        return cls(inputs.min(axis=0), inputs.max(axis=0), scale)

    def inputs(self, raw: Matrix) -> Matrix:
        span = self.input_max - self.input_min
        centre = 0.5 * (self.input_max + self.input_min)
        return np.where(span > 0.0, 2.0 * (raw - centre) / np.where(span > 0.0, span, 1.0), raw - centre)

    def outputs(self, world_m: Matrix) -> Matrix:
        """Eq. 2-42."""
        return world_m / self.output_scale

    def world(self, outputs: Matrix) -> Matrix:
        """Eq. 2-43."""
        return outputs * self.output_scale


@dataclass(frozen=True)
class NNCalibration:
    """A trained MLP calibration: world (x, y) in m of a pixel seen from a reported pose."""

    input_set: str
    hidden: int
    params: Matrix
    normalisation: Normalisation
    trained: bool = False
    training: dict[str, Any] = field(default_factory=dict)

    name = "nn"

    @property
    def inputs(self) -> int:
        return len(INPUT_SETS[self.input_set])

    def world_of(self, pixels_px: Matrix, bMe: Matrix) -> Matrix:
        """World (x, y) (N, 2) in m of pixels (N, 2) seen from reported poses bMe (N, 4, 4)."""
        x = self.normalisation.inputs(network_inputs(self.input_set, pixels_px, bMe))
        with torch.no_grad():
            out = forward(torch.from_numpy(self.params), torch.from_numpy(x), self.inputs, self.hidden).numpy()
        return self.normalisation.world(out)

    def save(self, path: str | Path) -> Path:
        arrays = {
            "params": self.params,
            "input_min": self.normalisation.input_min,
            "input_max": self.normalisation.input_max,
            "output_scale": self.normalisation.output_scale,
        }
        metadata = {
            "method": self.name,
            "input_set": self.input_set,
            "input_names": list(INPUT_SETS[self.input_set]),
            "hidden": self.hidden,
            "trained": self.trained,
            "training": self.training,
        }
        return write_archive(path, KIND, arrays, metadata)

    @classmethod
    def load(cls, path: str | Path, input_set: str | None = None) -> NNCalibration:
        """A trained calibration from a file; ModelFileError if it is untrained, its arrays
        do not match its layers, or it was trained on other inputs than ``input_set``."""
        arrays, meta = read_archive(path, KIND, ModelFileError)
        if not meta.get("trained"):
            raise ModelFileError(f"{path}: the network was never trained; train it first (vservo calibrate train)")
        stored_set, hidden = meta.get("input_set"), meta.get("hidden")
        if stored_set not in INPUT_SETS or meta.get("input_names") != list(INPUT_SETS[stored_set]):
            raise ModelFileError(f"{path}: unknown inputs {meta.get('input_names')!r}")
        if input_set is not None and stored_set != input_set:
            raise ModelFileError(
                f"{path}: the network takes the {stored_set!r} inputs {INPUT_SETS[stored_set]}, "
                f"not the {input_set!r} inputs {INPUT_SETS[input_set]}"
            )
        if not isinstance(hidden, int) or hidden < 1:
            raise ModelFileError(f"{path}: hidden layer size {hidden!r} is not a positive whole number")
        k = len(INPUT_SETS[stored_set])
        expected = {"params": (parameter_count(k, hidden),), "input_min": (k,), "input_max": (k,), "output_scale": (2,)}
        for name, shape in expected.items():
            if name not in arrays:
                raise ModelFileError(f"{path}: missing array {name}")
            if arrays[name].shape != shape:
                raise ModelFileError(f"{path}: {name} has shape {arrays[name].shape}, a {k}-{hidden}-2 network needs {shape}")
            if not np.all(np.isfinite(arrays[name])):
                raise ModelFileError(f"{path}: {name} holds NaN or infinite values")
        if np.any(arrays["output_scale"] <= 0.0):  # eq. 2-43 scales by max|X_0|, max|Y_0|: never zero
            raise ModelFileError(
                f"{path}: output_scale = {arrays['output_scale'].tolist()}: both scales must be "
                "positive (the largest |X_0| and |Y_0| of the training data)"
            )
        normalisation = Normalisation(arrays["input_min"], arrays["input_max"], arrays["output_scale"])
        return cls(stored_set, hidden, arrays["params"], normalisation, True, meta.get("training", {}))


@dataclass(frozen=True)
class TrainingData:
    """Normalised inputs and targets, as float64 tensors."""

    x: torch.Tensor
    t: torch.Tensor

    @classmethod
    def of(cls, dataset: CalibrationDataset, input_set: str, normalisation: Normalisation) -> TrainingData:
        raw = dataset.network_inputs(input_set)
        return cls(torch.from_numpy(normalisation.inputs(raw)), torch.from_numpy(normalisation.outputs(dataset.world_m)))


def residual_functions(data: TrainingData, inputs: int, hidden: int) -> tuple[Callable, Callable]:
    """v(x) (2N,) and its Jacobian J(x) (2N, P) for the normalised outputs (eqs. 2-28, 2-33).

    The Jacobian is reverse-mode automatic differentiation with one copy of the
    parameters per sample: sample n's outputs depend only on copy n, so the gradient of
    the sum over samples of output o with respect to the copies is, row by row, each
    sample's gradient, i.e. the rows of J for output o. Two backward passes give J.
    """
    n = len(data.x)

    def residuals(params: torch.Tensor) -> torch.Tensor:
        return (data.t - forward(params, data.x, inputs, hidden)).reshape(-1)

    def jacobian(params: torch.Tensor) -> torch.Tensor:
        copies = params.detach().expand(n, -1).clone().requires_grad_(True)
        out = forward(copies, data.x, inputs, hidden)
        dx_dp = torch.autograd.grad(out[:, 0].sum(), copies, retain_graph=True)[0]
        dy_dp = torch.autograd.grad(out[:, 1].sum(), copies)[0]
        return -torch.stack((dx_dp, dy_dp), dim=1).reshape(2 * n, -1)

    return residuals, jacobian


def train_nn(
    train: CalibrationDataset,
    input_set: str = "planar",
    *,
    validation: CalibrationDataset | None = None,
    hidden: int = HIDDEN_UNITS,
    settings: LMSettings = LMSettings(),
    seed: int = 0,
    on_epoch: Callable[[int, float], None] | None = None,
) -> NNCalibration:
    """Train the MLP by Levenberg-Marquardt (module docstring); seeded, reproducible."""
    train.validate(str(train.metadata.get("source", "the training data")), min_corners=0)  # the corner count: below
    raw = train.network_inputs(input_set)
    normalisation = Normalisation.fit(raw, train.world_m)
    k = raw.shape[1]
    if train.size * 2 <= parameter_count(k, hidden):
        raise ValueError(f"{train.size} corners cannot fit a {k}-{hidden}-2 network of {parameter_count(k, hidden)} weights")
    residuals, jacobian = residual_functions(TrainingData.of(train, input_set, normalisation), k, hidden)
    check = None
    if validation is not None:
        check, _ = residual_functions(TrainingData.of(validation, input_set, normalisation), k, hidden)
    x0 = torch.from_numpy(nguyen_widrow(k, hidden, np.random.default_rng(seed)))
    # The network's tensors are small: splitting each operation over threads costs more
    # than it gains, and on a busy machine waiting for a second thread costs most of all.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        result: LMResult = levenberg_marquardt(residuals, jacobian, x0, settings, check, on_epoch)
    finally:
        torch.set_num_threads(threads)
    training = {
        "samples": train.size,
        "validation_samples": validation.size if validation is not None else 0,
        "epochs": result.epochs,
        "stop": result.stop,
        "mse": result.mse,
        "validation_mse": result.validation_mse,
        "goal": settings.goal,
        "seed": seed,
        "dataset": dict(train.metadata),
    }
    return NNCalibration(input_set, hidden, result.x.numpy().copy(), normalisation, trained=True, training=training)
