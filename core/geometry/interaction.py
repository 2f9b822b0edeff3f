"""Interaction matrices (image Jacobians) of point features.

For a point fixed in the world and a camera moving with the twist (v, w) expressed in
the camera frame, the image motion of the point is s_dot = L @ (v, w). The matrix is
the one of Chaumette & Hutchinson (Visual Servo Control I, 2006) in OpenCV's camera
convention (see vservo.core.geometry.camera); thesis eq. 4-14 is the same matrix written in the
thesis's flipped image axes.

Points are stacked feature by feature: rows 2i and 2i + 1 belong to point i.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from vservo.core.geometry.camera import CameraModel, as_points
from vservo.core.geometry.spatial import Matrix


def point_interaction_matrix(xn: ArrayLike, Z: ArrayLike) -> Matrix:
    """L (2N, 6) of normalized image points xn (N, 2) or (2,) at depths Z (N,) or a scalar.

    Each point contributes the two rows
        [-1/Z,    0, x/Z,     x y, -(1 + x^2),  y]
        [   0, -1/Z, y/Z, 1 + y^2,       -x y, -x]
    Z is the point's depth in the camera frame (m) and must be positive; a scalar is
    used for every point (the usual approximation L(s*, Z*) at the desired pose).
    """
    xn = as_points(xn, 2, "xn")
    Z = np.broadcast_to(np.asarray(Z, dtype=float), (len(xn),))
    if not np.all(Z > 0.0):
        raise ValueError(f"depths Z must be positive, got {Z}")
    x, y = xn[:, 0], xn[:, 1]
    inv_Z = 1.0 / Z
    zero = np.zeros_like(x)
    L = np.empty((len(xn), 2, 6))
    L[:, 0] = np.column_stack((-inv_Z, zero, x * inv_Z, x * y, -(1.0 + x * x), y))
    L[:, 1] = np.column_stack((zero, -inv_Z, y * inv_Z, 1.0 + y * y, -x * y, -x))
    return L.reshape(-1, 6)


def pixel_interaction_matrix(camera: CameraModel, uv: ArrayLike, Z: ArrayLike) -> Matrix:
    """L (2N, 6) of pixel features uv (N, 2) or (2,) at depths Z (N,) or a scalar.

    diag(fx, fy) times the normalized matrix evaluated at the undistorted normalized
    point, so u_dot = L @ (v, w) in px/s. The Jacobian of the lens distortion itself is
    neglected, as in the thesis: it is close to identity near the image centre, and the
    servo loop only needs an estimate of L, not L itself.
    """
    k = camera.intrinsics
    L = point_interaction_matrix(camera.pixel_to_normalized(uv), Z)
    L[0::2] *= k.fx
    L[1::2] *= k.fy
    return L
