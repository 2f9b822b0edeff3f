"""Which of a part's symmetric grasps to pick and place it with.

A part whose top face is a square looks, and sits in its pocket, the same after a quarter
turn about the face's vertical axis through its centre; the cup holds it as well there
as at the taught grasp. So the taught grasp turned by k quarter turns about that axis
(k = 0 .. symmetry - 1; symmetry 4 for a square face, 2 for a face that only a half turn
maps onto itself, 1 for none) is an equally good grasp, and the place turned the same way
puts the part in the pocket the same way up to that symmetry.

Of these, a run takes the one that turns the flange least from where it is (and, for the
place, on to the check pose after it) among those the safety layer lets the arm reach:
the JRC's rotation rate makes each half turn of the flange seconds of cell time, and a
grasp turned away from the arm's reach can put a joint at its limit.

Frames: p is the flange at the taught grasp (the pick pose, or the place pose: the part
sits in the flange alike at both), O the part's frame (origin at a top-face corner, z up
out of the face, as core/cell/scene.py's Cube). The grasp turned by k is

    bMe_k = bMe @ pMo @ T_k @ pMo^-1,    T_k = C Rz(2 pi k / symmetry) C^-1,

C the translation to the top face's centre (s/2, s/2, 0) in O.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vservo.core.geometry.spatial import Matrix, inverse, rot_z, rotation_angle, transform

SYMMETRIES = (1, 2, 4)


@dataclass(frozen=True)
class GraspChoice:
    """The grasp chosen: ``turns`` of 360 / symmetry deg from the taught one, the flange
    pose ``bMe`` it puts the flange at, how far the flange turns to get there (and on to
    the next pose, when one was given), and how many grasps that turn it less were left
    out because the arm cannot reach them."""

    turns: int
    bMe: Matrix
    turn_rad: float
    unreachable_nearer: int


def turned_grasp(bMe: Matrix, pMo: Matrix, side_m: float, symmetry: int, turns: int) -> Matrix:
    """The flange pose of the grasp bMe turned ``turns`` times by 360 / symmetry deg about
    the part's vertical axis through its top face's centre (module docstring)."""
    centre = transform(t=(side_m / 2, side_m / 2, 0.0))
    oTo = centre @ transform(rot_z(2.0 * np.pi * turns / symmetry)) @ inverse(centre)
    return np.asarray(bMe, dtype=float) @ pMo @ oTo @ inverse(pMo)


def grasp_choice(
    bMe_taught: Matrix,
    pMo: Matrix,
    side_m: float,
    symmetry: int,
    bMe_from: Matrix,
    reachable: Callable[[Matrix], bool],
    bMe_next: Matrix | None = None,
) -> GraspChoice:
    """The grasp of least flange turn from bMe_from (plus on to bMe_next) that ``reachable``
    accepts; the taught grasp (turns 0) when none is, so that its move is refused saying why.

    reachable(bMe_k): whether the arm's moves to and from the grasp at bMe_k pass the
    safety layer's checks (the configured kinematic model, never a simulator's truth).
    """
    if symmetry not in SYMMETRIES:
        raise ValueError(f"grasp symmetry {symmetry!r}: one of {', '.join(map(str, SYMMETRIES))}")

    def turn(bMa: Matrix, bMb: Matrix) -> float:
        return rotation_angle(bMa[:3, :3].T @ bMb[:3, :3])

    candidates = []
    for k in range(symmetry):
        bMe_k = turned_grasp(bMe_taught, pMo, side_m, symmetry, k)
        cost = turn(bMe_from, bMe_k) + (0.0 if bMe_next is None else turn(bMe_k, bMe_next))
        candidates.append(GraspChoice(k, bMe_k, cost, 0))
    candidates.sort(key=lambda choice: (choice.turn_rad, choice.turns))
    for nearer, choice in enumerate(candidates):
        if reachable(choice.bMe):
            return GraspChoice(choice.turns, choice.bMe, choice.turn_rad, nearer)
    taught = next(choice for choice in candidates if choice.turns == 0)
    return GraspChoice(0, taught.bMe, taught.turn_rad, len(candidates))
