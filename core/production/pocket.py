"""The taught part against the cell's modelled pocket: where the pick and place set it down.

While a job is taught (Fig. C-2) the part is known three ways: as the desired image saw it
(bMo, planar PnP with the nominal camera), as the pick holds it (eMo: the desired view's
part seen from the flange that picks it), and so where a place pose sets it down
(bMe_place eMo). Against the pocket of the cell file's [metal_part] this says, before the
job is saved, how far off centre and how turned every run will place the part, and which
flange pose sets it down centred in the pocket (the "Go above the pocket" aid).

The part's top face is a square: a quarter turn of it fits the pocket as well, so turns
are compared modulo 90 deg.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vservo.core.cell.scene import MetalPart
from vservo.core.geometry.spatial import Matrix, inverse, rot_z, transform

QUARTER_TURN = np.pi / 2


@dataclass(frozen=True)
class PocketFit:
    """The part as a place pose sets it down, in the pocket's frame P."""

    bMo: Matrix  # the part's frame O (a top-face corner, z up) where the place puts it
    offset_mm: float  # its bottom face's centre from the pocket floor's centre, across the floor
    turn_deg: float  # its edges' turn from the pocket's, modulo the face's quarter turns, in [-45, 45)
    height_mm: float  # its bottom face above the pocket floor

    def words(self) -> str:
        offset, turn, height = (round(value, 1) + 0.0 for value in (self.offset_mm, self.turn_deg, self.height_mm))
        return f"the part sits {offset:.1f} mm and {turn:+.1f} deg from the pocket's centre, {height:+.1f} mm above its floor"


def part_on_flange(taught_bMe: Matrix, eMe_pick: Matrix, seen_bMo: Matrix) -> Matrix:
    """eMo: the part on the flange as the pick holds it, the part of the desired image
    picked by the flange pose taught_bMe eMe_pick (the pick transform of Fig. C-2)."""
    return inverse(taught_bMe @ eMe_pick) @ seen_bMo


def _bottom_centre(side_m: float) -> Matrix:
    return np.array([side_m / 2, side_m / 2, -side_m, 1.0])


def _quarter_turn_error(pMo: Matrix) -> float:
    """The part's turn about the pocket's z, modulo a quarter turn, in [-pi/4, pi/4)."""
    turn = float(np.arctan2(pMo[1, 0], pMo[0, 0]))
    return (turn + QUARTER_TURN / 2) % QUARTER_TURN - QUARTER_TURN / 2


def pocket_fit(bMo: Matrix, pocket: MetalPart, side_m: float) -> PocketFit:
    """How the part at bMo sits in ``pocket``: offset, turn (modulo quarter turns) and height."""
    pMo = inverse(pocket.bMp) @ bMo
    centre = pMo @ _bottom_centre(side_m)
    return PocketFit(
        bMo=bMo,
        offset_mm=1000.0 * float(np.linalg.norm(centre[:2])),
        turn_deg=float(np.rad2deg(_quarter_turn_error(pMo))),
        height_mm=1000.0 * float(centre[2]),
    )


def flange_in_pocket(eMo: Matrix, pocket: MetalPart, side_m: float, bMo_now: Matrix) -> Matrix:
    """bMe that sets the held part down centred in the pocket, its bottom on the floor, its
    edges along the pocket's in the quarter turn nearest the part's at bMo_now (the least
    turn of the wrist)."""
    pMo_now = inverse(pocket.bMp) @ bMo_now
    turn = float(np.arctan2(pMo_now[1, 0], pMo_now[0, 0]))
    quarter = QUARTER_TURN * round(turn / QUARTER_TURN)
    bMo = pocket.bMp @ transform(rot_z(quarter)) @ transform(t=(-side_m / 2, -side_m / 2, side_m))
    return bMo @ inverse(eMo)
