"""Commissioning: the robot shows the camera the board, and the cell's model is measured.

``vservo commission`` (and the Calibrate tab, through the controller) runs this on the
connected cell, virtual or real, through the same rig every run uses: the robot moves,
frames come from the cell's camera, nothing else is read. The steps (``Step``):

- camera: intrinsics and distortion from tilted views of the whole board;
- hand-eye: eMc from the same views (AX = XB, then refined with the board's pose);
- laser: the beam's line from its spot on the board at several heights and tilts;
- nn: the chapter 2 network, trained on a grid of views at the survey height.

The procedure is the integrator's: find the board roughly from above (the cell file
says only roughly where it lies), aim every later view with the best model so far,
skip a view the arm cannot reach or whose board cannot be named, and end with an
acceptance check: the camera is put over a few board corners and the world error of
the calibrated model is measured there. Every frame is kept in the data folder, with a
``views.json`` that says what each was and what was found in it.

The estimation itself lives in vservo.core.calibration (board_views, cell_calibration);
this module only moves, looks and records.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from vservo.core.calibration.board_views import BoardNotFound, BoardView, find_board
from vservo.core.calibration.cell_calibration import (
    AcceptanceCheck,
    BoardPlaneModel,
    CameraCalibration,
    HandEyeCalibration,
    Verdict,
    acceptance_errors,
    board_pose,
    calibrate_camera_views,
    calibrate_hand_eye,
    grid_dataset,
)
from vservo.core.calibration.laser_calibration import LaserCalibration, beam_line_error, fit_laser_beam
from vservo.core.calibration.levenberg_marquardt import LMSettings
from vservo.core.calibration.mlp import train_nn
from vservo.core.cell.config import BoardConfig, CellModel, ConfigError
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.errors import VservoError
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import Matrix, exp_twist, inverse, rot_x, rot_z, transform
from vservo.core.perception.vision.spot import detect_laser_spot
from vservo.core.production.protocol.state import CommissionStep
from vservo.core.production.rig import Rig
from vservo.core.robot.safety import SafetyRefusal, SafetyStopActive

# The camera looking straight down with the flange's tool-down orientation (flange z
# along -z of B), the orientation the NN's grid and a job's survey use.
bRc_DOWN = rot_x(np.pi)
# Corners this close to the laser spot are left out of a view: its glare shifts them.
SPOT_RADIUS_PX = 12.0


Step = CommissionStep  # the steps as the channel names them (core/production/protocol/state.py)


ALL_STEPS = tuple(Step)


class CommissioningError(VservoError, RuntimeError):
    """Commissioning cannot go on; the message says what to do."""


@dataclass(frozen=True)
class CommissionSettings:
    """Where the views are taken (distances are the camera's from the board, along its axis).

    camera_views: tilted views for the camera and the hand-eye steps, at distances in
      ``camera_distance_m`` and tilts in ``tilt_deg`` about horizontal axes all round,
      turned about the optical axis by up to ``turn_deg``.
    laser_heights_m: the camera's heights over the board for the laser's spot, each at
      ``laser_tilt_deg`` about both horizontal axes and not tilted.
    survey_height_m, grid_half_m, grid_step_m: the NN's grid of tool-down views.
    acceptance_corners, acceptance_height_m: the acceptance check.
    """

    camera_views: int = 24
    camera_distance_m: tuple[float, float] = (0.17, 0.27)
    tilt_deg: tuple[float, float] = (12.0, 35.0)
    turn_deg: float = 20.0
    laser_heights_m: tuple[float, ...] = (0.13, 0.16, 0.20, 0.25, 0.30, 0.35)
    laser_tilt_deg: float = 8.0
    survey_height_m: float = 0.30
    grid_half_m: tuple[float, float] = (0.06, 0.05)
    grid_step_m: float = 0.02
    acceptance_corners: int = 5
    acceptance_height_m: float = 0.27
    find_height_m: float = 0.32
    speed_m_s: float = 0.10
    nn_epochs: int = 60
    seed: int = 0


@dataclass(frozen=True)
class ViewRecord:
    """One view: what it was for, where the robot reported the flange, what was found."""

    step: str
    index: int
    bMe: Matrix | None
    image: str | None
    found: str

    def as_dict(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "index": self.index,
            "image": self.image,
            "found": self.found,
            "bMe": None if self.bMe is None else np.round(self.bMe, 9).tolist(),
        }


@dataclass(frozen=True)
class Progress:
    """What commissioning is doing now, for a progress bar or the Calibrate tab."""

    step: str
    done: int
    total: int
    note: str


@dataclass(frozen=True)
class StepResult:
    """A step's outcome: its figures (JSON-ready) and the verdict."""

    step: Step
    figures: dict[str, Any]
    verdict: Verdict

    def as_dict(self) -> dict[str, Any]:
        return {**self.figures, "verdict": "good" if self.verdict.good else "retake", "why": self.verdict.reason}


@dataclass(frozen=True)
class CommissionResult:
    """The measured model, each step's result, the acceptance check and the views taken."""

    model: CellModel
    bMboard: Matrix
    steps: dict[Step, StepResult]
    acceptance: dict[str, Any] | None
    nn_path: Path | None
    views: list[ViewRecord] = field(default_factory=list)
    cell_time_s: float = 0.0  # how long the real cell would take (RobotBackend.cell_clock_s)
    wall_time_s: float = 0.0

    @property
    def good(self) -> bool:
        return all(result.verdict.good for result in self.steps.values())


def look_at(
    target_b: Matrix, distance_m: float, tilt_rad: float = 0.0, azimuth_rad: float = 0.0, turn_rad: float = 0.0
) -> Matrix:
    """bMc of a camera ``distance_m`` from ``target_b`` along its optical axis, looking down
    at it tilted by ``tilt_rad`` about the horizontal axis at ``azimuth_rad``, turned by
    ``turn_rad`` about its own optical axis."""
    axis = tilt_rad * np.array([np.cos(azimuth_rad), np.sin(azimuth_rad), 0.0])
    bRc = exp_twist(np.concatenate((np.zeros(3), axis)))[:3, :3] @ bRc_DOWN @ rot_z(turn_rad)[:3, :3]
    return transform(bRc, np.asarray(target_b, float) - bRc[:, 2] * distance_m)


def _shifted(bMe: Matrix, dx_m: float, dy_m: float) -> Matrix:
    """bMe moved horizontally by (dx, dy) in B."""
    moved = np.array(bMe, dtype=float)
    moved[:2, 3] += (dx_m, dy_m)
    return moved


class Commissioning:
    """Runs the steps on a rig; ``on_progress`` hears of every view, ``stopped`` is polled
    between views (an e-stop or a cancel ends it with the robot where it stands)."""

    def __init__(
        self,
        rig: Rig,
        folder: Path,
        settings: CommissionSettings = CommissionSettings(),
        on_progress: Callable[[Progress], None] = lambda progress: None,
        stopped: Callable[[], bool] = lambda: False,
    ) -> None:
        if rig.config.board is None:
            raise ConfigError(
                f"{rig.config.source}: no [board]: commissioning needs the board's square, inner "
                "corners and rough place (docs/cell-file.md)"
            )
        self.rig, self.folder, self.settings = rig, Path(folder), settings
        self.board: BoardConfig = rig.config.board
        self.on_progress, self.stopped = on_progress, stopped
        self.rng = np.random.default_rng([settings.seed, 15])
        self.views: list[ViewRecord] = []
        # The best model so far: the cell file's, replaced step by step.
        self.model: CellModel = rig.config.nominal
        self.bMboard: Matrix = self.board.bMboard

    # -- moving and looking ----------------------------------------------------------------

    def _centre_b(self) -> Matrix:
        cols, rows = self.board.inner_corners
        centre = np.array([(cols - 1) / 2, (rows - 1) / 2, 0.0, 1.0]) * np.array([self.board.square_m] * 2 + [0, 1])
        return (self.bMboard @ centre)[:3]

    def _down_view(self, target_b: Matrix, height_m: float, turn_rad: float = 0.0, tilt_rad: float = 0.0) -> Matrix:
        """The flange pose ``height_m`` over ``target_b``, tool down (leaning sideways by ``tilt_rad``
        about the radial direction, turned by ``turn_rad`` about the vertical), placed so that the
        current model's optical axis meets the board's plane at ``target_b``."""
        radial = self._radial_azimuth()
        axis = tilt_rad * np.array([np.cos(radial), np.sin(radial), 0.0])
        bRe = exp_twist(np.concatenate((np.zeros(3), axis)))[:3, :3] @ rot_z(turn_rad)[:3, :3] @ bRc_DOWN
        bMe = transform(bRe, np.asarray(target_b, float) + np.array([0.0, 0.0, height_m]))
        bMc = bMe @ self.model.eMc
        normal = self.bMboard[:3, 2]
        along = float(normal @ (np.asarray(target_b, float) - bMc[:3, 3])) / float(normal @ bMc[:3, 2])
        hit = bMc[:3, 3] + along * bMc[:3, 2]
        bMe[:2, 3] += (np.asarray(target_b, float) - hit)[:2]
        return bMe

    def _go(self, bMe_target: Matrix) -> Matrix | None:
        """Move the flange to bMe_target; the reported flange pose, or None when the arm
        cannot reach it (the safety layer's checks refuse it before any motion)."""
        robot = self.rig.robot
        try:
            # Reach and workspace only: move_linear cuts the way there into allowed steps.
            robot.check_target(bMe_target, self.settings.speed_m_s, bMe_now=bMe_target)
            robot.move_linear(bMe_target, self.settings.speed_m_s)
        except SafetyStopActive:
            raise
        except (SafetyRefusal, UnreachableTarget):
            return None
        return robot.read_pose()

    def _frame(self, step: str, index: int) -> tuple[np.ndarray, str]:
        """A frame exposed after the robot stopped, kept as a PNG in the data folder."""
        frame = self.rig.camera.read_after(self.rig.robot.clock_s())
        name = f"{step}-{index:03d}.png"
        cv2.imwrite(str(self.folder / "views" / name), frame.image)
        return frame.image, name

    def _look(
        self, step: str, index: int, bMe_target: Matrix, spot: bool = False
    ) -> tuple[Matrix, BoardView, Matrix | None] | None:
        """Go to bMe_target, take a frame, find the board (and the laser spot when asked). None when
        the view cannot be used; the reason is recorded."""
        if self.stopped():
            raise CommissioningError("stopped by the operator")
        bMe = self._go(bMe_target)
        if bMe is None:
            self.views.append(ViewRecord(step, index, None, None, "unreachable"))
            return None
        image, name = self._frame(step, index)
        spot_px = None
        if spot:
            detection = detect_laser_spot(image)
            if not detection.found:
                self.views.append(ViewRecord(step, index, bMe, name, f"no laser spot: {detection.reason}"))
                return None
            spot_px = detection.spot_px
        try:
            view = find_board(self.board, image, spot_px=spot_px, spot_radius_px=SPOT_RADIUS_PX)
        except BoardNotFound as exc:
            self.views.append(ViewRecord(step, index, bMe, name, f"board refused: {exc}"))
            return None
        self.views.append(
            ViewRecord(
                step,
                index,
                bMe,
                name,
                f"{len(view.corners_px)} corners" + ("" if spot_px is None else f", spot at {np.round(spot_px, 2).tolist()}"),
            )
        )
        return bMe, view, spot_px

    def _report(self, step: str, done: int, total: int, note: str) -> None:
        self.on_progress(Progress(step, done, total, note))

    def _collect(self, step: str, poses: Sequence[Matrix], spot: bool = False) -> list[tuple[Matrix, BoardView, Matrix | None]]:
        found = []
        for k, bMe_target in enumerate(poses):
            seen = self._look(step, k, bMe_target, spot)
            if seen is not None:
                found.append(seen)
            self._report(step, k + 1, len(poses), self.views[-1].found)
        return found

    # -- the procedure ------------------------------------------------------------------------

    def run(self, steps: Sequence[Step] = ALL_STEPS) -> CommissionResult:
        started_wall, started_clock = time.monotonic(), self.rig.robot.cell_clock_s()
        (self.folder / "views").mkdir(parents=True, exist_ok=True)
        if self.rig.lay_board is not None:
            self.rig.lay_board(True)
        try:
            result = self._run(set(steps))
        finally:
            self._write_views()
            if self.rig.lay_board is not None:
                self.rig.lay_board(False)
        return replace(
            result,
            views=list(self.views),
            wall_time_s=time.monotonic() - started_wall,
            cell_time_s=self.rig.robot.cell_clock_s() - started_clock,
        )

    def _run(self, steps: set[Step]) -> CommissionResult:
        results: dict[Step, StepResult] = {}
        self._find_board()
        if steps & {Step.CAMERA, Step.HAND_EYE}:
            views = self._collect("tilted", self._tilted_poses())
            board_views = [v for _, v, _ in views]
            if Step.CAMERA in steps:
                camera = calibrate_camera_views(board_views, self.model.camera)
                self.model = replace(self.model, camera=camera.camera)
                results[Step.CAMERA] = StepResult(Step.CAMERA, camera_figures(camera, len(views)), camera.verdict)
                cMboard = list(camera.cMboard)
            else:
                cMboard = [board_pose(self.model.camera, v) for v in board_views]
            if Step.HAND_EYE in steps:
                hand_eye = calibrate_hand_eye([bMe for bMe, _, _ in views], board_views, self.model.camera, cMboard)
                self.model = replace(self.model, eMc=hand_eye.eMc)
                self.bMboard = hand_eye.bMboard
                results[Step.HAND_EYE] = StepResult(Step.HAND_EYE, hand_eye_figures(hand_eye), hand_eye.verdict)
        if Step.LASER in steps:
            views = self._collect("laser", self._laser_poses(), spot=True)
            if not views:
                raise CommissioningError("no laser view showed both the board and the spot (views.json says why)")
            laser = fit_laser_beam(
                self.model.camera, np.array([s for _, _, s in views]), [board_pose(self.model.camera, v) for _, v, _ in views]
            )
            self.model = replace(self.model, laser=LaserPointer(laser.cMl))
            results[Step.LASER] = StepResult(Step.LASER, laser_figures(laser), laser.verdict)
        nn_path = None
        if Step.NN in steps:
            nn_path, result = self._train_nn()
            results[Step.NN] = result
        acceptance = self._acceptance() if steps & {Step.CAMERA, Step.HAND_EYE} else None
        return CommissionResult(self.model, self.bMboard, results, acceptance, nn_path)

    def _find_board(self) -> None:
        """Look straight down at where the cell file says the board lies; from what is seen
        there, through the current model, where it really lies (enough to aim by)."""
        seen = self._look("find", 0, self._down_view(self._centre_b(), self.settings.find_height_m))
        if seen is None:
            raise CommissioningError(
                f"no board seen from {self.settings.find_height_m * 1000:.0f} mm over where "
                f"[board] pose puts it ({self.views[-1].found}): lay the board there "
                "(to a few centimetres), or correct [board] pose"
            )
        bMe, view, _ = seen
        self.bMboard = bMe @ self.model.eMc @ board_pose(self.model.camera, view)
        self._report("find", 1, 1, "board found")

    def _radial_azimuth(self) -> float:
        """The horizontal direction from the arm's base axis to the board's centre, the axis
        views are tilted about.

        At these heights the UPJ reaches tool-down poses only in a thin shell around its
        base axis: leaning the camera towards or away from the base swings the wrist out of
        it, leaning sideways (about this direction) keeps the wrist at its radius. Such
        tilts, combined with turns about the optical axis, still tilt the camera about both
        of its image axes (what the camera step needs) and turn the wrist about two axes
        (what AX = XB needs); poses are drawn until enough are reachable."""
        centre = self._centre_b()
        return float(np.arctan2(centre[1], centre[0]))

    def _reachable(self, bMe: Matrix) -> bool:
        try:
            self.rig.robot.check_target(bMe, self.settings.speed_m_s, bMe_now=bMe)
        except (SafetyRefusal, UnreachableTarget):
            return False
        return True

    def _draw(self, count: int, draw: Callable[[int], Matrix]) -> list[Matrix]:
        """``count`` reachable poses from ``draw`` (given the number drawn so far), or as many
        as 20 draws each find."""
        poses: list[Matrix] = []
        for k in range(20 * count):
            if len(poses) == count:
                break
            bMe = draw(k)
            if self._reachable(bMe):
                poses.append(bMe)
        return poses

    def _tilted_poses(self) -> list[Matrix]:
        s, rng = self.settings, self.rng
        centre, radial = self._centre_b(), self._radial_azimuth()
        return self._draw(
            s.camera_views,
            lambda k: (
                look_at(
                    centre + np.append(rng.uniform(-0.01, 0.01, 2), 0.0),
                    rng.uniform(*s.camera_distance_m),
                    np.deg2rad(rng.uniform(*s.tilt_deg)),
                    radial + np.pi * (k % 2),
                    rng.uniform(-np.pi, np.pi),
                )
                @ inverse(self.model.eMc)
            ),
        )

    def _laser_poses(self) -> list[Matrix]:
        """At each height, level and leaning both ways: the flange is put so that the beam
        the current model believes in meets the board near its centre."""
        s = self.settings
        tilt, centre = np.deg2rad(s.laser_tilt_deg), self._centre_b()
        normal = self.bMboard[:3, 2]
        poses = []
        for height in s.laser_heights_m:
            for tilt_rad in (0.0, tilt, -tilt):
                bMe = self._down_view(centre, height, tilt_rad=tilt_rad)
                beam = self.model.laser.beam(bMe @ self.model.eMc)
                reach = beam.intersect_plane(normal, float(normal @ self.bMboard[:3, 3]))
                if reach is not None:  # the believed spot, moved onto the centre
                    bMe[:2, 3] -= (beam.point_at(reach) - centre)[:2]
                poses.append(bMe)
        return poses

    def _grid_poses(self) -> list[Matrix]:
        """The NN's grid: the flange tool down at one height and orientation (the thesis's
        planar moves, section 3.2), in serpentine order over the board."""
        s = self.settings
        bMe0 = self._down_view(self._centre_b(), s.survey_height_m)
        xs = np.arange(-s.grid_half_m[0], s.grid_half_m[0] + 1e-9, s.grid_step_m)
        ys = np.arange(-s.grid_half_m[1], s.grid_half_m[1] + 1e-9, s.grid_step_m)
        return [_shifted(bMe0, x, y) for k, x in enumerate(xs) for y in (ys if k % 2 == 0 else ys[::-1])]

    def _train_nn(self) -> tuple[Path, StepResult]:
        views = self._collect("grid", self._grid_poses())
        dataset = grid_dataset([v for _, v, _ in views], [bMe for bMe, _, _ in views], self.bMboard)
        # What locating needs to know of the grid: where the flange was, and the plane's height.
        dataset = replace(
            dataset,
            metadata={
                **dataset.metadata,
                "survey_height_m": self.settings.survey_height_m,
                "cell": self.rig.config.source,
                "board_z_m": float(self.bMboard[2, 3]),
                "grid_bMe": [np.round(bMe, 9).tolist() for bMe, _, _ in views],
            },
        )
        dataset.save(self.folder / "grid.npz")
        order = np.random.default_rng([self.settings.seed, 5]).permutation(dataset.size)
        validation = max(dataset.size // 6, 1)
        fit, check = dataset.subset(order[validation:]), dataset.subset(order[:validation])
        model = train_nn(
            fit,
            "planar",
            validation=check,
            settings=LMSettings(epochs=self.settings.nn_epochs),
            seed=self.settings.seed,
            on_epoch=lambda epoch, mse: self._report("nn", epoch, self.settings.nn_epochs, f"mse {mse:.3g}"),
        )
        path = self.folder / "nn.npz"
        model.save(path)
        errors = model.world_of(check.pixels_px, check.bMe[check.view]) - check.world_m
        error_mm = 1000 * np.linalg.norm(errors, axis=1)
        figures = {
            "views": len(views),
            "corners": dataset.size,
            "validation_mean_mm": round(float(error_mm.mean()), 4),
            "validation_max_mm": round(float(error_mm.max()), 4),
            "file": str(path),
        }
        good = len(views) >= 10 and float(error_mm.mean()) < 0.5
        reason = (
            f"validation error {error_mm.mean():.3f} mm mean over {check.size} corners"
            if good
            else f"retake: {len(views)} grid views, validation error {error_mm.mean():.3f} mm mean"
        )
        return path, StepResult(Step.NN, figures, Verdict(good, reason))

    def _acceptance(self) -> dict[str, Any]:
        """The camera over a few board corners, each at a fresh turn: where the calibrated
        model puts the corner found there, against where the board says it is. Corners are
        taken in a random order, skipping those the arm cannot look at, until enough are seen."""
        corners = self.board.corners_board()
        wanted = min(self.settings.acceptance_corners, len(corners))
        seen: list[AcceptanceCheck] = []
        looks = 0
        for index in self.rng.permutation(len(corners)):
            if len(seen) == wanted:
                break
            corner_b = (self.bMboard @ np.append(corners[index], 1.0))[:3]
            # A fresh turn where the wrist allows one, else none.
            turns = (self.rng.uniform(-np.pi / 4, np.pi / 4), self.rng.uniform(-np.pi / 8, np.pi / 8), 0.0)
            views = [self._down_view(corner_b, self.settings.acceptance_height_m, turn_rad=t) for t in turns]
            view_bMe = next((v for v in views if self._reachable(v)), None)
            if view_bMe is None:
                continue
            found = self._look("acceptance", looks, view_bMe)
            looks += 1
            if found is not None:
                bMe, view, _ = found
                at = np.flatnonzero(np.all(np.isclose(view.corners_board, corners[index]), axis=1))
                if len(at):
                    seen.append(AcceptanceCheck(bMe, corners[index], view.corners_px[at[0]]))
                    self._report("acceptance", len(seen), wanted, self.views[-1].found)
        if not seen:
            raise CommissioningError("the acceptance check saw the board from none of its poses")
        errors = acceptance_errors(BoardPlaneModel(self.model.camera, self.model.eMc, self.bMboard), self.bMboard, seen)
        return {
            "corners": len(seen),
            "errors_mm": [round(float(e), 4) for e in errors.errors_mm],
            "mean_mm": round(errors.mean_mm, 4),
            "max_mm": round(errors.max_mm, 4),
        }

    def _write_views(self) -> None:
        (self.folder / "views.json").write_text(json.dumps([v.as_dict() for v in self.views], indent=1))


def model_errors(model: CellModel, reference: CellModel, depth_m: float) -> dict[str, Any]:
    """How far a measured model is from a reference one (a simulator's truth, or the last
    commissioning): the figures of the issue's acceptance."""
    from vservo.core.geometry.spatial import pose_error

    k, r = model.camera.intrinsics, reference.camera.intrinsics
    translation, rotation = pose_error(model.eMc, reference.eMc)
    beam_deg, beam_mm = beam_line_error(model.laser.cMl, reference.laser.cMl, depth_m)
    return {
        "fx_percent": round(100 * (k.fx / r.fx - 1), 4),
        "fy_percent": round(100 * (k.fy / r.fy - 1), 4),
        "principal_point_px": round(float(np.hypot(k.u0 - r.u0, k.v0 - r.v0)), 4),
        "eMc_mm": round(1000 * translation, 4),
        "eMc_deg": round(float(np.degrees(rotation)), 4),
        "beam_direction_deg": round(beam_deg, 4),
        f"beam_at_{depth_m * 1000:g}_mm": round(beam_mm, 4),
    }


def camera_summary(camera: CameraModel) -> dict[str, Any]:
    k = camera.intrinsics
    return {
        "fx_px": round(k.fx, 4),
        "fy_px": round(k.fy, 4),
        "principal_point_px": [round(k.u0, 4), round(k.v0, 4)],
        "distortion": [round(float(v), 6) for v in camera.distortion.as_opencv()],
    }


def commission_summary(result: CommissionResult) -> dict[str, Any]:
    """The JSON of ``vservo commission``: the measured model and every step's figures."""
    from vservo.core.geometry.spatial import pose_from_matrix, pose_to_mm_deg

    baseline_m, alpha_rad = laser_geometry(result.model.laser.cMl)
    return {
        "camera": camera_summary(result.model.camera),
        "eMc_mm_deg": [round(float(v), 4) for v in pose_to_mm_deg(pose_from_matrix(result.model.eMc))],
        "cMl_mm_deg": [round(float(v), 4) for v in pose_to_mm_deg(pose_from_matrix(result.model.laser.cMl))],
        "laser": {"baseline_mm": round(1000 * baseline_m, 4), "alpha_deg": round(float(np.degrees(alpha_rad)), 4)},
        "board_mm_deg": [round(float(v), 4) for v in pose_to_mm_deg(pose_from_matrix(result.bMboard))],
        "steps": {str(step): r.as_dict() for step, r in result.steps.items()},
        "acceptance": result.acceptance,
        "good": result.good,
        "views": {"taken": len(result.views), "used": sum(1 for v in result.views if "corners" in v.found)},
        "wall_time_s": round(result.wall_time_s, 1),
        "cell_time_s": round(result.cell_time_s, 1),
        "nn_file": None if result.nn_path is None else str(result.nn_path),
    }


def laser_geometry(cMl: Matrix) -> tuple[float, float]:
    """(baseline d, angle alpha) of a beam (eqs. 4-18 .. 4-21): d from the lens to where the
    beam crosses the camera's z = 0 plane, alpha between the beam and that baseline seen
    from the laser back towards the lens (80 deg for the thesis's in-plane laser)."""
    origin, direction = cMl[:3, 3], cMl[:3, 2]
    origin = origin - direction * (origin[2] / direction[2])
    baseline = float(np.linalg.norm(origin))
    return baseline, float(np.arccos(np.clip(direction @ (-origin / baseline), -1.0, 1.0)))


def camera_figures(camera: CameraCalibration, views: int) -> dict[str, Any]:
    return {
        **camera_summary(camera.camera),
        "views": views,
        "rms_px": round(camera.rms_px, 4),
        "worst_view_rms_px": round(float(np.max(camera.view_rms_px)), 4),
        "std_fx_px": round(camera.std_fx_px, 4),
        "std_fy_px": round(camera.std_fy_px, 4),
        "std_principal_point_px": [round(camera.std_u0_px, 4), round(camera.std_v0_px, 4)],
    }


def hand_eye_figures(hand_eye: HandEyeCalibration) -> dict[str, Any]:
    from vservo.core.geometry.spatial import pose_from_matrix, pose_to_mm_deg

    return {
        "eMc_mm_deg": [round(float(v), 4) for v in pose_to_mm_deg(pose_from_matrix(hand_eye.eMc))],
        "rms_px": round(hand_eye.rms_px, 4),
        "spread_mm": round(hand_eye.spread_mm, 4),
        "spread_deg": round(hand_eye.spread_deg, 4),
        "wrist_turns_deg": [round(t, 2) for t in hand_eye.turn_deg],
    }


def laser_figures(laser: LaserCalibration) -> dict[str, Any]:
    return {
        "spots": len(laser.points_c),
        "baseline_mm": round(1000 * laser.baseline_m, 4),
        "alpha_deg": round(float(np.degrees(laser.alpha_rad)), 4),
        "line_rms_mm": round(laser.rms_mm, 4),
        "depth_span_mm": round(laser.depth_span_mm, 2),
    }
