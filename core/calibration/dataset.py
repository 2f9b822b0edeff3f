"""A calibration dataset: pairs of (image corner, robot reading) and the corner's world
coordinates, with the metadata that says how they were taken.

Each row is one checkerboard corner seen from one viewpoint (section 2.3.2, step 1): its
pixel (u, v), the world (x_W, y_W) the board gives it, and the index of the viewpoint,
whose end-effector pose bMe is the one the JRC REPORTED there. The NN's
inputs (u, v, T_x, T_y[, T_z, tilt]) and every baseline's are derived from these.

``validate`` refuses what no calibration can use, naming the file and the fault: NaN or
infinite values, wrong array shapes, a viewpoint index with no pose, too few corners.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.calibration.storage import CalibrationFileError, read_archive, write_archive
from vservo.core.geometry.spatial import Matrix, rot_x, theta_u

KIND = "vservo calibration dataset"
# A fit of the 4-20-2 MLP has 142 weights: fewer corners than this cannot pin it down,
# nor any baseline worth the name.
MIN_CORNERS = 150
# The end-effector orientation of a tool-down pose (flange z along -z of B), against
# which tilts are measured.
bRe_TOOL_DOWN = rot_x(np.pi)


# The NN's input sets (vservo.core.calibration.mlp), all derived from a dataset's rows.
INPUT_SETS: dict[str, tuple[str, ...]] = {
    "planar": ("u", "v", "Tx", "Ty"),
    "height": ("u", "v", "Tx", "Ty", "Tz"),
    "pose": ("u", "v", "Tx", "Ty", "Tz", "rx", "ry", "rz"),
}


class DatasetError(CalibrationFileError):
    """A dataset that cannot be used; the message names it and the fault."""


@dataclass(frozen=True)
class CalibrationDataset:
    """Corners (N rows) seen from V viewpoints.

    pixels_px (N, 2): (u, v) of each corner, OpenCV convention.
    world_m (N, 2): (x_W, y_W) of each corner on the board (W = B on the table).
    view (N,): index of the viewpoint each corner was seen from.
    bMe (V, 4, 4): the end-effector pose the JRC reported at each viewpoint.
    metadata: how the data was taken (truth, noise, workspace, counts); JSON-able.
    """

    pixels_px: Matrix
    world_m: Matrix
    view: np.ndarray
    bMe: Matrix
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def size(self) -> int:
        return len(self.pixels_px)

    @property
    def views(self) -> int:
        return len(self.bMe)

    def validate(self, name: str = "dataset", min_corners: int = MIN_CORNERS) -> CalibrationDataset:
        """Itself, if every array has the right shape and only finite values; DatasetError otherwise."""
        n = len(self.pixels_px) if np.ndim(self.pixels_px) else 0
        for label, array, shape in (
            ("pixels_px", self.pixels_px, (n, 2)),
            ("world_m", self.world_m, (n, 2)),
            ("view", self.view, (n,)),
        ):
            if np.shape(array) != shape:
                raise DatasetError(f"{name}: {label} has shape {np.shape(array)}, expected {shape}")
        if np.ndim(self.bMe) != 3 or np.shape(self.bMe)[1:] != (4, 4):
            raise DatasetError(f"{name}: bMe has shape {np.shape(self.bMe)}, expected (views, 4, 4)")
        for label, array in (("pixels_px", self.pixels_px), ("world_m", self.world_m), ("bMe", self.bMe)):
            bad = ~np.isfinite(np.asarray(array, dtype=float))
            if bad.any():
                where = np.argwhere(bad)[0]
                raise DatasetError(
                    f"{name}: {label} holds {int(bad.sum())} NaN or infinite values (first at index {where.tolist()})"
                )
        bad_pose = _first_non_rigid(np.asarray(self.bMe, dtype=float))
        if bad_pose is not None:
            raise DatasetError(
                f"{name}: bMe[{bad_pose}] = {np.asarray(self.bMe[bad_pose]).tolist()} is not a rigid "
                "transform (a rotation and a translation over [0, 0, 0, 1])"
            )
        if not np.issubdtype(np.asarray(self.view).dtype, np.integer):
            raise DatasetError(f"{name}: view indices must be integers, got {np.asarray(self.view).dtype}")
        if n and (self.view.min() < 0 or self.view.max() >= len(self.bMe)):
            raise DatasetError(f"{name}: view indices run to {int(self.view.max())} but there are {len(self.bMe)} poses")
        if n < min_corners:
            raise DatasetError(f"{name}: {n} corners, too few to calibrate (at least {min_corners})")
        return self

    def end_effector(self) -> Matrix:
        """Per corner, the reported end-effector position (T_x, T_y, T_z) in m (eq. 2-12)."""
        return self.bMe[self.view, :3, 3]

    def network_inputs(self, input_set: str) -> Matrix:
        """The NN's raw inputs (N, k) for every corner (see ``network_inputs``)."""
        return network_inputs(input_set, self.pixels_px, self.bMe[self.view])

    def subset(self, rows: np.ndarray) -> CalibrationDataset:
        """The corners ``rows`` (an index or mask array), with every viewpoint kept."""
        return CalibrationDataset(self.pixels_px[rows], self.world_m[rows], self.view[rows], self.bMe, dict(self.metadata))

    def with_pixels(self, pixels_px: Matrix, **metadata: Any) -> CalibrationDataset:
        """The same corners measured at other pixels (e.g. with pixel noise added)."""
        return CalibrationDataset(pixels_px, self.world_m, self.view, self.bMe, {**self.metadata, **metadata})

    def save(self, path: str | Path) -> Path:
        self.validate(str(path))
        arrays = {"pixels_px": self.pixels_px, "world_m": self.world_m, "view": self.view.astype(np.int64), "bMe": self.bMe}
        return write_archive(path, KIND, arrays, self.metadata)

    @classmethod
    def load(cls, path: str | Path, min_corners: int = MIN_CORNERS) -> CalibrationDataset:
        """Read and validate a dataset file (DatasetError names the file and the fault)."""
        arrays, metadata = read_archive(path, KIND, DatasetError)
        missing = [key for key in ("pixels_px", "world_m", "view", "bMe") if key not in arrays]
        if missing:
            raise DatasetError(f"{path}: missing array {missing[0]}")
        return cls(arrays["pixels_px"], arrays["world_m"], arrays["view"], arrays["bMe"], metadata).validate(
            str(path), min_corners
        )


RIGID_TOLERANCE = 1e-3  # a robot's reported rotation is orthonormal far better than this


def _first_non_rigid(bMe: Matrix) -> int | None:
    """The index of the first pose that is no rotation plus translation (an all-zero pose, say), or None."""
    rotations = bMe[:, :3, :3]
    orthonormal = np.abs(rotations @ np.swapaxes(rotations, 1, 2) - np.eye(3)).max(axis=(1, 2)) <= RIGID_TOLERANCE
    proper = np.abs(np.linalg.det(rotations) - 1.0) <= RIGID_TOLERANCE
    bottom = np.all(bMe[:, 3, :] == [0.0, 0.0, 0.0, 1.0], axis=1)
    bad = np.flatnonzero(~(orthonormal & proper & bottom))
    return int(bad[0]) if bad.size else None


def network_inputs(input_set: str, pixels_px: Matrix, bMe: Matrix) -> Matrix:
    """The raw NN inputs (N, k) of ``input_set`` from pixels (N, 2) and reported poses (N, 4, 4):
    (u, v) in px, (T_x, T_y[, T_z]) in mm, and for ``pose`` the rotation vector (rad) of the
    end effector away from tool-down. The scale does not matter after normalisation."""
    if input_set not in INPUT_SETS:
        raise ValueError(f"unknown input set {input_set!r}: choose one of {', '.join(INPUT_SETS)}")
    columns = [np.asarray(pixels_px, dtype=float), 1000.0 * bMe[:, :2, 3]]
    if input_set in ("height", "pose"):
        columns.append(1000.0 * bMe[:, 2:3, 3])
    if input_set == "pose":
        columns.append(np.array([theta_u(bRe_TOOL_DOWN.T @ R) for R in bMe[:, :3, :3]]))
    return np.column_stack(columns)
