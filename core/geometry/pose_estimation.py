"""Pose from image points: planar PnP, DeMenthon's POSIT, and the Euclidean homography.

Three ways vision turns matched image points into 3-D motion:

* ``pose_from_planar_points``: cMo of a planar model (the four top-face corners) by
  IPPE (Collins & Bartoli 2014, "Infinitesimal Plane-Based Pose Estimation"), through
  OpenCV's ``solvePnP(..., SOLVEPNP_IPPE)``.
* ``pose_from_posit``: cMo of a non-planar model by POSIT (DeMenthon & Davis 1995,
  "Model-based object pose in 25 lines of code"), the thesis's choice: four coplanar
  corners plus one point off their plane.
* ``euclidean_homography`` and ``decompose_homography``: the motion between the desired
  and the current camera from the homography of the object plane (Malis, Chaumette &
  Boudet 1999, "2 1/2 D visual servoing"), which needs no model of the object.

Conventions are those of ``vservo.core.geometry.spatial`` (aMb is the pose of frame b in frame a, SI
units) and ``vservo.core.geometry.camera`` (OpenCV camera frame: z forward, x right, y down). Image
points are pixels with distortion (``*_px``) or undistorted normalized coordinates
(``*_xn``, x = X/Z, y = Y/Z). A row of NaN is an unseen point (``vservo.core.perception.features`` keeps
lost features as NaN); the pose functions leave such rows out and raise
``PoseEstimationError`` only when too few points remain.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike

from vservo.core.errors import VservoError
from vservo.core.geometry.camera import CameraModel, as_points
from vservo.core.geometry.spatial import Matrix, transform

# A model is planar when its thinnest extent (third singular value of the centred points)
# is below this fraction of its largest one. Beyond 1e-6 POSIT's pose is already swamped
# by any image noise, and IPPE would silently fit a plane through a solid.
_PLANAR_RTOL = 1e-6

# Points (or correspondences) whose spread is below this fraction of the largest one
# are degenerate: collinear for the plane-based methods, a repeated point for the DLT.
_DEGENERATE_RTOL = 1e-9


class PoseEstimationError(VservoError, ValueError):
    """The image points do not determine a pose; the message says why."""


# --- input checks ------------------------------------------------------------------------


def _correspondences(
    image: ArrayLike, object_points: ArrayLike, camera: CameraModel, image_name: str
) -> tuple[Matrix, Matrix, int]:
    """Undistorted normalized image points (M, 2), their model points (M, 3), and N.

    The M rows kept are those seen and undistorted (the camera model gives NaN where its
    lens model folds over). Object points are the model: a non-finite one is an error,
    not an unseen feature.
    """
    try:
        image = as_points(image, 2, image_name)
        object_points = as_points(object_points, 3, "object_points_o")
    except ValueError as error:
        raise PoseEstimationError(str(error)) from None
    if len(image) != len(object_points):
        raise PoseEstimationError(
            f"{image_name} has {len(image)} points but object_points_o has {len(object_points)}; they must correspond row by row"
        )
    if not np.all(np.isfinite(object_points)):
        raise PoseEstimationError("object_points_o must be finite (the model has no unseen points)")
    xn = camera.pixel_to_normalized(image)
    seen = np.all(np.isfinite(xn), axis=1)
    return xn[seen], object_points[seen], len(image)


def _require_points(count: int, seen: int, total: int, method: str) -> None:
    if seen < count:
        unseen = f" ({total - seen} of {total} are NaN or not finite)" if seen < total else ""
        raise PoseEstimationError(f"{method} needs at least {count} finite points, got {seen}{unseen}")


def _singular_values(points: Matrix) -> Matrix:
    """Singular values of the points about their centroid: their extent along the principal axes."""
    return np.linalg.svd(points - points.mean(axis=0), compute_uv=False)


def _nearest_rotation(M: ArrayLike) -> Matrix:
    """The rotation closest to M in the Frobenius norm (orthogonal Procrustes, via the SVD).

    With M = U S V^T it is U diag(1, 1, det(U V^T)) V^T; the determinant correction keeps
    it a proper rotation even when M is singular or a reflection.
    """
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


# --- planar PnP --------------------------------------------------------------------------


def pose_from_planar_points(corners_px: ArrayLike, object_points_o: ArrayLike, camera: CameraModel) -> Matrix:
    """cMo of a planar model from N >= 4 of its points seen in pixels.

    Candidates from IPPE (Collins & Bartoli 2014: the pose from the first-order expansion
    of the plane's homography, two of them for a plane seen almost orthographically) and
    from SQPnP (Terzakis & Lourakis 2020, globally optimal), each refined by
    Levenberg-Marquardt on the reprojection error; the pose in front of the camera with
    the smallest error wins.

    The pixels are undistorted with the camera model (``camera.pixel_to_normalized``, Newton
    to 1e-14) and handed to OpenCV with K = I and no distortion. That is the same camera
    model as passing K and the distortion coefficients, but OpenCV's own undistortion
    runs a fixed few iterations and leaves pose errors of a few 1e-6 rad with a strong
    lens; ours leaves ~1e-12.

    corners_px: (N, 2) pixels, distortion included; NaN rows (unseen) are left out.
    object_points_o: (N, 3) coplanar model points in the object frame O, any plane.
    Raises PoseEstimationError with fewer than 4 finite points, non-coplanar or collinear
    model points, or when OpenCV finds no pose.
    """
    xn, object_points, total = _correspondences(corners_px, object_points_o, camera, "corners_px")
    _require_points(4, len(xn), total, "planar PnP (IPPE)")

    extent = _singular_values(object_points)
    if extent[2] > _PLANAR_RTOL * extent[0]:
        raise PoseEstimationError(
            f"object_points_o are not coplanar (out-of-plane extent {extent[2]:.3g} m against "
            f"{extent[0]:.3g} m in plane); use pose_from_posit for a non-planar model"
        )
    if extent[1] <= _DEGENERATE_RTOL * extent[0]:
        raise PoseEstimationError("object_points_o are collinear: they span no plane")

    image = xn.reshape(-1, 1, 2)
    model = object_points.reshape(-1, 1, 3)
    # IPPE's two closed-form poses lose precision as the plane turns to face the camera
    # (NaN when it faces it exactly, as a taught view does); SQPnP is globally optimal
    # for any layout. Every candidate is polished by Levenberg-Marquardt on the
    # reprojection error and the best one kept.
    candidates = []
    for flags in (cv2.SOLVEPNP_IPPE, cv2.SOLVEPNP_SQPNP):
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(model, image, np.eye(3), None, flags=flags)
        candidates += [(r, t) for r, t in zip(rvecs[:count], tvecs[:count]) if np.all(np.isfinite(r)) and np.all(np.isfinite(t))]
    best, best_error = None, np.inf
    for rvec, tvec in candidates:
        rvec, tvec = cv2.solvePnPRefineLM(model, image, np.eye(3), None, rvec.copy(), tvec.copy())
        projected, _ = cv2.projectPoints(model, rvec, tvec, np.eye(3), None)
        error = float(np.sum((projected.reshape(-1, 2) - xn) ** 2))
        if tvec.ravel()[2] > 0 and error < best_error:
            best, best_error = (rvec, tvec), error
    if best is None:
        raise PoseEstimationError("OpenCV's IPPE and SQPnP found no pose in front of the camera for these points")
    rvec, tvec = best
    R, _ = cv2.Rodrigues(rvec)
    return transform(R, tvec.ravel())


# --- POSIT -------------------------------------------------------------------------------


def pose_from_posit(
    image_px: ArrayLike,
    object_points_o: ArrayLike,
    camera: CameraModel,
    iterations: int = 100,
    tolerance: float = 1e-12,
) -> Matrix:
    """cMo of a non-planar model from N >= 4 points by POSIT (DeMenthon & Davis 1995).

    With the first model point M0 as reference, f = 1 (normalized coordinates x, y) and
    i, j, k the rows of cRo, each other point Mi satisfies exactly

        M0Mi . I = x_i (1 + eps_i) - x_0,   M0Mi . J = y_i (1 + eps_i) - y_0,

    with I = i / Z0, J = j / Z0 and eps_i = M0Mi . k / Z0 (Z0 is the depth of M0).
    POS (Pose from Orthography and Scaling) fixes eps_i, solves both linear systems in
    least squares with the pseudo-inverse B of the object matrix A (rows M0Mi), and reads
    off s = (|I| + |J|) / 2 = 1 / Z0, i = I/|I|, j = J/|J|, k = i x j and
    cT0 = (x_0, y_0, 1) / s. POSIT starts from eps_i = 0 (scaled orthography) and
    repeats POS with the eps_i of the last pose until they change by less than
    ``tolerance``; the exact perspective pose is a fixed point, reached in a few
    iterations when the object is small against its distance. After at most
    ``iterations`` POS steps the last pose is returned (with noisy points the fixed point
    is not an exact pose anyway); the rotation is then projected onto SO(3) with the SVD,
    because i and j come out orthogonal only at an exact fixed point.

    The points are relative to M0 as in the paper, but the result is the pose of the
    object frame O: cMo = (R, cT0 - R oM0).

    image_px: (N, 2) pixels, distortion included; NaN rows (unseen) are left out and the
      first remaining point is the reference.
    object_points_o: (N, 3) model points in O, not all in one plane (A of rank 3).
    Raises PoseEstimationError with fewer than 4 finite points, coplanar model points
    (POSIT's linear systems are then underdetermined; the coplanar variant is Oberkampf,
    DeMenthon & Davis 1996, or use pose_from_planar_points), or a pose that is not finite.
    """
    if iterations < 1:
        raise ValueError(f"iterations must be at least 1, got {iterations}")
    if not tolerance >= 0.0:
        raise ValueError(f"tolerance must be non-negative, got {tolerance}")
    xn, object_points, total = _correspondences(image_px, object_points_o, camera, "image_px")
    _require_points(4, len(xn), total, "POSIT")

    A = object_points[1:] - object_points[0]  # object matrix, rows M0Mi
    extent = np.linalg.svd(A, compute_uv=False)
    if extent[2] <= _PLANAR_RTOL * extent[0]:
        raise PoseEstimationError(
            "POSIT needs object points that are not all coplanar: the object matrix has rank < 3 "
            f"(singular values {np.array2string(extent, precision=3)}); add a point off the plane "
            "or use pose_from_planar_points"
        )
    B = np.linalg.pinv(A)  # object matrix pseudo-inverse, 3 x (N - 1)

    x0, y0 = xn[0]
    eps = np.zeros(len(A))
    for _ in range(iterations):
        # The paper's I = i / Z0 and J = j / Z0, in least squares.
        vec_I = B @ (xn[1:, 0] * (1.0 + eps) - x0)
        vec_J = B @ (xn[1:, 1] * (1.0 + eps) - y0)
        norm_I, norm_J = np.linalg.norm(vec_I), np.linalg.norm(vec_J)
        if not (np.isfinite(norm_I) and np.isfinite(norm_J) and norm_I > 0.0 and norm_J > 0.0):
            raise PoseEstimationError("POSIT diverged: the image points admit no scaled orthographic pose")
        scale = (norm_I + norm_J) / 2.0  # s = f / Z0
        i, j = vec_I / norm_I, vec_J / norm_J
        k = np.cross(i, j)
        depth_0 = 1.0 / scale
        eps_new = A @ k / depth_0
        converged = np.max(np.abs(eps_new - eps)) <= tolerance
        eps = eps_new
        if converged:
            break

    R = _nearest_rotation(np.vstack((i, j, k)))
    c_t_0 = np.array([x0, y0, 1.0]) * depth_0  # position of M0 in the camera frame
    return transform(R, c_t_0 - R @ object_points[0])


# --- homography --------------------------------------------------------------------------


def _homogeneous(xn: Matrix) -> Matrix:
    return np.column_stack((xn, np.ones(len(xn))))


def _similarity_normalization(xn: Matrix) -> Matrix:
    """Hartley's conditioning: centroid to the origin, mean distance sqrt(2)."""
    centroid = xn.mean(axis=0)
    spread = np.mean(np.linalg.norm(xn - centroid, axis=1))
    if spread <= 0.0:
        raise PoseEstimationError("all points coincide: no homography")
    scale = np.sqrt(2.0) / spread
    return np.array([[scale, 0.0, -scale * centroid[0]], [0.0, scale, -scale * centroid[1]], [0.0, 0.0, 1.0]])


def _euclidean_scale(H: Matrix, desired_xn: Matrix) -> Matrix:
    """H / sigma_2(H) with the sign that makes (H m*)_z > 0 for every desired point.

    A Euclidean homography H = R + t n^T has middle singular value 1 (Zhang & Hanson 1996;
    Malis & Vargas 2007), and (H m*)_z = Z / Z* is positive for points in front of both
    cameras. These two conditions fix the scale of an H known up to a factor.
    """
    sigma = np.linalg.svd(H, compute_uv=False)
    if not sigma[1] > 0.0:
        raise PoseEstimationError(f"the homography has rank < 2 (singular values {sigma}): no motion")
    H = H / sigma[1]
    depth_ratio = (H @ _homogeneous(desired_xn).T)[2]
    if np.all(depth_ratio > 0.0):
        return H
    if np.all(depth_ratio < 0.0):
        return -H
    raise PoseEstimationError("(H m*)_z changes sign across the points: no sign of H puts them all in front of both cameras")


def _matched_normalized(desired_xn: ArrayLike, current_xn: ArrayLike) -> tuple[Matrix, Matrix]:
    try:
        desired_xn = as_points(desired_xn, 2, "desired_xn")
        current_xn = as_points(current_xn, 2, "current_xn")
    except ValueError as error:
        raise PoseEstimationError(str(error)) from None
    if len(desired_xn) != len(current_xn):
        raise PoseEstimationError(
            f"desired_xn has {len(desired_xn)} points but current_xn has {len(current_xn)}; they must correspond row by row"
        )
    seen = np.all(np.isfinite(desired_xn), axis=1) & np.all(np.isfinite(current_xn), axis=1)
    _require_points(4, int(seen.sum()), len(seen), "the homography")
    return desired_xn[seen], current_xn[seen]


def euclidean_homography(desired_xn: ArrayLike, current_xn: ArrayLike) -> Matrix:
    """The Euclidean homography H of the object plane, m ~ H m*, from N >= 4 point pairs.

    desired_xn, current_xn: (N, 2) undistorted normalized coordinates of the same plane
    points at the desired and the current camera pose; rows with NaN in either are left out.

    For a plane n*^T X* = d* (desired camera frame) and the motion X = cRc* X* + ct_c*,
    Z m = Z* (cRc* + ct_c* n*^T / d*) m*. H is estimated by the normalized DLT (Hartley &
    Zisserman 2003, Alg. 4.2: condition both point sets, take the null vector of the 2N x 9
    system, undo the conditioning) and scaled to be that Euclidean homography
    H = cRc* + (ct_c* / d*) n*^T (Malis, Chaumette & Boudet 1999): middle singular value 1
    and (H m*)_z = Z / Z* > 0 for every point.

    Raises PoseEstimationError with fewer than 4 finite pairs, a degenerate configuration
    (three of four points collinear, all points on a line), or pairs that no homography
    puts in front of both cameras.
    """
    desired_xn, current_xn = _matched_normalized(desired_xn, current_xn)
    T_d = _similarity_normalization(desired_xn)
    T_c = _similarity_normalization(current_xn)
    p = (T_d @ _homogeneous(desired_xn).T).T  # conditioned m*
    q = (T_c @ _homogeneous(current_xn).T).T  # conditioned m
    # q x (Hn p) = 0: two independent rows per pair in the 9 entries of Hn, row-major.
    zeros = np.zeros_like(p)
    rows_u = np.hstack((zeros, -q[:, 2:3] * p, q[:, 1:2] * p))
    rows_v = np.hstack((q[:, 2:3] * p, zeros, -q[:, 0:1] * p))
    system = np.vstack((rows_u, rows_v))
    _, sigma, Vt = np.linalg.svd(system)
    if sigma[7] <= _DEGENERATE_RTOL * sigma[0]:
        raise PoseEstimationError(
            "the point pairs do not determine a homography (three of four points collinear, or all points on one line)"
        )
    Hn = Vt[8].reshape(3, 3)
    H = np.linalg.solve(T_c, Hn @ T_d)
    return _euclidean_scale(H, desired_xn)


@dataclass(frozen=True)
class HomographyMotion:
    """One decomposition H = cRc* + t_over_d n*^T of a Euclidean homography.

    cRcd: (3, 3) rotation of the desired camera frame C* in the current frame C, cRc*.
    t_over_d: (3,) ct_c* / d*, the position of C*'s origin in C over the plane distance.
    normal_d: (3,) unit normal n* of the plane in C*, pointing from the camera towards
      the plane, so that n*^T X* = d* > 0 for the plane points X*.
    H: (3, 3) the Euclidean homography decomposed (middle singular value 1).
    """

    cRcd: Matrix
    t_over_d: Matrix
    normal_d: Matrix
    H: Matrix

    def depth_ratio(self, desired_xn: ArrayLike) -> Matrix:
        """Z / Z* = (H m*)_z for each desired point (N, 2) or (2,): its depth now over then."""
        m_star = _homogeneous(as_points(desired_xn, 2, "desired_xn"))
        return (self.H @ m_star.T)[2]

    def cMcd(self, plane_distance_d: float) -> Matrix:
        """cMc*, the pose of the desired camera frame in the current one, given d* in metres."""
        return transform(self.cRcd, self.t_over_d * plane_distance_d)


def _motion_from_normal(H: Matrix, normal: Matrix) -> tuple[Matrix, Matrix]:
    """(R, t) with H = R + t n^T for a known unit normal n.

    Every vector b orthogonal to n is mapped by H as by R, so R is the rotation closest to
    H (I - n n^T) (the determinant correction of the SVD projection fixes R n), and then
    t = (H - R) n. With a normal off by delta the error in R and t is of order |t| delta.
    """
    R = _nearest_rotation(H @ (np.eye(3) - np.outer(normal, normal)))
    return R, (H - R) @ normal


def homography_solutions(H: ArrayLike, desired_xn: ArrayLike, normal_hint_d: ArrayLike) -> tuple[HomographyMotion, ...]:
    """The physically valid decompositions of H, the one nearest the hint first.

    OpenCV's ``decomposeHomographyMat`` (the analytic method of Malis & Vargas 2007) gives
    four solutions in two pairs (R_a, t_a, n_a), (R_a, -t_a, -n_a), (R_b, t_b, n_b),
    (R_b, -t_b, -n_b); its n is our convention's n* up to that sign (H = R + t n^T, with
    n^T X* = d* > 0 for the true one), so the sign is settled by visibility. Kept are
    the solutions for which every desired point lies in front of the desired camera on
    that plane (n*^T m* = d* / Z* > 0) and in front of the current one
    (Z / Z* = (H m*)_z > 0, and the plane distance d / d* = 1 + n*^T cRc*^T t / d* > 0,
    the current camera on the same side of the plane). In general two solutions survive,
    both reproducing the images exactly: the homography of four coplanar points cannot
    tell the true plane and motion from the "mirror" one. They are sorted by the cosine
    between their normal and ``normal_hint_d``, largest first.

    Near H = I (entries of H^T H - I below ~1e-3) OpenCV declares a pure rotation and returns R = H,
    t = 0, n = 0, which is neither a rotation nor, for small translations, accurate. There
    the normal cannot be observed from H (its effect t n^T is of the order of image
    noise), so the hint is taken as the normal and (R, t) fitted to it exactly
    (``_motion_from_normal``): a single solution with an error of order |t/d*| times the
    hint's angular error, and R = I, t = 0 exactly when H = I.

    H: (3, 3) homography m ~ H m*, rescaled here to be Euclidean (see euclidean_homography).
    desired_xn: (N, 2) undistorted normalized desired points of the plane (NaN rows ignored).
    normal_hint_d: (3,) approximate plane normal in the desired camera frame, any length.
    Raises PoseEstimationError when no decomposition is physically valid.
    """
    H = np.asarray(H, dtype=float)
    if H.shape != (3, 3) or not np.all(np.isfinite(H)):
        raise PoseEstimationError(f"H must be a finite 3 x 3 matrix, got shape {H.shape}")
    try:
        desired_xn = as_points(desired_xn, 2, "desired_xn")
    except ValueError as error:
        raise PoseEstimationError(str(error)) from None
    desired_xn = desired_xn[np.all(np.isfinite(desired_xn), axis=1)]
    if len(desired_xn) == 0:
        raise PoseEstimationError("desired_xn has no finite point to check visibility against")
    hint = np.asarray(normal_hint_d, dtype=float)
    if hint.shape != (3,) or not np.all(np.isfinite(hint)) or not np.linalg.norm(hint) > 0.0:
        raise PoseEstimationError(f"normal_hint_d must be a finite non-zero (3,) vector, got {normal_hint_d!r}")
    hint = hint / np.linalg.norm(hint)
    H = _euclidean_scale(H, desired_xn)
    m_star = _homogeneous(desired_xn)

    _, rotations, translations, normals = cv2.decomposeHomographyMat(H, np.eye(3))
    candidates = []
    for R, t, n in zip(rotations, translations, normals):
        n = np.asarray(n, dtype=float).ravel()
        if np.linalg.norm(n) < 0.5:  # OpenCV's pure-rotation answer (n = 0)
            candidates.append((*_motion_from_normal(H, hint), hint))
        else:
            candidates.append((np.asarray(R, dtype=float), np.asarray(t, dtype=float).ravel(), n / np.linalg.norm(n)))

    solutions = []
    for R, t, n in candidates:
        in_front_desired = np.all(m_star @ n > 0.0)
        in_front_current = np.all(((R + np.outer(t, n)) @ m_star.T)[2] > 0.0) and 1.0 + n @ R.T @ t > 0.0
        if in_front_desired and in_front_current:
            solutions.append(HomographyMotion(cRcd=R, t_over_d=t, normal_d=n, H=H))
    if not solutions:
        raise PoseEstimationError(
            "no decomposition of H puts the points in front of both cameras "
            "(or, with H near identity, the normal hint does not face the points)"
        )
    return tuple(sorted(solutions, key=lambda s: -float(s.normal_d @ hint)))


def decompose_homography(H: ArrayLike, desired_xn: ArrayLike, normal_hint_d: ArrayLike) -> HomographyMotion:
    """The decomposition of H whose plane normal is nearest ``normal_hint_d``.

    Of the (in general two) physically valid solutions of ``homography_solutions`` the
    one whose n* makes the smallest angle with the hint. Teaching provides the hint from
    the object pose estimated at the desired view: the model plane's normal z_o in C*,
    +-c*Ro z_o with the sign that makes n*^T X* > 0 (n* towards the plane); the two solutions'
    normals are in general far apart, so a rough hint suffices. The choice is made once
    per call: a hint between the two normals picks whichever is nearer, and a hint
    pointing away from the true normal picks the mirror solution.
    """
    return homography_solutions(H, desired_xn, normal_hint_d)[0]
