"""Levenberg-Marquardt least squares (thesis eqs. 2-28 .. 2-41, section 2.3.2).

Minimises the sum of squared residuals E(x) = v(x)^T v(x) (eq. 2-29). Each epoch:

(i)   the residuals v(x_k) and E(x_k);
(ii)  the Jacobian J(x_k) (eq. 2-33), here by automatic differentiation;
(iii) the damped normal equations [J^T J + mu I] dx = -J^T v (eq. 2-40);
(iv)  E(x_k + dx): if it is smaller, divide mu by theta, accept the step and start the
      next epoch; otherwise multiply mu by theta and go back to (iii).

Large mu makes the step a short steepest-descent one (eq. 2-41), small mu a Gauss-Newton
one (eq. 2-38). theta = 10 and mu_0 = 0.001 are Matlab's trainlm values, which the
thesis used (Appendix B; trainlm has no learning rate, so the thesis's lr = 0.03 plays
no part). Training stops at the first of: the performance goal (mean squared error,
Matlab's ``goal``), the epoch limit, a gradient norm below ``min_gradient``, mu above
``mu_max`` (no step reduces E), or the validation error rising ``max_fail`` epochs in a
row (early stopping: the parameters of the best validation epoch are returned).
Everything is float64 torch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

Residuals = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class LMSettings:
    """Stopping rules and the mu schedule (module docstring)."""

    epochs: int = 500
    goal: float = 1e-8
    min_gradient: float = 1e-12
    mu: float = 1e-3
    theta: float = 10.0
    mu_max: float = 1e10
    max_fail: int = 6

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.max_fail < 1:
            raise ValueError("epochs and max_fail must be at least 1")
        if not (self.goal >= 0.0 and self.min_gradient >= 0.0 and self.mu > 0.0 and self.theta > 1.0 and self.mu_max > self.mu):
            raise ValueError(f"invalid Levenberg-Marquardt settings {self}")


@dataclass(frozen=True)
class LMResult:
    """Where training stopped and why; ``history`` is the MSE after each epoch."""

    x: torch.Tensor
    mse: float
    epochs: int
    stop: str
    history: list[float] = field(default_factory=list)
    validation_mse: float | None = None


def levenberg_marquardt(
    residuals: Residuals,
    jacobian: Residuals,
    x0: torch.Tensor,
    settings: LMSettings = LMSettings(),
    validation: Residuals | None = None,
    on_epoch: Callable[[int, float], None] | None = None,
) -> LMResult:
    """Minimise sum(residuals(x)^2) from x0 (module docstring).

    ``jacobian(x)`` is d residuals / dx (M, P); ``validation(x)``, if given, returns the
    residuals on held-out data for early stopping; ``on_epoch(epoch, mse)`` reports progress.
    """
    x = x0.detach().clone()
    v = residuals(x)
    mse = float(v @ v) / v.numel()
    mu = settings.mu
    history: list[float] = []
    best_x, best_val, fails = x, float("inf"), 0
    if validation is not None:
        r = validation(x)
        best_val = float(r @ r) / r.numel()
    identity = torch.eye(x.numel(), dtype=x.dtype)
    stop, epoch = "epochs", 0
    while epoch < settings.epochs:
        if mse <= settings.goal:
            stop = "goal"
            break
        J = jacobian(x)
        JtJ, g = J.T @ J, J.T @ v
        if float(torch.linalg.vector_norm(2.0 * g)) / v.numel() < settings.min_gradient:
            stop = "gradient"
            break
        while True:  # steps (iii) and (iv)
            dx = torch.linalg.solve(JtJ + mu * identity, -g)
            v_new = residuals(x + dx)
            mse_new = float(v_new @ v_new) / v_new.numel()
            if mse_new < mse:
                x, v, mse = x + dx, v_new, mse_new
                mu /= settings.theta
                break
            mu *= settings.theta
            if mu > settings.mu_max:
                break
        if mu > settings.mu_max:
            stop = "mu"
            break
        epoch += 1
        history.append(mse)
        if on_epoch is not None:
            on_epoch(epoch, mse)
        if validation is not None:
            r = validation(x)
            val = float(r @ r) / r.numel()
            if val < best_val:
                best_x, best_val, fails = x, val, 0
            else:
                fails += 1
                if fails >= settings.max_fail:
                    stop = "validation"
                    break
    else:
        stop = "goal" if mse <= settings.goal else "epochs"
    validation_mse = None
    if validation is not None:
        if stop == "validation":
            x = best_x
            v = residuals(x)
            mse = float(v @ v) / v.numel()
        r = validation(x)
        validation_mse = float(r @ r) / r.numel()
    return LMResult(x, mse, epoch, stop, history, validation_mse)
