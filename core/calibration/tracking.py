"""PBVS with a calibration (thesis section 2.4) and the tracking tests of chapter 3.

Point-to-point positioning (eq. 2-47): the end effector moves in the plane parallel to
the table with u = -K (wP - wS), wP the end effector's position (the JRC's
reading; W = B on the table, section 2.3.2) and wS the target's world position that the
calibration computes from the target's pixel and that same reading. Each cycle takes a
new look, so the law closes the loop through the camera. A target that leaves the image
stops the motion (zero velocity) and the point counts as lost.

The target is a point on the table; the simulated camera measures it as the cell
measures every feature: the TRUE camera's projection from its TRUE pose, plus the pixel
noise asked for.

Tests:
- the sinusoid of eq. 3-1, 41 points X = 200 .. 400 mm in 5 mm steps, Y = A sin(10 pi X)
  with X in METRES (as printed, in mm, the sine has a 0.2 mm period and aliases at a
  5 mm step: docs/thesis-notes.md section 7), tracked point after point, 10 s per point. The
  UPJ's tool-down shell at 300 mm over the table is about 130 mm thick, so the
  thesis's A = 100 mm cannot be reached anywhere: the curve is laid with its X along
  the base's y axis, centred at x = -450 mm, and A = 40 mm by default;
- random points (the analogue of Table 3-4's test positions): each target is reached
  from a random viewpoint near it, off the calibration grid (a viewpoint no fit has seen).

Errors are reported twice: where the JRC says the end effector is (what
the thesis could measure, and what the calibration is responsible for) and where it
truly is (which adds the arm's absolute error at the target, the same for every method).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from vservo.core.calibration.baselines import PlanarCalibration
from vservo.core.calibration.collection import MOVE_SPEED_M_S, cell_with_truth
from vservo.core.calibration.dataset import bRe_TOOL_DOWN
from vservo.core.cell.config import CellConfig
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.spatial import Matrix, inverse, transform
from vservo.core.robot.commands import PositionCommand, VelocityCommand
from vservo.core.sim.plant import SimulatedCell

SINUSOID_CENTRE_M = (-0.450, 0.0)


@dataclass(frozen=True)
class TrackingSettings:
    """The law's gain K (1/s), the control period, the time per point (10 s in section 3.2)
    and the camera's height over the table."""

    gain: float = 1.0
    dt_s: float = 0.2
    seconds_per_point: float = 10.0
    camera_height_m: float = 0.300
    pixel_noise_px: float = 0.0

    @property
    def steps(self) -> int:
        return max(1, int(round(self.seconds_per_point / self.dt_s)))


@dataclass(frozen=True)
class PointResult:
    """One target: where it was, where the end effector ended (reported and true), lost or not."""

    target_m: Matrix
    reported_m: Matrix
    true_m: Matrix
    lost: bool


def sinusoid_points(amplitude_m: float = 0.040, centre_m: tuple[float, float] = SINUSOID_CENTRE_M) -> Matrix:
    """The 41 points of eq. 3-1 (X in metres in the sine), laid along the base's y axis."""
    X = np.arange(0.200, 0.400 + 1e-9, 0.005)
    Y = amplitude_m * np.sin(10.0 * np.pi * X)
    return np.column_stack((centre_m[0] + Y, centre_m[1] + (X - 0.300)))


class Tracker:
    """Runs eq. 2-47 on a simulated cell built like the one the data came from."""

    def __init__(self, config: CellConfig, truth: str, seed: int, settings: TrackingSettings = TrackingSettings()) -> None:
        self.config = cell_with_truth(config, truth)
        self.cell = SimulatedCell(self.config, seed)
        self.settings = settings
        self.table_height_m = self.config.plant().scene.table_height_m
        self.noise = np.random.default_rng([seed, 11])

    def flange_over(self, xy: Matrix) -> Matrix:
        """bMe putting the NOMINAL camera over (x, y) at the tracking height, tool down."""
        bMc = transform(bRe_TOOL_DOWN, (xy[0], xy[1], self.table_height_m + self.settings.camera_height_m))
        return bMc @ inverse(self.config.nominal.eMc)

    def move_over(self, xy: Matrix) -> None:
        """Jog the arm over a point (a set-up move: raises UnreachableTarget)."""
        self.cell.execute(PositionCommand(self.flange_over(xy), MOVE_SPEED_M_S, 0.0))

    def look_at(self, target_m: Matrix) -> Matrix:
        """The target's pixel (2,), NaN when it is outside the image."""
        truth = self.cell.truth.model
        cMb = inverse(self.cell.ground_truth_bMe() @ truth.eMc)
        point = np.array([target_m[0], target_m[1], self.table_height_m])
        pixel = truth.camera.project(cMb[:3, :3] @ point + cMb[:3, 3])[0]
        if self.settings.pixel_noise_px:
            pixel = pixel + self.noise.normal(0.0, self.settings.pixel_noise_px, 2)
        return pixel if truth.camera.in_view(pixel)[0] else np.full(2, np.nan)

    def servo(self, calibration: PlanarCalibration, target_m: Matrix) -> PointResult:
        """Eq. 2-47 for ``seconds_per_point``: u = -K (wP - wS), in the plane of the table."""
        lost = False
        for _ in range(self.settings.steps):
            bMe = self.cell.measure(look=False).bMe
            pixel = self.look_at(target_m)
            if np.isnan(pixel).any():
                lost = True  # the target left the view: hold still
                break
            wS = calibration.world_of(pixel[None, :], bMe[None])[0]
            u_b = -self.settings.gain * (bMe[:2, 3] - wS)
            v_e = bMe[:3, :3].T @ np.array([u_b[0], u_b[1], 0.0])
            self.cell.execute(VelocityCommand(np.concatenate((v_e, np.zeros(3))), self.settings.dt_s))
        reported = self.cell.measure(look=False).bMe[:2, 3]
        true = self.cell.ground_truth_bMe()[:2, 3]
        return PointResult(np.asarray(target_m, dtype=float), reported.copy(), true.copy(), lost)

    def track_path(
        self, calibration: PlanarCalibration, points: Matrix, on_point: Callable[[PointResult], None] | None = None
    ) -> list[PointResult]:
        """Start over the first point (a set-up move), then servo onto each point in turn,
        the first included (section 3.2)."""
        self.move_over(points[0])
        results = []
        for target in points:
            results.append(self.servo(calibration, target))
            if on_point is not None:
                on_point(results[-1])
        return results

    def track_from(
        self,
        calibration: PlanarCalibration,
        targets: Matrix,
        starts: Matrix,
        on_point: Callable[[PointResult], None] | None = None,
    ) -> list[PointResult]:
        """Each target from its own start viewpoint (the random test)."""
        results = []
        for target, start in zip(targets, starts):
            self.move_over(start)
            results.append(self.servo(calibration, target))
            if on_point is not None:
                on_point(results[-1])
        return results


def random_targets(
    tracker: Tracker,
    count: int,
    seed: int,
    x_range_m: tuple[float, float],
    y_range_m: tuple[float, float],
    reach_m: tuple[float, float] = (0.035, 0.025),
) -> tuple[Matrix, Matrix]:
    """Random targets in the workspace and, for each, a random start viewpoint in the
    workspace within ``reach_m`` of it (so the target is in view); the arm reaches both."""
    rng = np.random.default_rng([seed, 13])
    arm = tracker.cell.jrc_arm
    targets: list[Matrix] = []
    starts: list[Matrix] = []
    for _ in range(500 * count):
        if len(targets) == count:
            break
        target = np.array([rng.uniform(*x_range_m), rng.uniform(*y_range_m)])
        start = target + rng.uniform(-1.0, 1.0, 2) * np.asarray(reach_m)
        if not (x_range_m[0] <= start[0] <= x_range_m[1] and y_range_m[0] <= start[1] <= y_range_m[1]):
            continue
        try:
            for xy in (target, start):
                arm.ik(tracker.flange_over(xy), tracker.cell.state.q, restarts=2, tolerance_m=1e-7, tolerance_rad=1e-7)
        except UnreachableTarget:
            continue
        targets.append(target)
        starts.append(start)
    if len(targets) < count:
        raise ValueError(f"only {len(targets)} of {count} random targets are reachable in the workspace")
    return np.array(targets), np.array(starts)


def error_summary(errors_m: Matrix) -> dict[str, Any]:
    """Mean |X|, |Y| and XY error and the largest XY error, in mm (Tables 3-2, 3-4)."""
    errors = 1000.0 * np.asarray(errors_m, dtype=float)
    xy = np.linalg.norm(errors, axis=1)
    return {
        "x_mm": round(float(np.mean(np.abs(errors[:, 0]))), 5),
        "y_mm": round(float(np.mean(np.abs(errors[:, 1]))), 5),
        "xy_mm": round(float(np.mean(xy)), 5),
        "max_xy_mm": round(float(np.max(xy)), 5),
        "points": len(errors),
    }


def tracking_summary(results: list[PointResult]) -> dict[str, Any]:
    """The summary of the points reached (reported position, thesis's measure) with the
    true-position summary beside it and the count of lost points."""
    reached = [r for r in results if not r.lost]
    if not reached:
        return {"lost": len(results), "points": 0}
    summary = error_summary(np.array([r.reported_m - r.target_m for r in reached]))
    summary["true"] = error_summary(np.array([r.true_m - r.target_m for r in reached]))
    summary["lost"] = len(results) - len(reached)
    return summary
