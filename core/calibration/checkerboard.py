"""The calibration checkerboard: its lattice, its image through a camera, and its corners
found in an image and named by the board.

The board lies on the table with its squares along the axes of the world frame W, which
the thesis makes coincide with the robot base frame B (section 2.3.2, step 1): W is B
moved down onto the table surface, so a board corner's world (x, y) is its (x, y) in B.
Inner corner (i, j) of the lattice sits at (i s, j s) with s the square side (10 mm in
the thesis), and square (i, j), spanning [i s, (i + 1) s] x [j s, (j + 1) s], is black
when i + j is even. The board is far larger than the camera's view (about 240 x 180 mm
at 300 mm), as a board under a moving camera must be.

Naming the corners. A partial view of a lattice says nothing of which corner is which,
so the board's own pattern has to. OpenCV's sector-based detector
(``findChessboardCornersSB`` with ``CALIB_CB_LARGER``) returns the ordered grid of inner
corners it sees; the colour of the square diagonally beyond each corner gives the parity
of its lattice index; what remains (the grid's orientation and a whole-number offset) is
fixed by where the JRC's reported pose and the NOMINAL camera model put the
corners. The model only has to be right to within a square (10 mm): it picks whole
numbers, never a coordinate. Every world coordinate comes from the board's lattice, none
from the simulator's truth. A view whose best naming leaves corners more than half a
square from the model, that two namings fit about equally, or whose grid the detector
linked unevenly, is refused (``BoardNotFound``), as an engineer would discard it.

Rendering uses the exact-area rasteriser of the synthetic camera (vservo.core.sim.render): each
black square's edges are subdivided and pushed through the lens distortion, so the
image is what the TRUE camera (intrinsics and distortion) sees from its TRUE pose.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from vservo.core.calibration.board_views import BoardNotFound, table_points
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import Matrix, inverse
from vservo.core.sim.raster import rasterize

# Chords per square edge: a distorted edge of ~27 px becomes 8 chords of ~3 px, whose
# sagitta is far below a thousandth of a pixel for any realistic lens.
_EDGE_CHORDS = 8
# The detector is asked for at least this grid; CALIB_CB_LARGER lets it return more.
_MIN_PATTERN = (5, 4)
# Refusal thresholds of the naming, in squares.
_NAMING_TOLERANCE = 0.5
_NAMING_AMBIGUITY = 0.2
_NAMING_STEP = 0.25
# Detector searches tried per image before a view is refused (see find_corners).
DETECTION_ATTEMPTS = 4


@dataclass(frozen=True)
class Checkerboard:
    """A checkerboard on the table: square side, lattice extent and where W lies in B.

    ``corner_range`` bounds the inner-corner indices (i_min, i_max, j_min, j_max) the
    board has; ``table_height_m`` is the table surface's height in B (W's origin). The
    grey levels and the optical blur (px) are what the rendered image shows.
    """

    square_m: float
    corner_range: tuple[int, int, int, int]
    table_height_m: float
    white_grey: float = 215.0
    black_grey: float = 30.0
    blur_sigma_px: float = 0.6

    def __post_init__(self) -> None:
        if not (np.isfinite(self.square_m) and self.square_m > 0.0):
            raise ValueError(f"square side must be positive, got {self.square_m!r}")
        i_min, i_max, j_min, j_max = self.corner_range
        if i_max <= i_min or j_max <= j_min:
            raise ValueError(f"corner range {self.corner_range} is empty")

    @classmethod
    def covering(
        cls,
        x_range_m: tuple[float, float],
        y_range_m: tuple[float, float],
        table_height_m: float,
        square_m: float = 0.010,
        margin_m: float = 0.2,
    ) -> Checkerboard:
        """A board that covers the given world rectangle plus a margin (for the view's edge)."""
        low = np.floor((np.array([x_range_m[0], y_range_m[0]]) - margin_m) / square_m).astype(int)
        high = np.ceil((np.array([x_range_m[1], y_range_m[1]]) + margin_m) / square_m).astype(int)
        return cls(square_m, (int(low[0]), int(high[0]), int(low[1]), int(high[1])), table_height_m)

    @property
    def bMw(self) -> Matrix:
        """The world frame W in B: B lowered onto the table surface."""
        bMw = np.eye(4)
        bMw[2, 3] = self.table_height_m
        return bMw

    def corner_w(self, ij: Matrix) -> Matrix:
        """World (x, y) of inner corners with lattice indices ij (N, 2)."""
        return np.asarray(ij, dtype=float) * self.square_m

    def _visible_squares(self, camera: CameraModel, wMc: Matrix) -> tuple[range, range]:
        """Index ranges of the squares that may show in the image from wMc (a square of margin)."""
        width, height = camera.image_size
        border = np.array(
            [
                [-0.5, -0.5],
                [width - 0.5, -0.5],
                [width - 0.5, height - 0.5],
                [-0.5, height - 0.5],
                [width / 2, -0.5],
                [width / 2, height - 0.5],
                [-0.5, height / 2],
                [width - 0.5, height / 2],
            ]
        )
        rays_c = np.column_stack((camera.pixel_to_normalized(border), np.ones(len(border))))
        rays_w = rays_c @ wMc[:3, :3].T
        if np.any(~np.isfinite(rays_w)) or np.any(rays_w[:, 2] >= 0.0):
            raise BoardNotFound("the camera does not look down onto the board")
        hits = wMc[:3, 3] - rays_w * (wMc[2, 3] / rays_w[:, 2])[:, None]
        low = np.floor(hits[:, :2].min(axis=0) / self.square_m).astype(int) - 1
        high = np.ceil(hits[:, :2].max(axis=0) / self.square_m).astype(int) + 1
        i_min, i_max, j_min, j_max = self.corner_range
        # Squares lie between corner indices i_min - 1 .. i_max (the board's outer border).
        return range(max(low[0], i_min - 1), min(high[0], i_max + 1)), range(max(low[1], j_min - 1), min(high[1], j_max + 1))

    def render(self, camera: CameraModel, bMc: Matrix) -> np.ndarray:
        """The 8-bit image of the board seen by ``camera`` from bMc (exact area coverage)."""
        wMc = inverse(self.bMw) @ np.asarray(bMc, dtype=float)
        cMw = inverse(wMc)
        width, height = camera.image_size
        image: np.ndarray = np.full((height, width), self.white_grey, dtype=np.float64)  # (GaussianBlur's result is any Mat)
        rows, cols = self._visible_squares(camera, wMc)
        squares = np.array([(i, j) for i in rows for j in cols if (i + j) % 2 == 0], dtype=float)
        if len(squares):
            # Each square's outline, _EDGE_CHORDS points per edge, in W (z = 0).
            t = np.arange(_EDGE_CHORDS) / _EDGE_CHORDS
            unit = np.concatenate(
                [
                    np.column_stack((t, np.zeros_like(t))),
                    np.column_stack((np.ones_like(t), t)),
                    np.column_stack((1.0 - t, np.ones_like(t))),
                    np.column_stack((np.zeros_like(t), 1.0 - t)),
                ]
            )
            outline_w = (squares[:, None, :] + unit[None, :, :]) * self.square_m
            points_w = np.concatenate((outline_w.reshape(-1, 2), np.zeros((outline_w.shape[0] * len(unit), 1))), axis=1)
            points_c = points_w @ cMw[:3, :3].T + cMw[:3, 3]
            pixels = camera.project(points_c).reshape(len(squares), len(unit), 2) + 0.5  # edge coordinates
            # Clockwise on screen counts positive in the rasteriser: orient every outline so.
            x, y = pixels[..., 0], pixels[..., 1]
            area2 = np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1)
            weights = np.where(area2 > 0.0, -1.0, 1.0)[:, None]
            coverage = rasterize(list(pixels), weights, 0, 0, width, height)[0]
            image -= (self.white_grey - self.black_grey) * np.clip(coverage, 0.0, 1.0)
        if self.blur_sigma_px > 0.0:
            image = cv2.GaussianBlur(image, (0, 0), self.blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
        return np.clip(image + 0.5, 0.0, 255.0).astype(np.uint8)

    def back_project(self, camera: CameraModel, bMc: Matrix, pixels_px: Matrix) -> Matrix:
        """World (x, y) (N, 2) where the rays through pixels (N, 2) meet the board, for a
        camera model at bMc: the inverse of ``predict_px``."""
        return table_points(camera, inverse(self.bMw) @ np.asarray(bMc, dtype=float), pixels_px)

    def predict_px(self, camera: CameraModel, bMc: Matrix, ij: Matrix) -> Matrix:
        """Pixels of lattice corners ij (N, 2) seen by ``camera`` from bMc."""
        cMw = inverse(inverse(self.bMw) @ np.asarray(bMc, dtype=float))
        points_w = np.column_stack((self.corner_w(ij), np.zeros(len(ij))))
        return camera.project(points_w @ cMw[:3, :3].T + cMw[:3, 3])


@dataclass(frozen=True)
class BoardView:
    """The corners found in one image: pixels (N, 2), lattice indices (N, 2), world (x, y) (N, 2) in m."""

    corners_px: Matrix
    lattice_ij: Matrix
    corners_w: Matrix


def detect_board(
    board: Checkerboard, image: np.ndarray, lattice_of: Callable[[Matrix], Matrix], attempts: int = DETECTION_ATTEMPTS
) -> BoardView:
    """Find and name the board's corners in an image (``find_corners``, ``name_corners``),
    trying the detector's search up to ``attempts`` times before refusing the view."""
    for attempt in range(attempts):
        try:
            return name_corners(board, image, find_corners(image, attempt), lattice_of)
        except BoardNotFound:
            if attempt == attempts - 1:
                raise
    raise ValueError("attempts must be at least 1")


def find_corners(image: np.ndarray, attempt: int = 0) -> Matrix:
    """OpenCV's sector-based checkerboard detection: the ordered grid of inner corners it
    sees, (rows, cols, 2) sub-pixel positions; ``CALIB_CB_LARGER`` lets the grid run to
    the image's edges, however much of the board lies beyond them.

    The exhaustive search draws from OpenCV's global random generator, and on oblique
    views it sometimes links a grid that skips squares (which ``name_corners`` refuses):
    ``attempt`` seeds the generator, so each attempt is reproducible and another
    attempt searches differently.
    """
    flags = cv2.CALIB_CB_LARGER | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    cv2.setRNGSeed(attempt)
    found, corners, meta = cv2.findChessboardCornersSBWithMeta(image, _MIN_PATTERN, flags)
    if not found or meta is None:
        raise BoardNotFound("no checkerboard found in the image")
    rows, cols = meta.shape
    return corners.reshape(rows, cols, 2).astype(np.float64)


def name_corners(board: Checkerboard, image: np.ndarray, grid_px: Matrix, lattice_of: Callable[[Matrix], Matrix]) -> BoardView:
    """Give each detected corner its lattice index (module docstring).

    ``grid_px`` is the detector's grid (rows, cols, 2); ``lattice_of(pixels)`` maps pixels
    to fractional lattice indices by the NOMINAL model (reported pose, nominal camera and
    hand-eye), only to choose whole numbers:

    1. the grid's step in the lattice along its rows and columns, M (lattice = M rc + d):
       the model's whole-number slope (the detector may step over every other row of a
       strongly distorted board: a coarser lattice of true corners, still usable);
    2. each corner's parity, from the colour of the square diagonally beyond it: the
       lattice square (i, j) at corner (i, j) is black when i + j is even;
    3. the offset d: of the whole-number shifts consistent with the parities, the one
       nearest to the model. It must fit within half a square, and clearly better than
       the next.
    """
    rows, cols = grid_px.shape[:2]
    rc = np.stack(np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij"), axis=-1).reshape(-1, 2)
    pixels = grid_px.reshape(-1, 2)
    modelled = lattice_of(pixels)
    if not np.all(np.isfinite(modelled)):
        raise BoardNotFound("the nominal model cannot map the corners found onto the board")
    affine = np.column_stack((rc, np.ones(len(rc))))
    M = np.round(np.linalg.lstsq(affine, modelled, rcond=None)[0][:2].T).astype(int)
    if round(abs(np.linalg.det(M))) not in (1, 2, 4):
        raise BoardNotFound(f"the detector's grid steps {M.tolist()} through the lattice: not a grid of its corners")
    # The nominal model's error varies smoothly across the image (lens distortion, a
    # tilt): between neighbours it hardly changes, unless the grid steps unevenly.
    offsets = (modelled - rc @ M.T).reshape(rows, cols, 2)
    steps = np.concatenate(
        (np.linalg.norm(np.diff(offsets, axis=0), axis=2).ravel(), np.linalg.norm(np.diff(offsets, axis=1), axis=2).ravel())
    )
    if steps.size and steps.max() > _NAMING_STEP:
        raise BoardNotFound("the detector's grid is not a lattice (it skips squares unevenly)")
    px_per_step = np.linalg.lstsq(affine, pixels, rcond=None)[0][:2].T
    diagonal = px_per_step @ np.linalg.solve(M, np.ones(2))
    probe = np.round(pixels + 0.5 * diagonal).astype(int)
    inside = (probe[:, 0] >= 0) & (probe[:, 0] < image.shape[1]) & (probe[:, 1] >= 0) & (probe[:, 1] < image.shape[0])
    level = 0.5 * (np.percentile(image, 5) + np.percentile(image, 95))
    dark = image[probe[inside, 1], probe[inside, 0]] < level
    base = rc @ M.T
    shift = np.floor(np.median(modelled - base, axis=0)).astype(int)
    candidates: list[tuple[float, Matrix]] = []
    for di in range(shift[0] - 1, shift[0] + 3):
        for dj in range(shift[1] - 1, shift[1] + 3):
            ij = base + np.array([di, dj])
            if np.mean(((ij[inside, 0] + ij[inside, 1]) % 2 == 0) == dark) < 0.9:
                continue
            candidates.append((float(np.median(np.linalg.norm(modelled - ij, axis=1))), ij))
    if not candidates:
        raise BoardNotFound("the squares seen do not alternate as a checkerboard's do")
    candidates.sort(key=lambda c: c[0])
    best_residual, best_ij = candidates[0]
    if best_residual > _NAMING_TOLERANCE:
        raise BoardNotFound(
            f"the corners found lie {best_residual:.2f} squares from where the nominal model puts "
            "the nearest naming: the model is too far off to name them"
        )
    if len(candidates) > 1 and candidates[1][0] - best_residual < _NAMING_AMBIGUITY:
        raise BoardNotFound("two namings of the corners fit the nominal model about equally well")
    i_min, i_max, j_min, j_max = board.corner_range
    if not (
        np.all(best_ij[:, 0] >= i_min)
        and np.all(best_ij[:, 0] <= i_max)
        and np.all(best_ij[:, 1] >= j_min)
        and np.all(best_ij[:, 1] <= j_max)
    ):
        raise BoardNotFound("the corners found run past the board's edge")
    return BoardView(pixels.copy(), best_ij.astype(float), board.corner_w(best_ij))
