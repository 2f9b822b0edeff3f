"""The physical objects of the cell: table, the 20 mm cube, the metal part and the checkerboard.

Everything is expressed in the robot base frame B. The scene is what the simulator
ray-casts against (the laser spot, occlusion of corners); it is also the nominal layout
an operator configures. Geometry is a set of oriented boxes, enough for a table-top
assembly cell and exact to intersect.

Object frame O (docs/thesis-notes.md section 6): it sits at one corner of the cube's top face,
the face spans +x and +y of O from 0 to the side length, and +z of O points out of the
face, so the cube's body lies at -side <= z <= 0. The four features are the top-face
corners in the order (0, 0), (s, 0), (s, s), (0, s).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from vservo.core.geometry.laser import Ray
from vservo.core.geometry.spatial import Matrix, inverse, transform

# How far from where its job was taught a new part arrives (a feeder's, or an operator's
# hand's spread): what the servo's job is to absorb.
PART_OFFSET_M = 0.015
PART_YAW_RAD = np.deg2rad(20.0)


def arrival(rng: np.random.Generator) -> tuple[Matrix, float]:
    """Where a new part arrives from where its job was taught: an offset (x, y in m, each
    within PART_OFFSET_M) and a turn about its centre (rad, within PART_YAW_RAD)."""
    offset = rng.uniform(-PART_OFFSET_M, PART_OFFSET_M, 2)
    return offset, float(rng.uniform(-PART_YAW_RAD, PART_YAW_RAD))


@dataclass(frozen=True)
class Box:
    """An oriented box: bMx is the pose of its centre, half_extents its half sizes (m)."""

    name: str
    bMx: Matrix
    half_extents: Matrix
    xMb: Matrix = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Ray casting is the simulator's inner loop: invert the pose once, not per ray.
        object.__setattr__(self, "xMb", inverse(self.bMx))

    def intersect(self, ray: Ray) -> float | None:
        """Distance along ``ray`` (in B) to the first entry into the box, by the slab method.

        A ray starting inside the box returns its exit distance, so a beam leaving a
        surface it lies on still reports that surface.
        """
        xMb = self.xMb
        origin = xMb[:3, :3] @ ray.origin + xMb[:3, 3]
        direction = xMb[:3, :3] @ ray.direction
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-self.half_extents - origin) / direction
            t2 = (self.half_extents - origin) / direction
        # Axis-parallel rays: inside the slab means unbounded, outside means no hit.
        parallel = np.abs(direction) < 1e-15
        inside_slab = np.abs(origin) <= self.half_extents
        t_near = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
        t_far = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
        enter, leave = float(np.max(t_near)), float(np.min(t_far))
        if enter > leave or leave < 0.0:
            return None
        return enter if enter >= 0.0 else leave


@dataclass(frozen=True)
class RayHit:
    """Where a ray first meets the scene."""

    distance_m: float
    point_b: Matrix
    surface: str


@dataclass(frozen=True)
class Cube:
    """The part to pick: a cube of side ``side_m`` whose frame O is at a top-face corner.

    The top face carries an orientation mark, a dark disc near corner 0 (like the pin-1
    dot of a chip): a square's corners are symmetric, and without it no image could say
    which corner is which after a half turn (task 1).
    """

    bMo: Matrix
    side_m: float = 0.020
    mark_radius_m: float = 0.0025

    @property
    def mark_o(self) -> Matrix:
        """Centre of the orientation mark in O: on the top face, a fifth of the side from corner 0."""
        return np.array([0.2 * self.side_m, 0.2 * self.side_m, 0.0])

    @property
    def corners_o(self) -> Matrix:
        """The four top-face corners in O, in feature order, (4, 3)."""
        s = self.side_m
        return np.array([[0.0, 0.0, 0.0], [s, 0.0, 0.0], [s, s, 0.0], [0.0, s, 0.0]])

    @property
    def corners_b(self) -> Matrix:
        """The four top-face corners in B, (4, 3)."""
        return self.corners_o @ self.bMo[:3, :3].T + self.bMo[:3, 3]

    @property
    def reference_b(self) -> Matrix:
        """The bottom corner below corner 0, in B: a model point off the top face's plane."""
        return self.bMo[:3, :3] @ np.array([0.0, 0.0, -self.side_m]) + self.bMo[:3, 3]

    @property
    def box(self) -> Box:
        s = self.side_m
        return Box("cube", self.bMo @ transform(t=(s / 2, s / 2, -s / 2)), np.full(3, s / 2))

    def moved_to(self, bMo: Matrix) -> Cube:
        return Cube(bMo, self.side_m, self.mark_radius_m)


@dataclass(frozen=True)
class MetalPart:
    """The receiving part: a block with a square pocket open to the top.

    bMp is the pose of the pocket frame P: at the centre of the pocket's floor, +z out of
    the pocket. A cube is placed when its bottom face sits on that floor.
    """

    bMp: Matrix
    pocket_side_m: float = 0.022
    pocket_depth_m: float = 0.012
    wall_m: float = 0.015
    floor_m: float = 0.010

    @property
    def boxes(self) -> tuple[Box, ...]:
        half_pocket = self.pocket_side_m / 2
        outer = half_pocket + self.wall_m
        depth = self.pocket_depth_m
        half_wall = self.wall_m / 2
        floor = Box(
            "metal_part",
            self.bMp @ transform(t=(0.0, 0.0, -self.floor_m / 2)),
            np.array([outer, outer, self.floor_m / 2]),
        )
        walls = []
        for sign in (-1.0, 1.0):
            centre = sign * (half_pocket + half_wall)
            walls.append(
                Box(
                    "metal_part",
                    self.bMp @ transform(t=(centre, 0.0, depth / 2)),
                    np.array([half_wall, outer, depth / 2]),
                )
            )
            walls.append(
                Box(
                    "metal_part",
                    self.bMp @ transform(t=(0.0, centre, depth / 2)),
                    np.array([half_pocket, half_wall, depth / 2]),
                )
            )
        return (floor, *walls)


@dataclass(frozen=True)
class LaidBoard:
    """The calibration checkerboard as it lies on the table: a printed sheet of no thickness.

    Board frame as [board] in the cell file: origin at the inner corner (0, 0) on the
    sheet, x along the columns, y along the rows, z up; the square [0, s] x [0, s] is
    black. The pattern has (cols + 1) x (rows + 1) squares around the cols x rows inner
    corners, and the white sheet one white square of margin around the pattern.
    """

    bMboard: Matrix
    square_m: float
    inner_corners: tuple[int, int]
    sheet_b: Matrix = field(init=False, repr=False, compare=False)
    black_squares_b: Matrix = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # The renderer draws these every frame: place them in B once.
        s = self.square_m
        cols, rows = self.inner_corners
        sheet = np.array([[-2 * s, -2 * s], [(cols + 1) * s, -2 * s], [(cols + 1) * s, (rows + 1) * s], [-2 * s, (rows + 1) * s]])
        unit = np.array([[0.0, 0.0], [s, 0.0], [s, s], [0.0, s]])
        squares = [unit + (i * s, j * s) for j in range(-1, rows) for i in range(-1, cols) if (i + j) % 2 == 0]
        object.__setattr__(self, "sheet_b", self._to_b(sheet))
        object.__setattr__(self, "black_squares_b", self._to_b(np.array(squares)))

    def _to_b(self, xy_board: Matrix) -> Matrix:
        points = np.concatenate((xy_board, np.zeros(xy_board.shape[:-1] + (1,))), axis=-1)
        return points @ self.bMboard[:3, :3].T + self.bMboard[:3, 3]

    @property
    def corners_b(self) -> Matrix:
        """The inner corners (N, 3) in B, row by row (x fastest), the order OpenCV reports them in."""
        cols, rows = self.inner_corners
        i, j = np.meshgrid(np.arange(cols), np.arange(rows))
        xy = np.column_stack((i.ravel(), j.ravel())) * self.square_m
        return self._to_b(xy.astype(float))


@dataclass(frozen=True)
class Scene:
    """Table plane z = table_height_m in B, the cube and the metal part, or the board.

    While a board is laid the table is cleared (as an integrator clears it to lay the
    sheet): the cube and the metal part are off it, kept where they go back when the
    board is taken away, and the scene's surfaces are the table and the sheet on it.
    """

    table_height_m: float
    cube: Cube
    metal_part: MetalPart
    table_half_size_m: float = 1.0
    board: LaidBoard | None = None
    boxes: tuple[Box, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # The table is a thin slab under z = table_height, large enough to fill any view.
        table = Box(
            "table",
            transform(t=(0.0, 0.0, self.table_height_m - 0.005)),
            np.array([self.table_half_size_m, self.table_half_size_m, 0.005]),
        )
        # The sheet has no thickness: a beam that lands on it lands on the table.
        boxes = (table,) if self.board is not None else (table, self.cube.box, *self.metal_part.boxes)
        object.__setattr__(self, "boxes", boxes)

    @property
    def parts_on_table(self) -> bool:
        """Whether the cube and the metal part are on the table (no board laid)."""
        return self.board is None

    def raycast(self, ray: Ray) -> RayHit | None:
        """First surface hit by a ray given in B, or None if it leaves the scene."""
        best: RayHit | None = None
        for box in self.boxes:
            distance = box.intersect(ray)
            if distance is not None and (best is None or distance < best.distance_m):
                best = RayHit(distance, ray.point_at(distance), box.name)
        return best

    def visible_from(self, bP_eye: Matrix, bP: Matrix, tolerance_m: float = 1e-6) -> bool:
        """True if nothing in the scene lies between the eye and the point ``bP``."""
        offset = np.asarray(bP, dtype=float) - np.asarray(bP_eye, dtype=float)
        distance = float(np.linalg.norm(offset))
        hit = self.raycast(Ray(np.asarray(bP_eye, dtype=float), offset / distance))
        return hit is None or hit.distance_m >= distance - tolerance_m

    def with_cube(self, cube: Cube) -> Scene:
        return replace(self, cube=cube)

    def with_board(self, board: LaidBoard | None) -> Scene:
        """The board laid (the table cleared of the parts), or taken away (None: the parts back)."""
        return replace(self, board=board)
