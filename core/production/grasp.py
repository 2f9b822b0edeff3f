"""Which of a part's symmetric views to servo on and grasps to pick and place it with.

A part whose top face is a square looks, and sits in its pocket, the same after a quarter
turn about the face's vertical axis through its centre; the cup holds it as well there
as at the taught grasp. So the desired view turned by k quarter turns about that axis
(k allowed by the job's ``grasp_symmetry``: 4 for a square face, any k; 2 for a face
that only a half turn maps onto itself, k even; 1 for none, k = 0) is an equally good
end of the servo, and the taught pick (eMe_pick) and place (bMe_place) from there put the
part in the pocket the same way up to that symmetry: the part sits in the cup turned by
k quarter turns, and in the pocket turned so about its centre.

The turned view is the taught desired image with its corners relabelled (a cyclic shift
by k), nothing else: the camera, its laser and the top face turned together about the
face's vertical axis through its centre keep every pixel where it was. The beam meets the
top face (a plane through that axis, mapped onto itself) at the turned point, which the
turned camera sees at the same pixel and the same depth Z*; the square's corners land on
the corners' places one shift along. So the spot, Z* and the corners' places stay, and
only which corner goes where changes:

    s*_k[i] = s*[(i + k) mod 4],    cdMo_k = cdMo C Rz(k pi / 2) C^-1,

C the translation to the top face's centre (s/2, s/2, 0) in O (the corners of
core/cell/scene.py's Cube run counter-clockwise about z, so corner (i + k) is corner i
turned by k quarter turns). No camera model, hand-eye or laser enters it.

Of these, a run servoes on the one the camera turns least to, decided in the image before
the servo (``view_turns``): the corners seen now against each relabelling of the desired
ones, by the image rotation that carries the one onto the other (the turn about the
camera's axis, which for a camera looking down at the part is the turn about the part).

The grasp itself may turn too: the taught pick and the taught place both turned by the same
j quarter turns about the vacuum cup's axis (the cup frame V, eMv of the cell file),

    bMe_pick_j = bMe_end eMe_pick eMv Rz(j pi / 2) eMv^-1,    bMe_place_j = bMe_place eMv Rz(j pi / 2) eMv^-1,

put the part where the taught ones do: the part's pose in the flange changes by the
inverse of what the place adds, bMo = bMe_place_j (bMe_pick_j^-1 bMo_part) = bMe_place eMe_pick^-1
bMe_end^-1 bMo_part, whatever eMv is. So an eMv off by millimetres changes only where the
flange goes, not where the part lands, and the cup's axis through the part's centre (as
the pick is taught) makes it the part's own quarter turn. Of the j the symmetry allows,
a run takes the one that turns the flange least from the servo's end to the pick, the
place and the check pose after it, among those the safety layer lets the arm reach: the
JRC's rotation rate makes each half turn of the flange seconds of cell time, and with the
cup 60 mm off the flange's axis, a grasp turned away from the arm's reach can put a joint
at its limit. (Turning the pick and the place by different quarter turns would not cancel:
the part would land turned about wherever the model puts the part in the cup, 44.6 mm off
on a cell whose hand-eye is 20 mm off.)

Whether the arm can reach the servo's end at a turned view, and the pick and place from
there, is predicted before the servo (``turned_goal``) from the taught view moved with the
part on the table: the part's move from where it was taught (a shift and a turn about the
vertical, the part lying on the table) carries the taught flange pose of the desired view,
and the view's k quarter turns turn it about the part's vertical axis. The part's move is
estimated through the cell's model, but as a difference of two estimates taken alike (at
the taught view and at the start pose), so that a model's bias mostly cancels; the
prediction only chooses and refuses, it positions nothing.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from vservo.core.geometry.spatial import Matrix, rot_z, rotation_angle, transform
from vservo.core.perception.features import DesiredImage

SYMMETRIES = (1, 2, 4)


def allowed_turns(symmetry: int) -> tuple[int, ...]:
    """The quarter turns k the job's grasp symmetry allows: 4 any, 2 even, 1 none."""
    if symmetry not in SYMMETRIES:
        raise ValueError(f"grasp symmetry {symmetry!r}: one of {', '.join(map(str, SYMMETRIES))}")
    return tuple(range(0, 4, 4 // symmetry))


def turned_desired(desired: DesiredImage, side_m: float, quarter_turns: int) -> DesiredImage:
    """The desired image of the view turned by ``quarter_turns`` about the part's vertical
    axis through its top face's centre (the module's docstring): the corners relabelled,
    cdMo turned with them, the spot and Z* as taught."""
    k = quarter_turns % 4
    if k == 0:
        return desired
    order = (np.arange(4) + k) % 4
    centre = transform(t=(side_m / 2, side_m / 2, 0.0))
    oTo = centre @ transform(rot_z(k * np.pi / 2)) @ np.linalg.inv(centre)
    return replace(
        desired,
        corners_px=np.asarray(desired.corners_px, dtype=float)[order],
        cdMo=np.asarray(desired.cdMo, dtype=float) @ oTo,
        corner_depths_m=np.asarray(desired.corner_depths_m, dtype=float)[order],
    )


def on_table(bMo: Matrix, height_m: float) -> Matrix:
    """A part's pose bMo laid level at ``height_m``: its position's x, y and its turn about
    the base's vertical (a part lying on the table neither tilts nor rises)."""
    bMo = np.asarray(bMo, dtype=float)
    return transform(rot_z(float(np.arctan2(bMo[1, 0], bMo[0, 0]))), (bMo[0, 3], bMo[1, 3], height_m))


def turned_goal(taught_bMe: Matrix, bMo_taught: Matrix, bMo_now: Matrix, side_m: float, quarter_turns: int) -> Matrix:
    """The flange pose the servo ends at on ``turned_desired(.., quarter_turns)`` for the part
    now at bMo_now, taught at bMo_taught (both laid level at the taught height) with the
    flange at taught_bMe: bMo_now T_k^-1 bMo_taught^-1 taught_bMe (T_k as in turned_desired)."""
    height_m = float(np.asarray(bMo_taught)[2, 3])
    centre = transform(t=(side_m / 2, side_m / 2, 0.0))
    oTo = centre @ transform(rot_z(-quarter_turns * np.pi / 2)) @ np.linalg.inv(centre)
    return on_table(bMo_now, height_m) @ oTo @ np.linalg.inv(on_table(bMo_taught, height_m)) @ np.asarray(taught_bMe, float)


def turned_about_cup(bMe: Matrix, eMv: Matrix, quarter_turns: int) -> Matrix:
    """The flange pose bMe turned ``quarter_turns`` about the cup's axis (V's z): bMe eMv Rz eMv^-1."""
    eMv = np.asarray(eMv, dtype=float)
    return np.asarray(bMe, dtype=float) @ eMv @ transform(rot_z(quarter_turns * np.pi / 2)) @ np.linalg.inv(eMv)


@dataclass(frozen=True)
class GraspChoice:
    """The grasp chosen: ``quarter_turns`` j about the cup's axis from the taught one, the pick
    and place flange poses it gives, how far the flange turns through them (rad), and why
    the grasps that turn it less were left out."""

    quarter_turns: int
    bMe_pick: Matrix
    bMe_place: Matrix
    turn_rad: float
    refused_nearer: tuple[str, ...]


def grasp_choice(
    bMe_end: Matrix,
    eMe_pick: Matrix,
    bMe_place: Matrix,
    eMv: Matrix,
    symmetry: int,
    refusal: Callable[[Matrix, Matrix], str | None],
    bMe_next: Matrix | None = None,
) -> tuple[GraspChoice | None, tuple[str, ...]]:
    """The grasp of least flange turn from the servo's end bMe_end through the pick, the place
    and on to bMe_next that ``refusal`` lets through, and why the others were refused (all of
    them when the choice is None).

    refusal(bMe_pick_j, bMe_place_j): why the arm's moves through that pick and place do not
    pass the safety layer's checks (the configured kinematic model), None when they do.
    """

    def turn(bMa: Matrix, bMb: Matrix) -> float:
        return rotation_angle(bMa[:3, :3].T @ bMb[:3, :3])

    candidates = []
    for j in allowed_turns(symmetry):
        pick = turned_about_cup(np.asarray(bMe_end, float) @ eMe_pick, eMv, j)
        place = turned_about_cup(bMe_place, eMv, j)
        cost = turn(bMe_end, pick) + turn(pick, place) + (0.0 if bMe_next is None else turn(place, bMe_next))
        candidates.append(GraspChoice(j, pick, place, cost, ()))
    candidates.sort(key=lambda choice: (choice.turn_rad, choice.quarter_turns))
    refused: list[str] = []
    for choice in candidates:
        why = refusal(choice.bMe_pick, choice.bMe_place)
        if why is None:
            return replace(choice, refused_nearer=tuple(refused)), tuple(refused)
        refused.append(f"the grasp turned {90 * choice.quarter_turns} deg: {why}")
    return None, tuple(refused)


@dataclass(frozen=True)
class ViewTurn:
    """A relabelling of the desired view: ``quarter_turns`` k, and the image rotation left
    from the corners seen now to its corners (rad, in (-pi, pi]; NaN when fewer than two
    corners are seen)."""

    quarter_turns: int
    image_turn_rad: float


def image_turn_rad(corners_px: Matrix, target_px: Matrix) -> float:
    """The rotation in the image that best carries the seen corners onto ``target_px``
    (same labels), from every pair of corners seen (translation and scale left out):
    the argument of sum (t_j - t_i) conj(c_j - c_i) over the pairs. NaN with fewer than two seen."""
    corners = np.asarray(corners_px, dtype=float)
    target = np.asarray(target_px, dtype=float)
    seen = np.flatnonzero(np.isfinite(corners).all(axis=1))
    if seen.size < 2:
        return float("nan")
    c = corners[seen, 0] + 1j * corners[seen, 1]
    t = target[seen, 0] + 1j * target[seen, 1]
    dc, dt = c[None, :] - c[:, None], t[None, :] - t[:, None]
    total = complex((dt * np.conj(dc)).sum())
    return float(np.angle(total)) if abs(total) > 0.0 else float("nan")


def view_turns(corners_px: Matrix, desired: DesiredImage, side_m: float, symmetry: int) -> list[ViewTurn]:
    """The relabellings the job's symmetry allows, the least image turn first (ties to the
    fewer quarter turns); the taught one alone when fewer than two corners are seen."""
    turns = [
        ViewTurn(k, image_turn_rad(corners_px, turned_desired(desired, side_m, k).corners_px)) for k in allowed_turns(symmetry)
    ]
    if any(np.isnan(turn.image_turn_rad) for turn in turns):
        return [ViewTurn(0, float("nan"))]
    return sorted(turns, key=lambda turn: (abs(turn.image_turn_rad), turn.quarter_turns))
