"""Bounded Levenberg-Marquardt, shared by the detectors' model fits (spot, side bands).

The fits are small (a handful of parameters, a few hundred pixels) and their models
cheap, so a plain damped Gauss-Newton with box bounds is all they need: parameters held
on a bound by the step are left out of it, the others' step is clipped into the box. An
optional robust loss reweights the residuals each iteration (iteratively reweighted
least squares).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from core.spatial import Matrix

#: A model: parameters -> (residuals (N,), Jacobian (N, P)).
Model = Callable[[Matrix], tuple[Matrix, Matrix]]


def levenberg_marquardt(
    model: Model,
    params: Matrix,
    lower: Matrix,
    upper: Matrix,
    iterations: int,
    settled: Callable[[Matrix, Matrix], bool],
    loss_scale: float | None = None,
) -> tuple[Matrix, Matrix]:
    """Minimise the cost of ``model``'s residuals with the parameters within [lower, upper].

    The cost is the sum of squares, or with ``loss_scale`` s the Cauchy loss
    sum log(1 + r^2 / s^2) (residuals weighted by 1 / (1 + r^2 / s^2)). Stops after
    ``iterations`` steps, or when an accepted step from the old to the new parameters
    ``settled(old, new)``, or when the damping has grown hopeless. Returns the
    parameters and their residuals.
    """

    def cost_of(residual: Matrix) -> float:
        if loss_scale is None:
            return float(residual @ residual)
        return float(np.log1p(residual * residual / loss_scale**2).sum())

    residual, jac = model(params)
    cost = cost_of(residual)
    damping = 1e-3
    identity = np.eye(len(params))
    for _ in range(iterations):
        if loss_scale is None:
            weighted = jac
        else:
            weighted = jac * (1.0 / (1.0 + residual * residual / loss_scale**2))[:, None]
        normal, gradient = weighted.T @ jac, weighted.T @ residual
        # Marquardt's damping; a parameter no residual depends on (a zero column: a
        # taper that shapes no pixel) gets a unit diagonal, and with its zero gradient
        # no step.
        diagonal = normal.diagonal().copy()
        normal += identity * (damping * diagonal + (diagonal == 0.0))
        step = _solve(normal, gradient)
        if step is None:
            damping *= 8.0
            if damping > 1e8:
                break
            continue
        # Parameters on a bound that the step pushes further out stay there, and the
        # others take the best step without them (a clipped joint step is not that):
        # the held ones' rows and columns become the identity's, their gradient zero.
        blocked = ((params <= lower) & (step < 0.0)) | ((params >= upper) & (step > 0.0))
        if blocked.any():
            normal[blocked] = 0.0
            normal[:, blocked] = 0.0
            normal[blocked, blocked] = 1.0
            gradient = np.where(blocked, 0.0, gradient)
            step = _solve(normal, gradient)
            if step is None:
                break
        trial = np.minimum(np.maximum(params + step, lower), upper)
        residual_t, jac_t = model(trial)
        cost_t = cost_of(residual_t)
        if cost_t < cost:
            old = params
            params, residual, jac, cost = trial, residual_t, jac_t, cost_t
            damping = max(damping / 4.0, 1e-7)
            if settled(old, params):
                break
        else:
            damping *= 8.0
            if damping > 1e8:
                break
    return params, residual


def _solve(normal: Matrix, gradient: Matrix) -> Matrix | None:
    """The Gauss-Newton step -normal^-1 gradient, None when ``normal`` is singular.

    OpenCV's solver: for these few parameters np.linalg.solve's call overhead costs
    several times the arithmetic, in the fits' inner loop.
    """
    ok, step = cv2.solve(normal, -gradient[:, None], flags=cv2.DECOMP_LU)
    return step[:, 0] if ok else None
