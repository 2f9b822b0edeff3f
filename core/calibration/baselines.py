"""The classical calibrations the NN is compared with, fitted on the same data.

Each gives the world (x, y) of a pixel seen from a reported end-effector pose, as the
NN does, so one PBVS law and one evaluation serve all.

- ``FreeHandEye`` (section 1.2.2.2, Zhuang's free hand-eye calibration): the camera is
  calibrated at ONE pose A with Tsai's model (pinhole and first-order radial distortion
  k1; from a single, nearly fronto-parallel view of a plane the focal length cannot be
  told from the distance, so the data-sheet focal length and principal point are kept,
  as Tsai's coplanar method keeps the sensor data), which maps pixels to the table at A.
  Seen from B, a pixel's world point is that map plus the end-effector offset
  (X_B, Y_B) = (X_A, Y_A) + (X_e, Y_e), with the offset from the robot's readings. No
  hand-eye transform is estimated.
- ``HandEyeAXXB``: a full camera calibration (OpenCV, k1 k2 p1 p2 k3) on views taken
  with wrist rotations, each view's board pose, and the hand-eye transform eMc from
  AX = XB (Park and Martin's closed form, ``solve_axxb``); the board's pose in B is the mean of
  bMe eMc cMw over the views. A pixel's world point is its ray from bMe eMc cut with
  the board plane. The analogue of the thesis's "Motai" method (a hand-eye calibration
  that solves AX = XB with a distortion model). Planar moves alone are degenerate for
  it (every rotation is the same), hence the separate rotated views.
- ``PlanarHomography``: the strongest simple model for planar moves at a fixed
  orientation: the same full camera calibration to undistort, then ONE homography from
  undistorted normalised coordinates to the world offset from the end effector,
  (x_W, y_W) - (T_x, T_y), least squares over every corner of the planar dataset. It is
  exact for a perfect arm at constant height and orientation whatever the camera's
  tilt and offset, so only what the arm's readings get wrong is left to it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from vservo.core.calibration.board_views import table_points
from vservo.core.calibration.dataset import CalibrationDataset
from vservo.core.calibration.storage import CalibrationFileError, read_archive, write_archive
from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics
from vservo.core.geometry.spatial import Matrix, inverse, theta_u, transform

KIND = "vservo classical calibration"


class PlanarCalibration(Protocol):
    """What every calibration offers the PBVS law and the evaluation."""

    name: str

    def world_of(self, pixels_px: Matrix, bMe: Matrix) -> Matrix:
        """World (x, y) (N, 2) in m of pixels (N, 2) seen from reported poses bMe (N, 4, 4)."""
        ...


def _object_points(world_m: Matrix) -> Matrix:
    return np.column_stack((world_m, np.zeros(len(world_m)))).astype(np.float32)


def _camera(K: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> CameraModel:
    d = np.ravel(dist)
    intrinsics = Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(size[0]), int(size[1]))
    return CameraModel(intrinsics, Distortion(*(float(v) for v in d[:5])))


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> Matrix:
    return transform(cv2.Rodrigues(rvec)[0], np.ravel(tvec))


def calibrate_camera(views: CalibrationDataset, nominal: CameraModel) -> tuple[CameraModel, list[Matrix], float]:
    """OpenCV camera calibration over the views of a dataset (k1 k2 p1 p2 k3), started at
    the nominal intrinsics: the camera, each view's cMw, and the RMS reprojection error (px)."""
    objects, images = [], []
    for k in range(views.views):
        rows = views.view == k
        objects.append(_object_points(views.world_m[rows]))
        images.append(views.pixels_px[rows].astype(np.float32))
    if len(objects) < 3:
        raise ValueError(f"camera calibration needs at least 3 views, the dataset has {len(objects)}")
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        objects, images, nominal.image_size, nominal.intrinsics.K.copy(), np.zeros(5), flags=cv2.CALIB_USE_INTRINSIC_GUESS
    )
    return _camera(K, dist, nominal.image_size), [_pose(r, t) for r, t in zip(rvecs, tvecs)], float(rms)


def _mean_pose(poses: list[Matrix]) -> Matrix:
    """The chordal mean of rigid poses: mean translation, rotation projected back onto SO(3)."""
    U, _, Vt = np.linalg.svd(np.mean([M[:3, :3] for M in poses], axis=0))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return transform(R, np.mean([M[:3, 3] for M in poses], axis=0))


def solve_axxb(bMe: list[Matrix], cMw: list[Matrix]) -> Matrix:
    """eMc from AX = XB over every pair of views (Park and Martin 1994, closed form).

    A = eiMej = bMe_i^-1 bMe_j is the flange's motion, B = ciMcj = cMw_i cMw_j^-1 the
    camera's, and X = eMc. The rotation vectors satisfy alpha = R_X beta: R_X is the
    orthogonal Procrustes fit of the betas onto the alphas; then
    (R_A - I) t_X = R_X t_B - t_A, stacked, by least squares. (This is OpenCV's
    CALIB_HAND_EYE_PARK; the Python wheel of OpenCV 5.0 no longer exports
    cv2.calibrateHandEye.) Needs rotations about at least two different axes.
    """
    pairs = [(i, j) for i in range(len(bMe)) for j in range(i + 1, len(bMe))]
    A = [inverse(bMe[i]) @ bMe[j] for i, j in pairs]
    B = [cMw[i] @ inverse(cMw[j]) for i, j in pairs]
    alpha = np.array([theta_u(M[:3, :3]) for M in A])
    beta = np.array([theta_u(M[:3, :3]) for M in B])
    if np.linalg.matrix_rank(alpha, tol=1e-3) < 2:
        raise ValueError("the views' wrist rotations are all about one axis: AX = XB cannot find eMc")
    U, _, Vt = np.linalg.svd(beta.T @ alpha)
    R = Vt.T @ np.diag([1.0, 1.0, np.linalg.det(Vt.T @ U.T)]) @ U.T
    lhs = np.concatenate([M[:3, :3] - np.eye(3) for M in A])
    rhs = np.concatenate([R @ Mb[:3, 3] - Ma[:3, 3] for Ma, Mb in zip(A, B)])
    return transform(R, np.linalg.lstsq(lhs, rhs, rcond=None)[0])


@dataclass(frozen=True)
class FreeHandEye:
    """Tsai-model camera calibration at one pose A plus end-effector offsets (module docstring)."""

    camera: CameraModel
    wMc_A: Matrix
    T_A: Matrix
    name = "free_hand_eye"

    @classmethod
    def fit(cls, planar: CalibrationDataset, nominal: CameraModel) -> FreeHandEye:
        """Calibrate at the viewpoint nearest the middle of the planar dataset's viewpoints."""
        positions = planar.bMe[:, :3, 3]
        counts = np.bincount(planar.view, minlength=planar.views)
        distance = np.linalg.norm(positions[:, :2] - positions[:, :2].mean(axis=0), axis=1)
        view_A = int(np.argmin(np.where(counts > 0, distance, np.inf)))
        rows = planar.view == view_A
        flags = (
            cv2.CALIB_USE_INTRINSIC_GUESS
            | cv2.CALIB_FIX_FOCAL_LENGTH
            | cv2.CALIB_FIX_PRINCIPAL_POINT
            | cv2.CALIB_FIX_ASPECT_RATIO
            | cv2.CALIB_ZERO_TANGENT_DIST
            | cv2.CALIB_FIX_K2
            | cv2.CALIB_FIX_K3
        )
        _, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [_object_points(planar.world_m[rows])],
            [planar.pixels_px[rows].astype(np.float32)],
            nominal.image_size,
            nominal.intrinsics.K.copy(),
            np.zeros(5),
            flags=flags,
        )
        return cls(_camera(K, dist, nominal.image_size), inverse(_pose(rvecs[0], tvecs[0])), planar.bMe[view_A, :3, 3].copy())

    def world_of(self, pixels_px: Matrix, bMe: Matrix) -> Matrix:
        offset = bMe[:, :2, 3] - self.T_A[:2]
        return table_points(self.camera, self.wMc_A, pixels_px) + offset


@dataclass(frozen=True)
class HandEyeAXXB:
    """Camera calibration, eMc from AX = XB and the board's pose in B (module docstring)."""

    camera: CameraModel
    eMc: Matrix
    bMw: Matrix
    name = "axxb"

    @classmethod
    def fit(cls, rotated: CalibrationDataset, nominal: CameraModel) -> HandEyeAXXB:
        camera, cMw, _ = calibrate_camera(rotated, nominal)
        bMe = [rotated.bMe[k] for k in range(rotated.views)]
        eMc = solve_axxb(bMe, cMw)
        bMw = _mean_pose([bMe[k] @ eMc @ cMw[k] for k in range(len(bMe))])
        return cls(camera, eMc, bMw)

    def world_of(self, pixels_px: Matrix, bMe: Matrix) -> Matrix:
        wMb = inverse(self.bMw)
        out = np.empty((len(pixels_px), 2))
        for k, (pixel, M) in enumerate(zip(pixels_px, bMe)):
            out[k] = table_points(self.camera, wMb @ M @ self.eMc, pixel[None, :])[0]
        return out


@dataclass(frozen=True)
class PlanarHomography:
    """Undistortion, one homography to the world offset, plus the end effector (module docstring)."""

    camera: CameraModel
    H: Matrix
    name = "planar_homography"

    @classmethod
    def fit(cls, planar: CalibrationDataset, camera: CameraModel) -> PlanarHomography:
        xn = camera.pixel_to_normalized(planar.pixels_px)
        offsets = planar.world_m - planar.end_effector()[:, :2]
        H, _ = cv2.findHomography(xn, offsets, 0)
        if H is None:
            raise ValueError("no homography fits the planar dataset")
        return cls(camera, np.asarray(H, dtype=np.float64))  # (float64 already; typed as any Mat)

    def world_of(self, pixels_px: Matrix, bMe: Matrix) -> Matrix:
        xn = self.camera.pixel_to_normalized(pixels_px)
        mapped = np.column_stack((xn, np.ones(len(xn)))) @ self.H.T
        return mapped[:, :2] / mapped[:, 2:3] + bMe[:, :2, 3]


# -- files -----------------------------------------------------------------------------


def _camera_arrays(camera: CameraModel) -> dict[str, Matrix]:
    k = camera.intrinsics
    return {"K": k.K, "distortion": camera.distortion.as_opencv(), "image_size": np.array([k.width, k.height])}


def save_classical(
    calibration: FreeHandEye | HandEyeAXXB | PlanarHomography, path: str | Path, metadata: dict[str, Any] | None = None
) -> Path:
    arrays = _camera_arrays(calibration.camera)
    if isinstance(calibration, FreeHandEye):
        arrays |= {"wMc_A": calibration.wMc_A, "T_A": calibration.T_A}
    elif isinstance(calibration, HandEyeAXXB):
        arrays |= {"eMc": calibration.eMc, "bMw": calibration.bMw}
    else:
        arrays |= {"H": calibration.H}
    return write_archive(path, KIND, arrays, {"method": calibration.name, **(metadata or {})})


_FIELDS = {
    FreeHandEye.name: (FreeHandEye, ("wMc_A", "T_A")),
    HandEyeAXXB.name: (HandEyeAXXB, ("eMc", "bMw")),
    PlanarHomography.name: (PlanarHomography, ("H",)),
}


def load_classical(path: str | Path) -> FreeHandEye | HandEyeAXXB | PlanarHomography:
    arrays, meta = read_archive(path, KIND)
    method = meta.get("method")
    if method not in _FIELDS:
        raise CalibrationFileError(f"{path}: unknown classical method {method!r}")
    cls, fields = _FIELDS[method]
    for name in ("K", "distortion", "image_size", *fields):
        if name not in arrays or not np.all(np.isfinite(arrays[name])):
            raise CalibrationFileError(f"{path}: array {name} is missing or not finite")
    size = arrays["image_size"]
    camera = _camera(arrays["K"], arrays["distortion"], (int(size[0]), int(size[1])))
    return cls(camera, *(arrays[name] for name in fields))
