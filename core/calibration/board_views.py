"""The commissioning board in one image: every inner corner found and named by the board.

The board (``BoardConfig``: square side s, (cols, rows) inner corners) is seen whole, so
OpenCV's sector-based detector is asked for exactly its pattern
(``findChessboardCornersSB``, its default flags). It
returns the grid ordered from one of its ends, which end it does not say; a square
pattern may also come back transposed. The board names its own corners: its square
[0, s] x [0, s] (diagonally beyond inner corner (0, 0), inside the pattern) is black, so
the inner square (i, j) is black when i + j is even. Of the orderings of the grid, the
one whose squares show that colouring, and which sees the board from its printed side
(its z axis towards the camera: x turns to y anticlockwise as the screen shows it), names the
corners. Nothing here uses a model of the camera or of the arm: a view is named by what
it shows or refused (``BoardNotFound``, saying why). A board with cols + rows even looks
the same turned half round; it cannot be named and is refused.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vservo.core.cell.config import BoardConfig
from vservo.core.errors import VservoError
from vservo.core.geometry.camera import CameraModel
from vservo.core.geometry.spatial import Matrix

# The share of the pattern's inner squares whose colour must match the naming: a glint
# or the laser spot may spoil one square, a wrong ordering spoils all of them.
_COLOUR_AGREEMENT = 0.9
# The detector's exhaustive search draws from OpenCV's global random generator: seeded,
# a view is found or refused the same way every time.
_DETECTOR_SEED = 0


class BoardNotFound(VservoError, ValueError):
    """No checkerboard, or none that can be named, in an image; the message says why."""


@dataclass(frozen=True, eq=False)
class BoardView:
    """The board's corners found in one image: pixels (N, 2) and the same corners in the
    board frame (N, 3), in board order (row by row, x fastest), both read-only."""

    corners_px: Matrix
    corners_board: Matrix

    def __post_init__(self) -> None:
        pixels = np.array(self.corners_px, dtype=float)
        board = np.array(self.corners_board, dtype=float)
        if pixels.ndim != 2 or pixels.shape[1] != 2 or board.shape != (len(pixels), 3):
            raise ValueError(
                f"a board view needs corners_px (N, 2) and corners_board (N, 3), got {pixels.shape} and {board.shape}"
            )
        if not (np.all(np.isfinite(pixels)) and np.all(np.isfinite(board))):
            raise ValueError("a board view's corners must be finite")
        pixels.flags.writeable = False
        board.flags.writeable = False
        object.__setattr__(self, "corners_px", pixels)
        object.__setattr__(self, "corners_board", board)

    def __len__(self) -> int:
        return len(self.corners_px)


def _grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 2:
        return image
    raise BoardNotFound(f"an image must be grey (H, W) or BGR (H, W, 3), got shape {image.shape}")


def _orderings(grid: np.ndarray) -> list[np.ndarray]:
    """The grid (rows, cols, 2) read from each of its ends, and transposed when square."""
    flips = [grid, grid[::-1], grid[:, ::-1], grid[::-1, ::-1]]
    if grid.shape[0] == grid.shape[1]:
        flips += [np.transpose(g, (1, 0, 2)) for g in flips]
    return flips


def _seen_from_front(grid: np.ndarray) -> bool:
    """Whether x (along a row) turns anticlockwise to y (down the rows) as the screen shows
    it, v pointing down: the board's z axis, out of its printed side, faces the camera (a
    mirrored ordering turns the other way)."""
    along_x = grid[:, -1].mean(axis=0) - grid[:, 0].mean(axis=0)
    along_y = grid[-1].mean(axis=0) - grid[0].mean(axis=0)
    return float(along_x[0] * along_y[1] - along_x[1] * along_y[0]) < 0.0


def _colour_agreement(grey: np.ndarray, grid: np.ndarray) -> float:
    """The share of inner squares (i, j) that are dark exactly when i + j is even; each
    square is read at its centre (the mean of its four corners), over a 3 x 3 patch."""
    centres = 0.25 * (grid[:-1, :-1] + grid[1:, :-1] + grid[:-1, 1:] + grid[1:, 1:])
    j, i = np.meshgrid(np.arange(centres.shape[0]), np.arange(centres.shape[1]), indexing="ij")
    blurred = cv2.blur(grey.astype(np.float32), (3, 3))
    cu = np.clip(np.round(centres[..., 0]).astype(int), 0, grey.shape[1] - 1)
    cv = np.clip(np.round(centres[..., 1]).astype(int), 0, grey.shape[0] - 1)
    levels = blurred[cv, cu]
    dark = levels < 0.5 * (levels.min() + levels.max())
    return float(np.mean(dark == ((i + j) % 2 == 0)))


def find_board(board: BoardConfig, image: np.ndarray, spot_px: Matrix | None = None, spot_radius_px: float = 0.0) -> BoardView:
    """The board's corners in ``image``, named by the board (module docstring).

    ``spot_px`` (2,), with ``spot_radius_px``: corners nearer than that to the pixel (the
    laser spot, whose glare shifts them) are left out of the view.
    """
    cols, rows = board.inner_corners
    if (cols + rows) % 2 == 0:
        raise BoardNotFound(
            f"a board of {cols} x {rows} inner corners looks the same turned half round: "
            "its corners cannot be named (use one with an odd and an even count)"
        )
    grey = _grey(np.asarray(image))
    if grey.dtype != np.uint8:
        raise BoardNotFound(f"an image must hold 8-bit pixels, got {grey.dtype}")
    cv2.setRNGSeed(_DETECTOR_SEED)
    # Default flags: CALIB_CB_EXHAUSTIVE | CALIB_CB_ACCURACY about doubles the time and moves
    # every corner the commissioning figures were measured with, for a board seen whole anyway.
    found, corners = cv2.findChessboardCornersSB(grey, (cols, rows))
    if not found:
        raise BoardNotFound(f"no checkerboard of {cols} x {rows} inner corners in the image (all of it must be in view)")
    grid = corners.reshape(rows, cols, 2).astype(np.float64)
    named = [g for g in _orderings(grid) if _seen_from_front(g) and _colour_agreement(grey, g) >= _COLOUR_AGREEMENT]
    if not named:
        raise BoardNotFound(
            "no ordering of the grid shows the board's colouring (its square beyond corner (0, 0) "
            "black): the squares are not seen clearly enough to name the corners"
        )
    if len(named) > 1:
        raise BoardNotFound(f"{len(named)} orderings of the grid show the board's colouring: the corners cannot be named")
    pixels = named[0].reshape(-1, 2)
    keep = np.ones(len(pixels), dtype=bool)
    if spot_px is not None:
        keep = np.linalg.norm(pixels - np.asarray(spot_px, dtype=float), axis=1) >= spot_radius_px
    return BoardView(pixels[keep], board.corners_board()[keep])


def table_points(camera: CameraModel, wMc: Matrix, pixels_px: Matrix) -> Matrix:
    """(x, y) (N, 2) in W where the rays through pixels (N, 2) of a camera at wMc meet the
    plane z_W = 0; NaN where a ray does not reach it."""
    wMc = np.asarray(wMc, dtype=float)
    xn = camera.pixel_to_normalized(pixels_px)
    rays_w = np.column_stack((xn, np.ones(len(xn)))) @ wMc[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = -wMc[2, 3] / rays_w[:, 2]
    hits = wMc[:3, 3] + rays_w * np.where(reach > 0.0, reach, np.nan)[:, None]
    return hits[:, :2]
