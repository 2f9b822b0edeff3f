"""Rigid-body conventions shared by every vservo module.

Names are frame-encoded as in ViSP: ``aMb`` is the 4x4 homogeneous pose of frame b
expressed in frame a (the thesis writes it aHb), ``aVb`` the 6x6 twist transform that
carries a twist expressed in b into a. Twists are ordered (v, w): linear velocity
first, then angular, the order of eq. 4-1 and of Pinocchio's ``Motion``.

Everything here is SI (m, rad). The thesis tables and the Yaskawa controllers use
(X, Y, Z, phi, theta, psi) in mm and degrees; ``pose_from_mm_deg`` and
``pose_to_mm_deg`` are the only place where those units cross into the library.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

# vservo's one array type: float arrays of any shape. As in Eigen, a vector is a matrix
# of one column, so poses, points, twists and Jacobians all read ``Matrix``.
Matrix = NDArray[np.float64]


class Pose6(NamedTuple):
    """A pose as (X, Y, Z, phi, theta, psi), with R = Rz(phi) Ry(theta) Rx(psi) (eq. 2-13).

    phi is the roll about Z, theta the pitch about Y, psi the yaw about X. A Yaskawa
    controller's (X, Y, Z, Rx, Ry, Rz) is the same pose with phi = Rz, theta = Ry,
    psi = Rx: both compose fixed-axis rotations about X, then Y, then Z.
    Units are whatever the caller holds (SI inside the library).
    """

    x: float
    y: float
    z: float
    phi: float
    theta: float
    psi: float


def skew(w: ArrayLike) -> Matrix:
    """Skew-symmetric matrix sk(w) with sk(w) @ p = w x p."""
    wx, wy, wz = np.asarray(w, dtype=float)
    return np.array([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]])


def rot_x(angle: float) -> Matrix:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> Matrix:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> Matrix:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_from_rpy(phi: float, theta: float, psi: float) -> Matrix:
    """R = Rz(phi) Ry(theta) Rx(psi), eq. 2-13."""
    return rot_z(phi) @ rot_y(theta) @ rot_x(psi)


def rpy_from_rotation(R: ArrayLike) -> tuple[float, float, float]:
    """Inverse of eq. 2-13: (phi, theta, psi) with theta in [-pi/2, pi/2].

    At the gimbal lock (|theta| = pi/2) only phi - psi (or phi + psi) is defined;
    psi is then set to 0 and phi carries the whole rotation about the vertical.
    """
    R = np.asarray(R, dtype=float)
    theta = float(np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0])))
    if np.hypot(R[0, 0], R[1, 0]) > 1e-9:
        phi = float(np.arctan2(R[1, 0], R[0, 0]))
        psi = float(np.arctan2(R[2, 1], R[2, 2]))
    else:
        psi = 0.0
        phi = float(np.arctan2(-R[0, 1], R[1, 1]))
    return phi, theta, psi


def transform(R: ArrayLike | None = None, t: ArrayLike | None = None) -> Matrix:
    """Homogeneous 4x4 matrix from a rotation and a translation (either may be omitted)."""
    M = np.eye(4)
    if R is not None:
        M[:3, :3] = np.asarray(R, dtype=float)
    if t is not None:
        M[:3, 3] = np.asarray(t, dtype=float)
    return M


def inverse(aMb: ArrayLike) -> Matrix:
    """bMa from aMb, using R^T rather than a general matrix inverse."""
    aMb = np.asarray(aMb, dtype=float)
    R, t = aMb[:3, :3], aMb[:3, 3]
    return transform(R.T, -R.T @ t)


def matrix_from_pose(pose: ArrayLike) -> Matrix:
    """aMb from (X, Y, Z, phi, theta, psi) in m and rad (eqs. 2-11 .. 2-13)."""
    x, y, z, phi, theta, psi = np.asarray(pose, dtype=float)
    return transform(rotation_from_rpy(phi, theta, psi), (x, y, z))


def pose_from_matrix(aMb: ArrayLike) -> Pose6:
    """(X, Y, Z, phi, theta, psi) in m and rad from aMb."""
    aMb = np.asarray(aMb, dtype=float)
    x, y, z = (float(v) for v in aMb[:3, 3])
    return Pose6(x, y, z, *rpy_from_rotation(aMb[:3, :3]))


def pose_from_mm_deg(values: ArrayLike) -> Pose6:
    """A pose written as mm and degrees (thesis tables, JRC wire, UI) into m and rad."""
    v = np.asarray(values, dtype=float)
    if v.shape != (6,):
        raise ValueError(f"a pose has 6 values (X, Y, Z, phi, theta, psi), got {v.shape}")
    return Pose6(*(v[:3] / 1000.0), *np.deg2rad(v[3:]))


def pose_to_mm_deg(pose: ArrayLike) -> Pose6:
    """A pose in m and rad into mm and degrees, for the edges of the system."""
    v = np.asarray(pose, dtype=float)
    return Pose6(*(v[:3] * 1000.0), *np.rad2deg(v[3:]))


def twist_transform(aMb: ArrayLike) -> Matrix:
    """aVb, the 6x6 matrix that expresses in frame a a twist (v, w) given in frame b.

    With aMb = (R, t): aVb = [[R, sk(t) R], [0, R]]. For a = E and b = C this is eq. 4-16,
    whose upper-right block -eRc sk(cTe) equals sk(eTc) eRc since cTe = -cRe eTc.
    """
    aMb = np.asarray(aMb, dtype=float)
    R, t = aMb[:3, :3], aMb[:3, 3]
    V = np.zeros((6, 6))
    V[:3, :3] = R
    V[:3, 3:] = skew(t) @ R
    V[3:, 3:] = R
    return V


def exp_twist(twist: ArrayLike) -> Matrix:
    """The rigid motion aMa' produced by holding the body twist (v, w) of frame a for unit time.

    Closed form of the SE(3) exponential (Rodrigues for R, its left Jacobian for t); a
    frame a moved by a twist expressed in a becomes ``aMb @ exp_twist(twist * dt)``.
    """
    v = np.asarray(twist, dtype=float)[:3]
    w = np.asarray(twist, dtype=float)[3:]
    angle = float(np.linalg.norm(w))
    W = skew(w)
    if angle < 1e-9:
        # Second-order series: exact to machine precision at this size.
        R = np.eye(3) + W + 0.5 * W @ W
        V = np.eye(3) + 0.5 * W
    else:
        a = np.sin(angle) / angle
        # 1 - cos(angle) cancels to 0 below ~1e-8 rad; the half-angle form does not.
        b = 0.5 * (np.sin(angle / 2.0) / (angle / 2.0)) ** 2
        c = (angle - np.sin(angle)) / angle**3
        R = np.eye(3) + a * W + b * W @ W
        V = np.eye(3) + b * W + c * W @ W
    return transform(R, V @ v)


def theta_u(R: ArrayLike) -> Matrix:
    """Rotation vector theta*u of a rotation matrix (angle in [0, pi]).

    The angle comes from atan2(sin, cos), which keeps full precision near 0 where an
    arccos of the trace cannot resolve angles below 1e-8 rad. Near pi the axis is taken
    from the symmetric part of R, where (R - R^T) / (2 sin theta) loses all precision.
    """
    R = np.asarray(R, dtype=float)
    axis_sin = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    sin_angle = float(np.linalg.norm(axis_sin))
    angle = float(np.arctan2(sin_angle, (np.trace(R) - 1.0) / 2.0))
    if angle < 1e-9:
        return axis_sin
    if angle < np.pi - 1e-4:
        return axis_sin * (angle / sin_angle)
    # R = cos I + sin sk(u) + (1 - cos) u u^T, so the symmetric part gives u u^T exactly
    # ((R + I) / 2 would keep the sin sk(u) term, an axis error of ~(pi - angle) / 2).
    cos_angle = (np.trace(R) - 1.0) / 2.0
    S = ((R + R.T) / 2.0 - cos_angle * np.eye(3)) / (1.0 - cos_angle)
    k = int(np.argmax(np.diag(S)))
    u = S[:, k] / np.sqrt(S[k, k])
    if np.dot(u, axis_sin) < 0.0:
        u = -u
    return u * angle


def rotation_angle(R: ArrayLike) -> float:
    """Angle in [0, pi] of a rotation matrix."""
    return float(np.linalg.norm(theta_u(R)))


def interpolate(aMb: ArrayLike, aMc: ArrayLike, fraction: float) -> Matrix:
    """The pose ``fraction`` of the way from aMb to aMc on the straight line: the origin
    moved linearly, the orientation turned about the fixed axis of bRc (theta-u)."""
    aMb, aMc = np.asarray(aMb, dtype=float), np.asarray(aMc, dtype=float)
    bRc = aMb[:3, :3].T @ aMc[:3, :3]
    R = aMb[:3, :3] @ exp_twist(np.concatenate([np.zeros(3), fraction * theta_u(bRc)]))[:3, :3]
    return transform(R, (1.0 - fraction) * aMb[:3, 3] + fraction * aMc[:3, 3])


def pose_error(aMb: ArrayLike, aMc: ArrayLike) -> tuple[float, float]:
    """(translation in m, rotation in rad) between two poses of the same frame."""
    aMb, aMc = np.asarray(aMb, dtype=float), np.asarray(aMc, dtype=float)
    translation = float(np.linalg.norm(aMb[:3, 3] - aMc[:3, 3]))
    return translation, rotation_angle(aMb[:3, :3].T @ aMc[:3, :3])
