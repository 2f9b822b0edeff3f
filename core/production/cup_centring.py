"""The vacuum cup put on the middle of the part by the camera and the vacuum sensor alone.

On a cell never commissioned the cup pose the Teach tab computes for a part it sees
("Cup on it") rests on the nominal camera and hand-eye, and can be tens of millimetres
off (Table 5-5's errors put it 22 mm beside the part). This aid needs neither: only the
arm's own motions, the cup's mount eMv (a machined part, not a calibration) and the
image of the part's top-face centre (the crossing of its diagonals, the image of the
centre under any perspective).

From a pose where the camera sees the part (the desired view):

1. the image Jacobian of the top face's plane: two known flange translations along the
   base's x and y move the centre's pixel by J_c d; the part moving by d in a still
   camera moves it by J = -J_c (the plane seen from above maps affinely to the image);
2. the flange's axis against the part's centre: the flange turned by theta about its own
   vertical axis A (joint 6 alone, within reach wherever the arm is) shows the part's
   centre P where the camera left unturned would see P turned by -theta about A, that is
   moved by (Rz(-theta) - I)(P - A); so the pixel's move m gives P - A = (Rz(-theta) - I)^-1
   J^-1 m, from a turn each way (least squares); the cup's axis lies beside A as eMv puts it;
3. the face's height: a known descent dz of the camera scales the part's image by
   s2 / s1 = Z1 / (Z1 - dz), so its distance below the camera is Z1 = dz s2 / (s2 - s1)
   (the camera's own height comes from the model's hand-eye: a few millimetres off);
4. the cup carried over P and lowered onto the face by touch-down: suction on at steps
   of TOUCH_STEP_M from TOUCH_START_M above the estimate until the vacuum sensor feels
   the part (its grip window is 11 mm deep, the steps 4 mm), then left pressed
   PRESS_M into its level compensator with the suction off.

The flange keeps its orientation throughout; the result is the pick pose for Set pick
pose here. Steps 1 .. 3 are made twice from the view, and again until two in a row agree:
a look on a frame that lagged the arm (a busy host's, docs/vision.md) makes one differ, or
shows as motion the arm cannot have made (FramesLagged, made again after a pause); only
when no two agree is the operator told to try again.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix, rot_z, transform
from vservo.core.perception.features import pattern_scale
from vservo.core.production.placement_check import diagonals_crossing

JOG_M = 0.010  # each of step 1's translations
TURN_RAD = np.radians(15.0)  # step 2's turns, each way: the part stays in view with the cup 60 mm aside
DESCENT_M = 0.020  # step 3's descent
TOUCH_START_M = 0.012  # the touch-down starts this far above the estimated face (the hand-eye's height error and more)
TOUCH_STEP_M = 0.004
TOUCH_STEPS = 8
PRESS_M = 0.003  # how far the cup is left pressed into its level compensator (as the demo job's pick)
GRIP_GAP_M = 0.001  # a cup grips from this far above the face (the sensor's window's top)
# Bounds on what the camera saw, against frames that lag the arm (docs/vision.md): a view of
# the part is a few tenths of a metre above it, where a 10 mm jog moves it tens of pixels.
MIN_JOG_PX = 3.0
MAX_DEPTH_M = 1.0
# Steps 1 .. 3 are made from the view until two in a row agree this closely (a look on a
# frame that lagged the arm makes one differ), MEASUREMENTS times at most; one whose own
# bounds show lagging frames is made again after a pause of the host's time, in which a
# starved camera reader catches up.
MEASUREMENTS = 4
AGREE_OFFSET_M = 0.001
AGREE_DEPTH = 0.03
LOOK_AGAIN_AFTER_S = 1.0

log = logging.getLogger("vservo.cup_centring")


class CentringError(VservoError, RuntimeError):
    """The cup could not be put on the part; the message says why and what to do."""


class FramesLagged(CentringError):
    """What the camera saw cannot be the arm's motion: its frames lag the arm (a busy host)."""


@dataclass(frozen=True)
class CellMotions:
    """What centring drives: move the flange (a linear move), read its pose, the part's
    four corners in a fresh frame (NaN where unseen), and one grip test (suction on, the
    sensor read, suction off)."""

    move_to: Callable[[Matrix], None]
    read_pose: Callable[[], Matrix]
    corners_px: Callable[[], Matrix]
    grips: Callable[[], bool]


@dataclass(frozen=True)
class Centred:
    """The cup on the middle of the part: the flange pose, the part centre's distance from the
    cup's axis before the move (m) and the face's height as the touch-down found it (m)."""

    bMe: Matrix
    offset_m: float
    face_z_m: float


def _seen(cell: CellMotions) -> tuple[Matrix, float]:
    corners = np.asarray(cell.corners_px(), dtype=float)
    if not np.all(np.isfinite(corners)):
        raise CentringError("the camera must see the part's four corners to centre the cup on it: go to a view of the part first")
    try:
        return diagonals_crossing(corners), pattern_scale(corners)
    except np.linalg.LinAlgError:  # parallel diagonals: no face, whatever the detector said
        raise FramesLagged("the part's four corners seen do not make a face (a blurred frame?): try again") from None


def _shifted(bMe: Matrix, d_m: Matrix) -> Matrix:
    moved = np.array(bMe, dtype=float)
    moved[:3, 3] += d_m
    return moved


def _turned_about(bMe: Matrix, axis_b: Matrix, angle_rad: float) -> Matrix:
    """bMe turned by angle_rad about the vertical line through axis_b."""
    centre = transform(t=(axis_b[0], axis_b[1], 0.0))
    return centre @ transform(rot_z(angle_rad)) @ np.linalg.inv(centre) @ bMe


def part_axis_offset(cell: CellMotions) -> tuple[Matrix, float, float]:
    """Steps 1 .. 3 from the pose the camera sees the part from: P - A in the base's xy (m, A
    the flange's vertical axis),
    the face's distance below the camera (m), and the camera's pattern scale there (px)."""
    bMe0 = cell.read_pose()
    centre0, scale0 = _seen(cell)
    J_c = np.empty((2, 2))
    for axis in (0, 1):
        d = np.zeros(3)
        d[axis] = JOG_M
        cell.move_to(_shifted(bMe0, d))
        J_c[:, axis] = (_seen(cell)[0] - centre0) / JOG_M
    if np.min(np.linalg.norm(J_c, axis=0)) * JOG_M < MIN_JOG_PX:
        cell.move_to(bMe0)
        raise FramesLagged(
            f"the part moved less than {MIN_JOG_PX:g} px in the image as the arm moved {1000 * JOG_M:g} mm: the camera's "
            "frames lag the arm (a busy host) or it is not looking at the part; try again"
        )
    J = -J_c
    axis_b = bMe0[:3, 3]
    rows, moves = [], []
    for angle in (TURN_RAD, -TURN_RAD):
        cell.move_to(_turned_about(bMe0, axis_b, angle))
        rows.append(J @ (rot_z(-angle)[:2, :2] - np.eye(2)))
        moves.append(_seen(cell)[0] - centre0)
    offset, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(moves), rcond=None)
    cell.move_to(_shifted(bMe0, np.array([0.0, 0.0, -DESCENT_M])))
    scale1 = _seen(cell)[1]
    cell.move_to(bMe0)
    if not scale1 > scale0:
        raise FramesLagged(
            "the part did not grow in the image as the camera came down: the camera's frames lag the arm (a busy host), "
            "or it is not looking down at the part; try again"
        )
    depth_m = DESCENT_M * scale1 / (scale1 - scale0)
    if depth_m > MAX_DEPTH_M:
        raise FramesLagged(
            f"the part grew too little in the image as the camera came down {1000 * DESCENT_M:g} mm (it would lie "
            f"{depth_m:.2f} m below the camera): the camera's frames lag the arm (a busy host); try again"
        )
    return offset, depth_m, scale0


def _measured_from(cell: CellMotions, bMe0: Matrix) -> tuple[Matrix, float, float]:
    """part_axis_offset from the view bMe0 until two in a row agree (AGREE_OFFSET_M, AGREE_DEPTH);
    one that trips its own bounds (FramesLagged) is made again after LOOK_AGAIN_AFTER_S."""
    last: tuple[Matrix, float, float] | None = None
    why = ""
    for attempt in range(MEASUREMENTS):
        try:
            measured = part_axis_offset(cell)
        except FramesLagged as exc:
            why = str(exc)
            log.info("centring, measurement %d: %s; again in %g s", attempt + 1, exc, LOOK_AGAIN_AFTER_S)
            cell.move_to(bMe0)
            time.sleep(LOOK_AGAIN_AFTER_S)
            continue
        if last is not None:
            apart_m = float(np.linalg.norm(measured[0] - last[0]))
            if apart_m <= AGREE_OFFSET_M and abs(measured[1] / last[1] - 1.0) <= AGREE_DEPTH:
                return measured
            why = (
                f"two measurements from the same view disagree ({1000 * apart_m:.1f} mm apart across, the face "
                f"{1000 * last[1]:.0f} and {1000 * measured[1]:.0f} mm below the camera): the camera's frames lag the "
                "arm (a busy host); try again"
            )
            log.info("centring, measurement %d: %s", attempt + 1, why)
        last = measured
    raise FramesLagged(why)


def centre_cup(cell: CellMotions, eMv: Matrix, eMc: Matrix) -> Centred:
    """The cup on the middle of the part seen from here (module docstring). ``eMc`` (the
    model's) only places the camera's height for the touch-down's start: an error of it
    costs steps, not accuracy."""
    bMe0 = cell.read_pose()
    from_flange, depth_m, _ = _measured_from(cell, bMe0)
    offset = from_flange - ((bMe0 @ eMv)[:2, 3] - bMe0[:2, 3])
    camera_z = float((bMe0 @ eMc)[2, 3])
    face_z = camera_z - depth_m
    cup_z = float((bMe0 @ eMv)[2, 3])
    over = _shifted(bMe0, np.array([offset[0], offset[1], 0.0]))
    start = face_z + TOUCH_START_M - cup_z  # the flange's rise (negative: descent) to the touch-down's start
    # Over the part at the height of the view first: a straight move there from the view
    # pose crosses nothing, then down.
    cell.move_to(over)
    for rise in (0.0, TOUCH_START_M):  # a grip at the first step: the face was higher, start again higher
        for step in range(TOUCH_STEPS):
            bMe = _shifted(over, np.array([0.0, 0.0, start + rise - step * TOUCH_STEP_M]))
            cell.move_to(bMe)
            if not cell.grips():
                continue
            if step == 0:
                break
            # The first grip after a miss: the face lies within (cup - GRIP_GAP_M, cup + TOUCH_STEP_M - GRIP_GAP_M).
            face_z = float((bMe @ eMv)[2, 3]) + TOUCH_STEP_M / 2 - GRIP_GAP_M
            pick = _shifted(bMe, np.array([0.0, 0.0, face_z - PRESS_M - float((bMe @ eMv)[2, 3])]))
            cell.move_to(pick)
            return Centred(pick, float(np.hypot(*offset)), face_z)
    cell.move_to(over)
    raise CentringError(
        f"the vacuum sensor felt no part over {1000 * TOUCH_STEP_M * TOUCH_STEPS:.0f} mm of descent where the camera "
        "puts the part's centre: is the cup's mount [vacuum] eMv right, and the part on the table?"
    )
