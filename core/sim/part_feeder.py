"""A new part on the simulated table: what a feeder, or an operator's hand, brings.

The part arrives near where the job was taught, at a random offset and turn: the servo's
job is to absorb exactly this (the thesis's parts arrive by hand or on a feeder).
"""

from __future__ import annotations

import numpy as np

from vservo.core.geometry.spatial import Matrix, inverse, rot_z, transform
from vservo.core.sim.plant import SimulatedCell

PART_OFFSET_M = 0.015
PART_YAW_RAD = np.deg2rad(20.0)


def present_part(cell: SimulatedCell, taught_bMo: Matrix, rng: np.random.Generator) -> Matrix:
    """Put a new part on the table within PART_OFFSET_M and PART_YAW_RAD (about its
    centre) of ``taught_bMo``, releasing whatever the cup held; returns its pose bMo."""
    offset = rng.uniform(-PART_OFFSET_M, PART_OFFSET_M, 2)
    yaw = rng.uniform(-PART_YAW_RAD, PART_YAW_RAD)
    side = cell.state.scene.cube.side_m
    centre = transform(t=(side / 2, side / 2, 0.0))
    bMo = transform(t=(*offset, 0.0)) @ taught_bMo @ centre @ transform(rot_z(yaw)) @ inverse(centre)
    cell.vacuum(False)
    cell.place_cube(bMo)
    return bMo
