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

from vservo.core.geometry.spatial import Matrix

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
            return float(residual.dot(residual))
        return float(np.log1p(residual * residual / loss_scale**2).sum())

    # The bookkeeping of a few parameters runs on Python floats: numpy's per-call
    # overhead would cost many times the arithmetic.
    bounds = list(zip(lower.tolist(), upper.tolist()))
    values = params.tolist()
    residual, jac = model(params)
    cost = cost_of(residual)
    damping = 1e-3
    for _ in range(iterations):
        if loss_scale is None:
            weighted = jac
        else:
            weighted = jac * (1.0 / (1.0 + residual * residual / loss_scale**2))[:, None]
        normal, gradient = weighted.T.dot(jac), weighted.T.dot(residual)
        # Marquardt's damping; a parameter no residual depends on (a zero column: a
        # taper that shapes no pixel) gets a unit diagonal, and with its zero gradient
        # no step.
        normal.flat[:: len(values) + 1] = [x + (damping * x + (x == 0.0)) for x in normal.diagonal().tolist()]
        descent = _solve(normal, gradient)  # the step's negative
        if descent is None:
            damping *= 8.0
            if damping > 1e8:
                break
            continue
        # Parameters on a bound that the step pushes further out stay there, and the
        # others take the best step without them (a clipped joint step is not that):
        # the held ones' rows and columns become the identity's, their gradient zero.
        held = [(x <= low and d > 0.0) or (x >= high and d < 0.0) for x, (low, high), d in zip(values, bounds, descent)]
        if any(held):
            blocked = np.array(held)
            normal[blocked] = 0.0
            normal[:, blocked] = 0.0
            normal[blocked, blocked] = 1.0
            descent = _solve(normal, np.where(blocked, 0.0, gradient))
            if descent is None:
                break
        trial_values = [_clip(x - d, low, high) for x, (low, high), d in zip(values, bounds, descent)]
        trial = np.array(trial_values)
        residual_t, jac_t = model(trial)
        cost_t = cost_of(residual_t)
        if cost_t < cost:
            old = params
            params, values, residual, jac, cost = trial, trial_values, residual_t, jac_t, cost_t
            damping = max(damping / 4.0, 1e-7)
            if settled(old, params):
                break
        else:
            damping *= 8.0
            if damping > 1e8:
                break
    return params, residual


def _solve(normal: Matrix, gradient: Matrix) -> list[float] | None:
    """normal^-1 gradient (the Gauss-Newton step's negative), None when ``normal`` is singular.

    OpenCV's solver: for these few parameters np.linalg.solve's call overhead costs
    several times the arithmetic, in the fits' inner loop.
    """
    ok, solution = cv2.solve(normal, gradient[:, None], flags=cv2.DECOMP_LU)
    return solution.ravel().tolist() if ok else None


def _clip(x: float, low: float, high: float) -> float:
    """``x`` within [low, high] (NaN stays NaN, as with np.minimum(np.maximum(...)))."""
    x = low if x < low else x
    return high if x > high else x
