"""Data collection on the simulated cell (thesis section 2.3.2 step 1, section 3.2).

The camera is moved over the checkerboard, at a fixed height, to the viewpoints of a
grid over the workspace; at each one the cell's TRUE camera takes an 8-bit image of the
board from its TRUE pose, OpenCV finds the corners, the board names them (world
coordinates), and each corner is paired with the end-effector pose the JRC
REPORTS (its nominal model: wrong by the arm's placement errors and repeatability, as
on a real cell). Pixel noise, when asked for, is added to every corner found.

Truths (``--truth``):

- ``ideal``: the cell is exactly its nominal model: no lens distortion, the camera frame
  is the end-effector frame (the thesis's simulation), a perfect arm, no noise.
- ``realistic``: what a real cell has and simple models miss: a lens with radial
  distortion to the sixth order and decentring (k1 k2 p1 p2 k3), a focal length and
  principal point off the data sheet (the thesis's own calibration found 6.02 mm and
  (326, 228), Table 5-5), a camera mounted 0.3-0.4 deg off the flange axes and a
  millimetre off its centre, an arm whose joint placements are off by 0.1 mm and
  0.02 deg (drawn from the seed: some 0.3-0.5 mm of absolute error, varying by a few
  tenths over the workspace) with 0.01 mm / 0.002 deg repeatability.
- ``cell``: the [simulation] section of the cell file as it stands.

The workspace. The thesis moved the camera at Z = 300 mm over a 700 x 700 mm workspace
on a 20 mm grid. The UPJ of the shipped cell (on its 175 mm pedestal) reaches tool-down
poses with the camera 300 mm over the table only in a shell 0.38-0.52 m from its base
axis: of the 36 x 36 viewpoints of the square X -800 .. -100 mm, Y -350 .. 350 mm it
reaches about a fifth, a crescent around the base. The grid keeps those (the count is
in the dataset's metadata) and the calibration covers the crescent. Viewpoints are
visited in serpentine order, as an integrator's program would.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from vservo.core.calibration.checkerboard import BoardNotFound, Checkerboard, detect_board
from vservo.core.calibration.dataset import CalibrationDataset, bRe_TOOL_DOWN
from vservo.core.cell.config import CellConfig, CellModel
from vservo.core.cell.kinematics import UnreachableTarget
from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics
from vservo.core.geometry.spatial import Matrix, exp_twist, inverse, matrix_from_pose, pose_from_mm_deg, rot_z, transform
from vservo.core.robot.commands import PositionCommand
from vservo.core.sim.plant import SimulatedCell

TRUTHS = ("ideal", "realistic", "cell")
MOVE_SPEED_M_S = 0.1

# The realistic truth (module docstring).
REALISTIC_CAMERA = CameraModel(
    Intrinsics.from_sensor(6.02e-3, (7.4e-6, 7.4e-6), (324.0, 236.5), (640, 480)),
    Distortion(k1=-0.16, k2=0.11, p1=6e-4, p2=-4e-4, k3=-0.02),
)
REALISTIC_eMc_MM_DEG = (0.6, -0.5, 1.2, 0.35, -0.3, 0.4)
REALISTIC_JOINT_PLACEMENT = (0.1e-3, np.deg2rad(0.02))
REALISTIC_REPEATABILITY = (0.01e-3, np.deg2rad(0.002))


def cell_with_truth(config: CellConfig, truth: str) -> CellConfig:
    """The cell file's nominal model with the simulated truth of ``truth`` (TRUTHS)."""
    if truth == "cell":
        return config
    sim = config.plant()
    if truth == "ideal":
        simulation = replace(
            sim,
            truth=config.nominal,
            pixel_noise_px=0.0,
            repeatability_m=0.0,
            repeatability_rad=0.0,
            joint_placement_error_m=0.0,
            joint_placement_error_rad=0.0,
        )
    elif truth == "realistic":
        model = CellModel(
            camera=REALISTIC_CAMERA,
            eMc=config.nominal.eMc @ matrix_from_pose(pose_from_mm_deg(REALISTIC_eMc_MM_DEG)),
            laser=config.nominal.laser,
            eMv=config.nominal.eMv,
        )
        simulation = replace(
            sim,
            truth=model,
            pixel_noise_px=0.0,
            repeatability_m=REALISTIC_REPEATABILITY[0],
            repeatability_rad=REALISTIC_REPEATABILITY[1],
            joint_placement_error_m=REALISTIC_JOINT_PLACEMENT[0],
            joint_placement_error_rad=REALISTIC_JOINT_PLACEMENT[1],
        )
    else:
        raise ValueError(f"unknown truth {truth!r}: choose one of {', '.join(TRUTHS)}")
    return replace(config, simulation=simulation)


@dataclass(frozen=True)
class Workspace:
    """Where the camera goes: a rectangle of the table (world = base x, y, in m), the grid
    step and the camera's height over the table (section 3.2: 700 x 700 mm, 20 mm, 300 mm)."""

    x_range_m: tuple[float, float] = (-0.800, -0.100)
    y_range_m: tuple[float, float] = (-0.350, 0.350)
    step_m: float = 0.020
    camera_height_m: float = 0.300

    def __post_init__(self) -> None:
        for name in ("x_range_m", "y_range_m"):
            low, high = getattr(self, name)
            if not (np.isfinite(low) and np.isfinite(high) and high >= low):
                raise ValueError(f"workspace {name} = {(low, high)}: must be two finite numbers, low <= high")
        if not (self.step_m > 0.0 and self.camera_height_m > 0.0):
            raise ValueError("workspace step and camera height must be positive")

    def grid(self) -> Matrix:
        """The viewpoints (K, 2) of the grid, in serpentine order (rows along y)."""
        xs = np.arange(self.x_range_m[0], self.x_range_m[1] + 1e-9, self.step_m)
        ys = np.arange(self.y_range_m[0], self.y_range_m[1] + 1e-9, self.step_m)
        return np.array([(x, y) for k, x in enumerate(xs) for y in (ys if k % 2 == 0 else ys[::-1])])

    def as_dict(self) -> dict[str, Any]:
        return {
            "x_range_mm": [1000 * v for v in self.x_range_m],
            "y_range_mm": [1000 * v for v in self.y_range_m],
            "step_mm": 1000 * self.step_m,
            "camera_height_mm": 1000 * self.camera_height_m,
        }


@dataclass(frozen=True)
class CollectionCounts:
    """What happened at the viewpoints asked for."""

    requested: int
    unreachable: int
    refused: dict[str, int]
    views: int
    corners: int

    def as_dict(self) -> dict[str, Any]:
        return {
            "requested": self.requested,
            "unreachable": self.unreachable,
            "refused": dict(self.refused),
            "views": self.views,
            "corners": self.corners,
        }


class Collector:
    """Moves the simulated cell's camera over the board and records what it sees."""

    def __init__(self, config: CellConfig, truth: str, seed: int, workspace: Workspace) -> None:
        self.config = cell_with_truth(config, truth)
        self.truth = truth
        self.seed = seed
        self.workspace = workspace
        self.cell = SimulatedCell(self.config, seed)
        self.board = Checkerboard.covering(workspace.x_range_m, workspace.y_range_m, self.config.plant().scene.table_height_m)
        self.arm = self.cell.jrc_arm

    # -- where to look --------------------------------------------------------------

    def camera_target(self, x_m: float, y_m: float, height_m: float | None = None, tilt: Matrix | None = None) -> Matrix:
        """bMe that puts the NOMINAL camera over (x, y) at a height over the table, tool
        down, turned by the rotation vector ``tilt`` (rad) about its own axes."""
        height = self.workspace.camera_height_m if height_m is None else height_m
        bMc = transform(bRe_TOOL_DOWN, (x_m, y_m, self.board.table_height_m + height))
        if tilt is not None:
            bMc = bMc @ exp_twist(np.concatenate((np.zeros(3), tilt)))
        return bMc @ inverse(self.config.nominal.eMc)

    def reachable(self, bMe: Matrix) -> bool:
        """Whether the JRC's own IK reaches bMe (a quick screen before moving)."""
        try:
            self.arm.ik(bMe, self.cell.state.q, restarts=2, tolerance_m=1e-7, tolerance_rad=1e-7)
        except UnreachableTarget:
            return False
        return True

    def grid_targets(self) -> tuple[list[Matrix], int]:
        """The grid's viewpoints the arm reaches, and how many of the grid it does not."""
        targets = [self.camera_target(x, y) for x, y in self.workspace.grid()]
        reached = [bMe for bMe in targets if self.reachable(bMe)]
        return reached, len(targets) - len(reached)

    def heldout_targets(self, count: int, rng: np.random.Generator) -> list[Matrix]:
        """Random reachable viewpoints in the workspace: a fit has seen none of them."""
        return self._random_reachable(count, rng, lambda: self.camera_target(*self._random_xy(rng)))

    def varying_targets(
        self,
        count: int,
        rng: np.random.Generator,
        heights_m: tuple[float, float] = (0.26, 0.34),
        tilt_rad: float = np.deg2rad(3.0),
        yaw_rad: float = np.deg2rad(10.0),
    ) -> list[Matrix]:
        """Random reachable viewpoints at varying height, tilt and yaw (the 6-DOF variant)."""

        def draw() -> Matrix:
            tilt = np.array([rng.uniform(-tilt_rad, tilt_rad), rng.uniform(-tilt_rad, tilt_rad), rng.uniform(-yaw_rad, yaw_rad)])
            return self.camera_target(*self._random_xy(rng), rng.uniform(*heights_m), tilt)

        return self._random_reachable(count, rng, draw)

    def rotated_targets(
        self, count: int, rng: np.random.Generator, centre_xy: tuple[float, float], tilt_deg: tuple[float, float] = (8.0, 20.0)
    ) -> list[Matrix]:
        """Viewpoints looking at the board around ``centre_xy`` from tilted directions with
        turns about the optical axis: the wrist rotations AX = XB needs (planar moves are
        degenerate for it)."""

        def draw() -> Matrix:
            # Turns by whole quarter turns (and a little) keep the board's rows along the
            # image's: OpenCV's sector detector often mis-links a grid turned 20-70 deg.
            tilt, azimuth = np.deg2rad(rng.uniform(*tilt_deg)), rng.uniform(0, 2 * np.pi)
            turn = np.deg2rad(90.0 * rng.integers(0, 4) + rng.uniform(-5.0, 5.0))
            look_at = np.array([*centre_xy, self.board.table_height_m]) + np.append(rng.uniform(-0.02, 0.02, 2), 0.0)
            # Tool down, tilted by `tilt` about a horizontal axis at `azimuth`, turned about the optical axis.
            bRc = exp_twist(np.concatenate((np.zeros(3), tilt * np.array([np.cos(azimuth), np.sin(azimuth), 0.0]))))[:3, :3]
            bRc = bRc @ bRe_TOOL_DOWN @ rot_z(turn)
            eye = look_at - bRc[:, 2] * self.workspace.camera_height_m
            return transform(bRc, eye) @ inverse(self.config.nominal.eMc)

        return self._random_reachable(count, rng, draw)

    def _random_xy(self, rng: np.random.Generator) -> tuple[float, float]:
        return rng.uniform(*self.workspace.x_range_m), rng.uniform(*self.workspace.y_range_m)

    def _random_reachable(self, count: int, rng: np.random.Generator, draw: Callable[[], Matrix]) -> list[Matrix]:
        targets: list[Matrix] = []
        for _ in range(200 * count):
            if len(targets) == count:
                break
            bMe = draw()
            if self.reachable(bMe):
                targets.append(bMe)
        if len(targets) < count:
            raise ValueError(
                f"only {len(targets)} of {count} random viewpoints are reachable in the workspace {self.workspace.as_dict()}"
            )
        return targets

    # -- looking ----------------------------------------------------------------------

    def look(self, bMe_target: Matrix) -> tuple[Matrix, Matrix, Matrix]:
        """Move to bMe_target and find the board: (pixels, world, reported bMe).

        The image is the TRUE camera's from its TRUE pose; the corners are named with the
        reported pose and the NOMINAL camera and hand-eye. Raises UnreachableTarget or
        BoardNotFound.
        """
        self.cell.execute(PositionCommand(bMe_target, MOVE_SPEED_M_S, 0.0))
        bMe = self.cell.measure(look=False).bMe
        truth = self.cell.truth.model
        image = self.board.render(truth.camera, self.cell.ground_truth_bMe() @ truth.eMc)
        nominal = self.config.nominal
        bMc_nominal = bMe @ nominal.eMc

        def lattice_of(pixels: Matrix) -> Matrix:
            return self.board.back_project(nominal.camera, bMc_nominal, pixels) / self.board.square_m

        view = detect_board(self.board, image, lattice_of)
        return view.corners_px, view.corners_w, bMe

    def collect(
        self, targets: Iterable[Matrix], on_view: Callable[[str], None] | None = None
    ) -> tuple[CalibrationDataset, CollectionCounts]:
        """Look from every target; viewpoints the arm cannot reach or whose board cannot be
        named are skipped and counted. Pixels are noise-free detections (see add_pixel_noise)."""
        targets = list(targets)
        pixels: list[Matrix] = []
        world: list[Matrix] = []
        views: list[np.ndarray] = []
        poses: list[Matrix] = []
        unreachable = 0
        refused: dict[str, int] = {}
        for bMe_target in targets:
            try:
                px, w, bMe = self.look(bMe_target)
            except UnreachableTarget:
                unreachable += 1
                note = "unreachable"
            except BoardNotFound as exc:
                refused[str(exc)] = refused.get(str(exc), 0) + 1
                note = "board refused"
            else:
                pixels.append(px)
                world.append(w)
                views.append(np.full(len(px), len(poses)))
                poses.append(bMe)
                note = f"{len(px)} corners"
            if on_view is not None:
                on_view(note)
        if not poses:
            raise ValueError(
                f"no viewpoint of {len(targets)} gave a named board ({unreachable} unreachable, refused: {refused or 'none'})"
            )
        dataset = CalibrationDataset(
            np.concatenate(pixels),
            np.concatenate(world),
            np.concatenate(views).astype(np.int64),
            np.array(poses),
            self.metadata(),
        )
        counts = CollectionCounts(len(targets), unreachable, refused, len(poses), dataset.size)
        return dataset, counts

    def metadata(self) -> dict[str, Any]:
        return {
            "truth": self.truth,
            "cell": self.config.source,
            "seed": self.seed,
            "workspace": self.workspace.as_dict(),
            "board": {
                "square_mm": 1000 * self.board.square_m,
                "corner_range": list(self.board.corner_range),
                "table_height_mm": 1000 * self.board.table_height_m,
            },
            "pixel_noise_px": 0.0,
        }


def add_pixel_noise(dataset: CalibrationDataset, noise_px: float, seed: int, stream: int = 0) -> CalibrationDataset:
    """The dataset with zero-mean Gaussian noise of ``noise_px`` (px) on every corner,
    drawn from the generator (seed, stream): one stream per dataset of a collection."""
    if not (np.isfinite(noise_px) and noise_px >= 0.0):
        raise ValueError(f"pixel noise must be finite and >= 0, got {noise_px!r}")
    if noise_px == 0.0:
        return dataset.with_pixels(dataset.pixels_px.copy(), pixel_noise_px=0.0)
    rng = np.random.default_rng([seed, 7, stream])
    return dataset.with_pixels(
        dataset.pixels_px + rng.normal(0.0, noise_px, dataset.pixels_px.shape), pixel_noise_px=float(noise_px)
    )
