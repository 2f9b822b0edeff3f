"""Reference computations for the tests, written independently of vservo.core.geometry.spatial."""

import cv2
import numpy as np


def rodrigues(rvec):
    """Rotation matrix of a rotation vector, by OpenCV."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))
    return R


def homogeneous(R, t):
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = t
    return M


def random_unit(rng):
    u = rng.normal(size=3)
    return u / np.linalg.norm(u)
