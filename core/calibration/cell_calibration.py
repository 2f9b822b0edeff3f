"""Commissioning a cell from views of its board: the camera, the hand-eye transform and
the board's pose, the NN's data set, and the acceptance check (docs/calibration.md,
"Commissioning a cell").

Pure functions on views already taken (``board_views.find_board``); the orchestration
that moves the arm and takes the frames calls them. Each result carries its residuals and
a ``Verdict``: good, or retake with what to do differently.

1. ``calibrate_camera_views``: OpenCV's calibration (pinhole and k1 k2 p1 p2 k3) over
   tilted views of the board; each view's cMboard, the RMS reprojection error overall
   and per view, and the standard deviations of fx, fy, u0, v0.
2. ``calibrate_hand_eye``: eMc from AX = XB (``solve_axxb``), then eMc's translation
   and bMboard refined together so that every corner, carried from the board through
   the arm's reported bMe, eMc and the calibrated camera, lands on the pixel it was
   found at (Levenberg-Marquardt, eqs. 2-28 .. 2-41).
3. ``grid_dataset``: every corner's base-frame (x, y) through that bMboard, for the
   chapter 2 network.
4. ``acceptance_errors``: at check poses, where a calibrated model puts a corner's pixel
   against where the corner is.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from numpy.typing import ArrayLike

from vservo.core.calibration.baselines import PlanarCalibration, solve_axxb
from vservo.core.calibration.board_views import BoardView
from vservo.core.calibration.dataset import CalibrationDataset
from vservo.core.calibration.levenberg_marquardt import LMSettings, levenberg_marquardt
from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics
from vservo.core.geometry.spatial import Matrix, inverse, pose_error, theta_u, transform

# OpenCV needs four corners per view; fewer than this many leave a view's pose (and its
# share of the intrinsics) poorly fixed, so such a view is refused rather than used.
MIN_CORNERS_PER_VIEW = 10
# Camera: ten tilted views pin five distortion terms and four intrinsics (Zhang's rule of
# thumb); the corner detector's own error is ~0.05 px, so an RMS ten times that, or one
# view at twenty, is a blurred, moving or misnamed board. 0.2 % of fx is 0.6 mm at the
# 300 mm working distance.
MIN_CAMERA_VIEWS = 10
MAX_CAMERA_RMS_PX = 0.5
MAX_VIEW_RMS_PX = 1.0
MAX_FOCAL_STD = 0.002
MAX_PRINCIPAL_STD_PX = 1.0
# Hand-eye: AX = XB needs turns about two axes, and the more the better fixed eMc's
# rotation is; 0.2 mm of error in the arm's readings shows as ~1.2 px per corner at
# 200 mm, so beyond 2 px the board moved or the readings are worse than an arm's.
MIN_HAND_EYE_VIEWS = 8
MIN_SECOND_AXIS_DEG = 5.0
MAX_HAND_EYE_RMS_PX = 2.0
# The refinement runs until no step lowers the sum of squares (the goal of zero is never
# met): nine parameters, a few epochs.
_REFINEMENT = LMSettings(epochs=100, goal=0.0, min_gradient=1e-14)


@dataclass(frozen=True)
class Verdict:
    """Whether a step's result can be used (``good``) and why, in one line for the operator."""

    good: bool
    reason: str

    @classmethod
    def of(cls, faults: Sequence[str], summary: str) -> Verdict:
        """Good with ``summary`` when there are no faults, else retake naming every fault."""
        if faults:
            return cls(False, "retake: " + "; ".join(faults))
        return cls(True, "good: " + summary)


def read_only(array: ArrayLike) -> Matrix:
    """A read-only float copy, so that a frozen result really is frozen."""
    out = np.array(array, dtype=float)
    out.flags.writeable = False
    return out


def pose_error_mm_deg(aMb: Matrix, aMb_ref: Matrix) -> tuple[float, float]:
    """(translation in mm, rotation in deg) of aMb from aMb_ref."""
    translation_m, rotation_rad = pose_error(aMb, aMb_ref)
    return 1000.0 * translation_m, float(np.degrees(rotation_rad))


def _check_views(views: Sequence[BoardView]) -> None:
    for k, view in enumerate(views):
        if len(view) < MIN_CORNERS_PER_VIEW:
            raise ValueError(f"view {k} has {len(view)} corners: a view needs at least {MIN_CORNERS_PER_VIEW}")


# -- 1. the camera ---------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """The calibrated camera, each view's cMboard, RMS reprojection errors (px) overall and
    per view, the standard deviations (px) of fx, fy, u0, v0, and the verdict."""

    camera: CameraModel
    cMboard: tuple[Matrix, ...]
    rms_px: float
    view_rms_px: Matrix
    std_fx_px: float
    std_fy_px: float
    std_u0_px: float
    std_v0_px: float
    verdict: Verdict


def calibrate_camera_views(views: Sequence[BoardView], nominal: CameraModel) -> CameraCalibration:
    """OpenCV's calibration (``calibrateCameraExtended``, k1 k2 p1 p2 k3) over board views,
    started at the nominal intrinsics (module docstring, step 1).

    Verdict: retake with fewer than ``MIN_CAMERA_VIEWS`` views, an RMS above
    ``MAX_CAMERA_RMS_PX`` or a view above ``MAX_VIEW_RMS_PX`` (naming it), fx or fy
    uncertain to more than ``MAX_FOCAL_STD``, or u0, v0 to more than
    ``MAX_PRINCIPAL_STD_PX`` (the views are not tilted enough to tell the focal length
    from the distance, or the centre from a shift).
    """
    if len(views) < 3:
        raise ValueError(f"camera calibration needs at least 3 views, got {len(views)}")
    _check_views(views)
    objects = [v.corners_board.astype(np.float32) for v in views]
    images = [v.corners_px.astype(np.float32) for v in views]
    rms, K, dist, rvecs, tvecs, std_intrinsics, _, view_errors = cv2.calibrateCameraExtended(
        objects, images, nominal.image_size, nominal.intrinsics.K.copy(), np.zeros(5), flags=cv2.CALIB_USE_INTRINSIC_GUESS
    )
    width, height = nominal.image_size
    camera = CameraModel(
        Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height),
        Distortion(*(float(d) for d in np.ravel(dist)[:5])),
    )
    std_fx, std_fy, std_u0, std_v0 = (float(s) for s in np.ravel(std_intrinsics)[:4])
    view_rms = np.ravel(view_errors)
    faults = []
    if len(views) < MIN_CAMERA_VIEWS:
        faults.append(f"only {len(views)} views, take at least {MIN_CAMERA_VIEWS}")
    if rms > MAX_CAMERA_RMS_PX:
        faults.append(
            f"corners reproject at {rms:.2f} px RMS (at most {MAX_CAMERA_RMS_PX}): "
            "check the focus, the light and that the board lies still"
        )
    worst = int(np.argmax(view_rms))
    if view_rms[worst] > MAX_VIEW_RMS_PX:
        faults.append(f"view {worst} reprojects at {view_rms[worst]:.2f} px RMS, retake it")
    focal_std = max(std_fx / camera.intrinsics.fx, std_fy / camera.intrinsics.fy)
    if focal_std > MAX_FOCAL_STD:
        faults.append(f"fx, fy uncertain to {100 * focal_std:.2f} %, tilt the camera more")
    if max(std_u0, std_v0) > MAX_PRINCIPAL_STD_PX:
        faults.append(f"the principal point uncertain to {max(std_u0, std_v0):.1f} px, tilt the camera more, about both axes")
    verdict = Verdict.of(faults, f"RMS {rms:.3f} px over {len(views)} views, fx uncertain to {100 * focal_std:.3f} %")
    cMboard = tuple(read_only(transform(cv2.Rodrigues(r)[0], np.ravel(t))) for r, t in zip(rvecs, tvecs))
    return CameraCalibration(camera, cMboard, float(rms), read_only(view_rms), std_fx, std_fy, std_u0, std_v0, verdict)


def board_pose(camera: CameraModel, view: BoardView) -> Matrix:
    """cMboard of one view through a calibrated camera (OpenCV's iterative PnP): the
    board's pose in a view taken after the calibration, as the laser's views are."""
    _check_views([view])
    ok, rvec, tvec = cv2.solvePnP(
        view.corners_board, view.corners_px, camera.intrinsics.K, camera.distortion.as_opencv(), flags=cv2.SOLVEPNP_ITERATIVE
    )
    if not ok:
        raise ValueError("the board's pose cannot be found from the view's corners")
    return transform(cv2.Rodrigues(rvec)[0], np.ravel(tvec))


# -- 2. hand-eye and the board's pose ----------------------------------------------------


@dataclass(frozen=True, eq=False)
class HandEyeCalibration:
    """eMc and bMboard refined together, through ``camera``.

    ``eMc_axxb`` is the closed-form start; ``rms_px`` the corners' reprojection RMS through
    the arm's poses; ``spread_mm``, ``spread_deg`` the RMS distance of each view's own
    bMe eMc cMboard from ``bMboard``; ``turn_deg`` the RMS turn of the wrist about the
    principal axes of its rotations (largest first: the second says whether AX = XB was
    well posed). As a ``PlanarCalibration`` it puts a pixel on the board plane.
    """

    camera: CameraModel
    eMc: Matrix
    bMboard: Matrix
    eMc_axxb: Matrix
    rms_px: float
    spread_mm: float
    spread_deg: float
    turn_deg: tuple[float, float, float]
    verdict: Verdict
    name = "hand_eye"

    def world_of(self, pixels_px: Matrix, bMe: Matrix) -> Matrix:
        """Base (x, y) (N, 2) where the rays through pixels (N, 2), seen from bMe (N, 4, 4),
        meet the board plane; NaN where a ray does not reach it."""
        return BoardPlaneModel(self.camera, self.eMc, self.bMboard).world_of(pixels_px, bMe)


@dataclass(frozen=True, eq=False)
class BoardPlaneModel:
    """A calibrated camera, hand-eye and board plane as a ``PlanarCalibration``: a pixel
    seen from bMe is its ray from bMe eMc met with the board plane (what the acceptance
    check holds any calibrated model to)."""

    camera: CameraModel
    eMc: Matrix
    bMboard: Matrix
    name = "board_plane"

    def world_of(self, pixels_px: Matrix, bMe: Matrix) -> Matrix:
        """Base (x, y) (N, 2) where the rays through pixels (N, 2), seen from bMe (N, 4, 4),
        meet the board plane; NaN where a ray does not reach it."""
        pixels_px = np.atleast_2d(np.asarray(pixels_px, dtype=float))
        normal_b, origin_b = self.bMboard[:3, 2], self.bMboard[:3, 3]
        out = np.full((len(pixels_px), 2), np.nan)
        rays_c = np.column_stack((self.camera.pixel_to_normalized(pixels_px), np.ones(len(pixels_px))))
        for k, (ray_c, M) in enumerate(zip(rays_c, np.asarray(bMe, dtype=float).reshape(-1, 4, 4))):
            bMc = M @ self.eMc
            ray_b = bMc[:3, :3] @ ray_c
            with np.errstate(divide="ignore", invalid="ignore"):
                s = float(normal_b @ (origin_b - bMc[:3, 3])) / float(normal_b @ ray_b)
            if s > 0.0:
                out[k] = (bMc[:3, 3] + s * ray_b)[:2]
        return out


def _exp_so3(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a rotation vector (exact, and differentiable at zero)."""
    zero = torch.zeros((), dtype=w.dtype)
    W = torch.stack([torch.stack([zero, -w[2], w[1]]), torch.stack([w[2], zero, -w[0]]), torch.stack([-w[1], w[0], zero])])
    return torch.linalg.matrix_exp(W)


def _perturbed(M0: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """M0 turned by the rotation vector x[:3] in its own frame and moved by x[3:]."""
    top = torch.cat([M0[:3, :3] @ _exp_so3(x[:3]), (M0[:3, 3] + x[3:]).unsqueeze(1)], dim=1)
    return torch.cat([top, M0[3:]], dim=0)


def _project(camera: CameraModel, cP: torch.Tensor) -> torch.Tensor:
    """Pixels (N, 2) of camera-frame points (N, 3): ``CameraModel.project`` in torch."""
    k, d = camera.intrinsics, camera.distortion
    x, y = cP[:, 0] / cP[:, 2], cP[:, 1] / cP[:, 2]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
    xd = x * radial + 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x)
    yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y
    return torch.stack([k.fx * xd + k.u0, k.fy * yd + k.v0], dim=1)


def _wrist_turns_deg(bMe: Sequence[Matrix]) -> tuple[float, float, float]:
    """RMS turn (deg) of the flange's orientations about the principal axes of their
    spread around the mean orientation, largest first."""
    U, _, Vt = np.linalg.svd(np.sum([M[:3, :3] for M in bMe], axis=0))
    mean = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    turns = np.array([theta_u(mean.T @ M[:3, :3]) for M in bMe])
    spread = np.linalg.svd(turns, compute_uv=False) / np.sqrt(len(bMe))
    a, b, c = (float(np.degrees(s)) for s in spread)
    return a, b, c


def calibrate_hand_eye(
    bMe_list: Sequence[Matrix], views: Sequence[BoardView], camera: CameraModel, cMboard_list: Sequence[Matrix]
) -> HandEyeCalibration:
    """eMc and bMboard from the arm's reported poses and the board's views (module
    docstring, step 2).

    The closed form X of AX = XB with A = bMe_i^-1 bMe_j and B = cMboard_i cMboard_j^-1
    gives eMc. Its rotation is kept: it comes from the rotations alone, which the arm
    reports to hundredths of a degree, while in the image a small turn of the camera about
    the board's centre, taken up by a shift, changes almost nothing (the board is a few
    centimetres wide seen from twenty): fitted to the pixels, that turn would absorb the
    arm's position errors (0.2 deg of eMc for 0.2 mm of reading error, against 0.07 deg
    kept). eMc's translation and bMboard (9 parameters) are then refined together by
    Levenberg-Marquardt (eqs. 2-28 .. 2-41), minimising the reprojection of every corner,
        p_n - project(camera, (bMe_k eMc)^-1 bMboard P_n),
    which weighs each view by what it shows. A ValueError when the views cannot fix eMc
    (fewer than 3, or every turn about one axis). Verdict: retake with fewer than
    ``MIN_HAND_EYE_VIEWS`` views, a second turning axis below ``MIN_SECOND_AXIS_DEG``,
    or a corner RMS above ``MAX_HAND_EYE_RMS_PX``.
    """
    if not len(bMe_list) == len(views) == len(cMboard_list):
        raise ValueError(
            f"hand-eye calibration needs one pose and one board pose per view: {len(bMe_list)} poses, "
            f"{len(views)} views, {len(cMboard_list)} board poses"
        )
    if len(views) < 3:
        raise ValueError(f"hand-eye calibration needs at least 3 views, got {len(views)}")
    _check_views(views)
    bMe = [np.asarray(M, dtype=float) for M in bMe_list]
    eMc_axxb = solve_axxb(bMe, [np.asarray(M, dtype=float) for M in cMboard_list])
    bMboard_0 = bMe[0] @ eMc_axxb @ np.asarray(cMboard_list[0], dtype=float)

    eMc0, bMboard0 = torch.from_numpy(eMc_axxb), torch.from_numpy(bMboard_0)
    eMb = [torch.from_numpy(inverse(M)) for M in bMe]
    corners = [torch.from_numpy(v.corners_board.copy()) for v in views]
    found = torch.from_numpy(np.concatenate([v.corners_px for v in views]).ravel())

    def poses(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        eMc = torch.cat([torch.cat([eMc0[:3, :3], (eMc0[:3, 3] + x[:3]).unsqueeze(1)], dim=1), eMc0[3:]])
        return eMc, _perturbed(bMboard0, x[3:])

    def residuals(x: torch.Tensor) -> torch.Tensor:
        eMc, bMboard = poses(x)
        cMe = torch.linalg.inv(eMc)
        predicted = []
        for M, P in zip(eMb, corners):
            cMboard = cMe @ M @ bMboard
            predicted.append(_project(camera, P @ cMboard[:3, :3].T + cMboard[:3, 3]))
        return torch.cat(predicted).ravel() - found

    def jacobian(x: torch.Tensor) -> torch.Tensor:
        # Nine inputs, thousands of residuals: forward mode, one pass per parameter.
        return torch.autograd.functional.jacobian(residuals, x, vectorize=True, strategy="forward-mode")

    result = levenberg_marquardt(residuals, jacobian, torch.zeros(9, dtype=torch.float64), _REFINEMENT)
    eMc_t, bMboard_t = poses(result.x)
    eMc, bMboard = eMc_t.detach().numpy(), bMboard_t.detach().numpy()
    rms = float(np.sqrt(2.0 * result.mse))  # per corner, as OpenCV's calibration reports it
    errors = np.array([pose_error_mm_deg(M @ eMc @ np.asarray(C, dtype=float), bMboard) for M, C in zip(bMe, cMboard_list)])
    spread_mm, spread_deg = (float(s) for s in np.sqrt(np.mean(errors**2, axis=0)))
    turns = _wrist_turns_deg(bMe)
    faults = []
    if len(views) < MIN_HAND_EYE_VIEWS:
        faults.append(f"only {len(views)} views, take at least {MIN_HAND_EYE_VIEWS}")
    if turns[1] < MIN_SECOND_AXIS_DEG:
        faults.append(
            f"the wrist turned by {turns[1]:.1f} deg RMS about its second axis (at least "
            f"{MIN_SECOND_AXIS_DEG:.0f}): tilt it about two axes"
        )
    if rms > MAX_HAND_EYE_RMS_PX:
        faults.append(
            f"corners reproject at {rms:.2f} px RMS through the arm's poses (at most {MAX_HAND_EYE_RMS_PX}): "
            "the board moved, or the arm's readings are off"
        )
    verdict = Verdict.of(
        faults, f"RMS {rms:.3f} px over {len(views)} views, board spread {spread_mm:.2f} mm {spread_deg:.3f} deg"
    )
    return HandEyeCalibration(
        camera, read_only(eMc), read_only(bMboard), read_only(eMc_axxb), rms, spread_mm, spread_deg, turns, verdict
    )


# -- 3. the network's data set ---------------------------------------------------------


def grid_dataset(views: Sequence[BoardView], bMe_list: Sequence[Matrix], bMboard: Matrix) -> CalibrationDataset:
    """The chapter 2 network's data set (section 2.3.2, step 1) from board views: each
    corner's pixel, its base-frame (x, y) = (bMboard P)_xy, and the reported bMe.

    The world is the board plane as the hand-eye step measured it (``bMboard``): the
    network learns pixels to that plane, so it locates parts lying on it (or as high as
    the board is thick above it). With the "planar" inputs the views must share one
    height and orientation, as in the thesis.
    """
    if len(views) != len(bMe_list):
        raise ValueError(f"one pose per view: {len(views)} views, {len(bMe_list)} poses")
    bMboard = np.asarray(bMboard, dtype=float)
    pixels = np.concatenate([v.corners_px for v in views])
    world = np.concatenate([v.corners_board @ bMboard[:3, :3].T + bMboard[:3, 3] for v in views])[:, :2]
    view = np.concatenate([np.full(len(v), k, dtype=np.int64) for k, v in enumerate(views)])
    metadata = {"world": "base (x, y) of the board's corners through the hand-eye step's bMboard", "bMboard": bMboard.tolist()}
    return CalibrationDataset(pixels, world, view, np.array([np.asarray(M, dtype=float) for M in bMe_list]), metadata)


# -- 4. acceptance -----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class AcceptanceCheck:
    """One check pose: the arm's reported bMe, the board corner aimed at (3,) in the board
    frame, and the pixel (2,) it was found at in the frame taken there."""

    bMe: Matrix
    corner_board: Matrix
    corner_px: Matrix


@dataclass(frozen=True, eq=False)
class AcceptanceErrors:
    """Per check, the distance (mm) on the board plane between where the model puts the
    found pixel and where the corner is; their mean and largest."""

    errors_mm: Matrix
    mean_mm: float
    max_mm: float


def acceptance_errors(model: PlanarCalibration, bMboard: Matrix, checks: Sequence[AcceptanceCheck]) -> AcceptanceErrors:
    """How far a calibrated model (the NN, or a ``HandEyeCalibration``) puts the corners
    seen at check poses from where they are.

    The model gives a base (x, y); lifted onto the board plane (the plane's height there),
    it is compared with the corner, bMboard P, in 3D: the distance on the board plane.
    """
    if not checks:
        raise ValueError("acceptance needs at least one check")
    bMboard = np.asarray(bMboard, dtype=float)
    pixels = np.array([np.asarray(c.corner_px, dtype=float) for c in checks])
    bMe = np.array([np.asarray(c.bMe, dtype=float) for c in checks])
    xy = model.world_of(pixels, bMe)
    normal, origin = bMboard[:3, 2], bMboard[:3, 3]
    z = origin[2] - ((xy - origin[:2]) @ normal[:2]) / normal[2]
    placed = np.column_stack((xy, z))
    corners = np.array([bMboard[:3, :3] @ np.asarray(c.corner_board, dtype=float) + bMboard[:3, 3] for c in checks])
    errors = 1000.0 * np.linalg.norm(placed - corners, axis=1)
    return AcceptanceErrors(read_only(errors), float(np.mean(errors)), float(np.max(errors)))
