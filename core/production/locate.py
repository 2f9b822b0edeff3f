"""Finding the part anywhere in the survey view, with the chapter 2 network.

A job that locates its part first moves the camera to its survey pose and takes a
frame. The vision finds the part's top face (its four corners, ordered by the
orientation mark, corner 0 at the origin of the part frame O). The network trained at
commissioning (``[commissioning] nn_file``) maps each corner's pixel and the reported
flange position to the world (x, y) on the board's plane, which is the table's: the
thesis's use of it (eq. 2-47's X, Y from u, v, T_x, T_y).

The top face is a part's side above that plane, so a corner's ray meets the plane
behind the corner: the point is slid back along the ray, towards the camera centre c
(from the calibrated flange and hand-eye), by the share side / (c_z - z_table) of the
way (similar triangles). The corners then give the part frame: origin at corner 0, x
towards corner 1, z up, at the top face's height.

The network is valid where it was trained: the survey must be taken at the grid's
height and orientation, its flange within the grid. A survey outside that is refused,
not extrapolated.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from vservo.core.cell.config import CellConfig, CellModel, ConfigError
from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix, rotation_angle, transform

if TYPE_CHECKING:
    from vservo.core.calibration.mlp import NNCalibration

# How far the survey may be from the network's grid: a flange outside the trained
# positions by more than this, or at another height or orientation, is refused.
GRID_MARGIN_M = 0.005
HEIGHT_TOLERANCE_M = 0.005
ORIENTATION_TOLERANCE_RAD = np.deg2rad(1.0)


class LocateError(VservoError, RuntimeError):
    """The part could not be located; the message says why."""


@dataclass(frozen=True)
class LocatedPart:
    """Where the survey saw the part: its frame O in B, and the corners it was found from."""

    bMo: Matrix
    corners_px: Matrix
    corners_b: Matrix


@dataclass(frozen=True)
class PartLocator:
    """The network, the calibrated model it goes with, and the height of its plane in B."""

    nn: NNCalibration
    model: CellModel
    table_z_m: float
    grid_bMe: Matrix  # (K, 4, 4) the flange poses the network was trained at

    @classmethod
    def from_config(cls, config: CellConfig) -> PartLocator | None:
        """The locator of a commissioned cell (its [commissioning] nn_file); None before."""
        record = config.commissioning
        if record is None or record.nn_path is None:
            return None
        # Only a commissioned cell pays for importing the network's torch.
        from vservo.core.calibration.mlp import NNCalibration

        nn = NNCalibration.load(record.nn_path, "planar")
        grid = nn.training.get("dataset", {})
        if "grid_bMe" not in grid or "board_z_m" not in grid:
            raise ConfigError(
                f"{config.source}: commissioning.nn_file {str(record.nn_path)!r} was not trained by "
                "vservo commission (it holds no survey grid): commission the nn step"
            )
        return cls(nn, config.nominal, float(grid["board_z_m"]), np.array(grid["grid_bMe"], dtype=float))

    def check_survey(self, bMe: Matrix) -> None:
        """Refuse a survey pose the network was not trained for (module docstring)."""
        reference = self.grid_bMe[0]
        if abs(bMe[2, 3] - reference[2, 3]) > HEIGHT_TOLERANCE_M:
            raise LocateError(
                f"the survey's flange is at z = {bMe[2, 3] * 1000:.1f} mm, the network was trained at "
                f"z = {reference[2, 3] * 1000:.1f} mm: commission the nn step at this survey height"
            )
        if rotation_angle(bMe[:3, :3].T @ reference[:3, :3]) > ORIENTATION_TOLERANCE_RAD:
            raise LocateError(
                "the survey's flange is turned from the orientation the network was trained at: "
                "survey tool-down as the commissioning grid was"
            )
        low = self.grid_bMe[:, :2, 3].min(axis=0) - GRID_MARGIN_M
        high = self.grid_bMe[:, :2, 3].max(axis=0) + GRID_MARGIN_M
        if np.any(bMe[:2, 3] < low) or np.any(bMe[:2, 3] > high):
            raise LocateError(
                f"the survey's flange ({bMe[0, 3] * 1000:.1f}, {bMe[1, 3] * 1000:.1f}) mm is outside the "
                f"grid the network was trained on (x {low[0] * 1000:.0f}..{high[0] * 1000:.0f}, "
                f"y {low[1] * 1000:.0f}..{high[1] * 1000:.0f} mm)"
            )

    def locate(self, corners_px: Matrix | None, bMe: Matrix, part_side_m: float) -> LocatedPart:
        """The part frame of the part whose top-face corners were seen at ``corners_px``
        (ordered as the vision orders them) from the reported flange pose bMe."""
        self.check_survey(bMe)
        if corners_px is None or not np.all(np.isfinite(corners_px)):
            raise LocateError("no part seen from the survey pose")
        corners_px = np.asarray(corners_px, dtype=float)
        on_plane = self.nn.world_of(corners_px, np.repeat(bMe[None], len(corners_px), axis=0))
        if not np.all(np.isfinite(on_plane)):
            raise LocateError("the network gives no world point for the corners seen")
        centre_b = (bMe @ self.model.eMc)[:3, 3]
        height = centre_b[2] - self.table_z_m
        if height <= part_side_m:
            raise LocateError("the survey camera is not above the part")
        share = part_side_m / height
        points = np.column_stack((on_plane, np.full(len(on_plane), self.table_z_m)))
        corners_b = points + share * (centre_b - points)
        x_axis = corners_b[1] - corners_b[0]
        yaw = float(np.arctan2(x_axis[1], x_axis[0]))
        R = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        return LocatedPart(transform(R, corners_b[0]), corners_px, corners_b)
