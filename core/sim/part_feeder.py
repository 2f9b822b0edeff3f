"""A new part on the simulated table: what a feeder, or an operator's hand, brings.

``present_part``: the part arrives near where the job was taught, at a random offset and
turn, what the servo's job is to absorb (the thesis's parts arrive by hand or on a
feeder). ``place_part``: the part put down at a given place, anywhere on the table clear
of the metal part, for locating it from a survey view.
"""

from __future__ import annotations

import numpy as np

from vservo.core.cell.scene import arrival
from vservo.core.geometry.spatial import Matrix, inverse, rot_z, transform
from vservo.core.sim.plant import CellStateError, SimulatedCell


def present_part(cell: SimulatedCell, taught_bMo: Matrix, rng: np.random.Generator) -> Matrix:
    """Put a new part on the table within core/cell/scene.py's arrival() (about its
    centre) of ``taught_bMo``, releasing whatever the cup held; returns its pose bMo."""
    _check_table_free(cell)
    offset, yaw = arrival(rng)
    side = cell.state.scene.cube.side_m
    centre = transform(t=(side / 2, side / 2, 0.0))
    bMo = transform(t=(*offset, 0.0)) @ taught_bMo @ centre @ transform(rot_z(yaw)) @ inverse(centre)
    cell.vacuum(False)
    cell.place_cube(bMo)
    return bMo


def place_part(cell: SimulatedCell, x_m: float, y_m: float, yaw_rad: float) -> Matrix:
    """Put the part resting on the table with its frame O (a top-face corner) at (x_m, y_m)
    in B, turned yaw_rad about the vertical, releasing whatever the cup held; returns bMo.

    Raises ValueError for a place off the table or overlapping the metal part, and
    CellStateError while the board is laid.
    """
    values = {"x": x_m, "y": y_m, "yaw": yaw_rad}
    for name, value in values.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise ValueError(f"the part's {name} must be a finite number, got {value!r}")
    _check_table_free(cell)
    scene = cell.state.scene
    side = scene.cube.side_m
    bMo = transform(rot_z(float(yaw_rad)), (float(x_m), float(y_m), scene.table_height_m + side))
    footprint = scene.cube.moved_to(bMo).corners_b[:, :2]
    if np.any(np.abs(footprint) > scene.table_half_size_m):
        raise ValueError(
            f"the part at x = {1000 * x_m:g} mm, y = {1000 * y_m:g} mm would hang off the table "
            f"(it spans +-{1000 * scene.table_half_size_m:g} mm about the base)"
        )
    if _overlap(footprint, _outline_b(scene.metal_part.boxes[0].bMx, scene.metal_part.boxes[0].half_extents)):
        px, py = 1000 * scene.metal_part.bMp[:2, 3]
        raise ValueError(
            f"the part at x = {1000 * x_m:g} mm, y = {1000 * y_m:g} mm would overlap the metal part "
            f"(centred at x = {px:g} mm, y = {py:g} mm)"
        )
    cell.vacuum(False)
    cell.place_cube(bMo)
    return bMo


def _check_table_free(cell: SimulatedCell) -> None:
    if not cell.state.scene.parts_on_table:
        raise CellStateError("the board is laid on the table: take it away before a part is put there")


def _outline_b(bMx: Matrix, half_extents: Matrix) -> Matrix:
    """A box's footprint on the table, (4, 2) in B (the metal part stands level)."""
    hx, hy = half_extents[:2]
    local = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]])
    return (local @ bMx[:3, :3].T + bMx[:3, 3])[:, :2]


def _overlap(a: Matrix, b: Matrix) -> bool:
    """Whether two convex polygons (n, 2) overlap, by the separating axis theorem."""
    for polygon in (a, b):
        edges = np.roll(polygon, -1, axis=0) - polygon
        for normal in np.column_stack((-edges[:, 1], edges[:, 0])):
            pa, pb = a @ normal, b @ normal
            if pa.max() <= pb.min() or pb.max() <= pa.min():
                return False
    return True
