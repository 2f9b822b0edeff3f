"""The servo tasks of the thesis's simulation study (Tables 5-1, 5-2) and the robustness
test (Table 5-3), as docs/thesis-notes.md section 6 reads them.

A task is an initial and a desired pose of the cube frame O in the camera frame C
(cMo, Table 5-1's convention: X, Y, Z in m, R = Rz(phi) Ry(theta) Rx(psi)). The cube's
frame sits at a top-face corner with the face along +x, +y; the desired poses put the
face 0.162 m in front of the camera, centred near the laser spot, which gives the
desired features of Table 5-2 (with the fourth point of set 1 read as (277, 190)).

- Task 1: the desired pose turned by pi about the optical axis (Chaumette's 1998 case,
  as the thesis describes it; read literally, Table 5-1's row turns about the corner).
- Task 2: a small discrepancy, about 0.3 m and 1.1 rad.
- Task 3: a large one, about 0.3 m and 2.9 rad.
- Task 4: as task 2 but 5 cm further left: the cube starts partly outside the image.

The UPJ reaches only a thin shell of tool-down poses, and a servo from 0.42 m away with
a 3 rad turn sweeps a large part of it. Each task therefore places the cube on the
table (distance from the base axis, yaw) where the arm can follow both ways a servo may
go, turning then translating or straight, within its joint limits and away from its
singularities; ``find_placement`` searched them for the shipped cell, whose table is
175 mm below the robot base. Margins (worst joint clearance in rad or smallest singular
value of the flange Jacobian) of tasks 1 and 2: 0.13, 0.085. Tasks 3 and 4 sweep more of
the workspace than the UPJ has, and their placements were checked by running the
servos: task 3 lies where the arm can follow both the laser method and 2.5D (0.36 m at
0 deg and 0.40 m at 345 deg are the only such places on the grid), task 4 where the
laser servo's path stays feasible (0.40 .. 0.44 m at 285 deg; every other method stops
at the first frame, which lacks a corner).

The robustness test (Table 5-3) is task 2 servoed by a control law whose camera, laser and
hand-eye models differ from the cell's. The table gives an "actual" and an "applied"
value of each; the thesis's own result fixes which is which. In the robustness run the
laser spot no longer travels parallel to the image's u axis (section 5.2.2, Fig. 5-5 a).
The spot's image path is that of the physical beam, whatever the control law believes: the
actual beam [30 0 0 0 -10 0] lies in the camera's x-z plane and keeps the spot on the row
v = v0, only the applied beam [30 10 10 0 -12 2] takes it off. So the applied values are
what the simulated cell is, and the actual ones (the ideal simulation's camera and laser)
what the control law keeps. Read the other way round the spot stays on its row and the run
diverges: stages 1 and 2 leave the camera looking at the part from about 30 deg off the
desired direction (task 2's initial viewing direction, which neither stage 1's turn in
place nor stage 2's approach changes), and stage 3's constant interaction matrix, built
with a principal point 64 / 48 px off, turns the camera further round the part.

The miscalibrated stage 1.C moves the flange to keep a camera offset the cell does not
have, so the robustness run's flange path is not task 2's: at task 2's placement joint 2
meets its limit in stage 2. The run therefore has its own placement (ROBUSTNESS_TASK),
where the arm follows it with every joint at least 3 deg from its limits.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any

import numpy as np

from vservo.core.cell.kinematics import ArmKinematics, UnreachableTarget
from vservo.core.geometry.spatial import (
    Matrix,
    Pose6,
    exp_twist,
    inverse,
    matrix_from_pose,
    pose_error,
    rot_z,
    theta_u,
    transform,
)

# Table 5-4: length of the end-effector path (m) in the thesis; None is a failure.
THESIS_PATH_LENGTH_M: dict[int, dict[str, float | None]] = {
    1: {"laser": 0.0, "2.5d": 0.01, "ibvs": None},
    2: {"laser": 0.348, "2.5d": 0.308, "ibvs": 0.404},
    3: {"laser": 0.364, "2.5d": 0.398, "ibvs": None},
    4: {"laser": 0.361, "2.5d": None, "ibvs": None},
}

# Table 5-2 with the corrected fourth point of set 1 (and third of set 2).
THESIS_DESIRED_FEATURES_PX = {
    1: np.array([[277, 290], [377, 290], [377, 190], [277, 190]], dtype=float),
    2: np.array([[377, 290], [377, 190], [277, 190], [277, 290]], dtype=float),
}
THESIS_DESIRED_LASER_PX = np.array([327.0, 240.0])


def distance_to_thesis_set(corners_px: Matrix, thesis_px: Matrix) -> float:
    """Largest distance (px) from a point of a Table 5-2 set to the nearest given corner.

    The sets are compared as sets: which corner is called the first depends on where the
    object frame sits on the face, which the thesis does not say.
    """
    distances = np.linalg.norm(thesis_px[:, None, :] - corners_px[None, :, :], axis=2)
    return float(distances.min(axis=1).max())


@dataclass(frozen=True)
class ServoTask:
    name: str
    initial_cMo: Matrix
    desired_cMo: Matrix
    placement: Placement  # where the cube lies on the table
    description: str

    @property
    def camera_motion(self) -> tuple[float, float]:
        """(translation m, rotation rad) of the camera from its initial to its desired pose."""
        return pose_error(inverse(self.initial_cMo), inverse(self.desired_cMo))


@dataclass(frozen=True)
class Placement:
    """Where a task puts the cube on the table: distance from the base axis (on the -x
    side, where the UPJ's tool-down poses lie) and yaw about the vertical."""

    distance_m: float
    yaw_deg: float

    def bMo(self, table_height_m: float, side_m: float) -> Matrix:
        return transform(rot_z(np.radians(self.yaw_deg)), (-self.distance_m, 0.0, table_height_m + side_m))


def _interpolate(aMb: Matrix, aMc: Matrix, s: float, rotate_first: bool) -> Matrix:
    """A pose between aMb (s = 0) and aMc (s = 1): along the SE(3) geodesic, or turning in
    place during the first half and translating during the second."""
    if rotate_first:
        turn, move = min(1.0, 2.0 * s), max(0.0, 2.0 * s - 1.0)
        R = aMb[:3, :3] @ exp_twist(np.concatenate([np.zeros(3), turn * theta_u(aMb[:3, :3].T @ aMc[:3, :3])]))[:3, :3]
        return transform(R, (1.0 - move) * aMb[:3, 3] + move * aMc[:3, 3])
    bMc = inverse(aMb) @ aMc
    return aMb @ exp_twist(s * np.concatenate([bMc[:3, 3], theta_u(bMc[:3, :3])]))


def placement_margin(
    arm: ArmKinematics, q_seed: Matrix, bMo: Matrix, initial_cMo: Matrix, desired_cMo: Matrix, eMc: Matrix, samples: int = 9
) -> float:
    """How comfortably the arm serves a task with the cube at bMo; 0 if it cannot.

    Both ways a servo may go from the initial to the desired camera pose are sampled
    (turn then translate, as the laser method does; straight, as PBVS and 2.5D do). The
    margin is the worst over the samples of the smaller of the joint-limit clearance
    (rad) and the smallest singular value of the flange Jacobian.
    """
    worst = np.inf
    bMc_initial, bMc_desired = bMo @ inverse(initial_cMo), bMo @ inverse(desired_cMo)
    for rotate_first in (True, False):
        q = q_seed
        for s in np.linspace(0.0, 1.0, samples):
            bMe = _interpolate(bMc_initial, bMc_desired, s, rotate_first) @ inverse(eMc)
            try:
                q = arm.ik(bMe, q, restarts=4).q
            except UnreachableTarget:
                return 0.0
            clearance = float(np.min(np.minimum(q - arm.lower, arm.upper - q)))
            dexterity = float(np.linalg.svd(arm.jacobian(q), compute_uv=False)[-1])
            worst = min(worst, clearance, dexterity)
    return worst


def find_placement(
    arm: ArmKinematics,
    q_seed: Matrix,
    table_height_m: float,
    side_m: float,
    initial_cMo: Matrix,
    desired_cMo: Matrix,
    eMc: Matrix,
) -> tuple[Placement, float]:
    """The placement with the best margin on a grid of distances (2 cm) and yaws (15 deg).

    How the placements of TASKS were found (for the shipped cell's table); a scene given
    on the command line is placed by it too.
    """
    scored = []
    for distance in np.arange(0.34, 0.5601, 0.02):
        for yaw in range(0, 360, 15):
            placement = Placement(round(float(distance), 2), float(yaw))
            bMo = placement.bMo(table_height_m, side_m)
            scored.append((placement_margin(arm, q_seed, bMo, initial_cMo, desired_cMo, eMc, samples=7), placement))
    margin, placement = max(scored, key=lambda item: item[0])
    if margin <= 0.0:
        raise UnreachableTarget("no placement of the cube on the table lets the arm serve this scene")
    return placement, margin


_DESIRED_SET_2 = matrix_from_pose(Pose6(0.011, -0.01, 0.162, np.pi, 0.0, -np.pi))
_DESIRED_SET_1 = matrix_from_pose(Pose6(0.011, 0.01, 0.162, -np.pi / 2, 0.0, -np.pi))

TASKS: dict[int, ServoTask] = {
    1: ServoTask(
        "task 1",
        transform(rot_z(np.pi)) @ _DESIRED_SET_2,
        _DESIRED_SET_2,
        Placement(0.38, 345.0),
        "pure rotation of pi about the optical axis",
    ),
    2: ServoTask(
        "task 2",
        matrix_from_pose(Pose6(-0.12, -0.05, 0.42, -0.524, 0.349, -2.793)),
        _DESIRED_SET_1,
        Placement(0.40, 255.0),
        "small pose discrepancy",
    ),
    3: ServoTask(
        "task 3",
        matrix_from_pose(Pose6(-0.07, -0.08, 0.44, 0.175, -0.175, -2.444)),
        _DESIRED_SET_2,
        Placement(0.40, 345.0),
        "large pose discrepancy",
    ),
    4: ServoTask(
        "task 4",
        matrix_from_pose(Pose6(-0.17, -0.05, 0.42, -0.524, 0.349, -2.793)),
        _DESIRED_SET_1,
        Placement(0.42, 285.0),
        "cube partly outside the initial image",
    ),
}

# Table 5-3 (mm, deg, px): its two columns. The reproduction reads them as the module's
# docstring says (the control law keeps the actual values, the simulated cell has the
# applied ones); the other reading swaps them (the controller applies the erroneous values).
# Cell-file tables: table -> key -> value, as a TOML reader gives them.
TABLE_5_3_ACTUAL: dict[str, dict[str, Any]] = {
    "camera": {"focal_length_mm": 6.0, "principal_point_px": [320.0, 240.0]},
    "laser": {"cMl": [30.0, 0.0, 0.0, 0.0, -10.0, 0.0]},
    "hand_eye": {"eMc": [-20.0, 20.0, 20.0, 5.0, 5.0, 5.0]},
}
TABLE_5_3_APPLIED: dict[str, dict[str, Any]] = {
    "camera": {"focal_length_mm": 7.2, "principal_point_px": [384.0, 288.0]},
    "laser": {"cMl": [30.0, 10.0, 10.0, 0.0, -12.0, 2.0]},
    "hand_eye": {"eMc": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]},
}
ROBUSTNESS_TASK = replace(TASKS[2], placement=Placement(0.40, 270.0))


class Table53Reading(StrEnum):
    """Which column of Table 5-3 the control law keeps (docs/thesis-notes.md section 6)."""

    REPRODUCTION = "reproduction"  # the law keeps the actual values, the cell has the applied ones
    OTHER = "other"  # the law applies the applied (erroneous) values, the cell has the actual ones


def servo_task(number: int, robust: bool = False) -> ServoTask:
    """Task ``number`` of Table 5-1; with ``robust``, task 2 as the robustness test places it."""
    return ROBUSTNESS_TASK if robust and number == 2 else TASKS[number]


def robustness_cell(data: dict, reading: Table53Reading = Table53Reading.REPRODUCTION) -> dict:
    """A copy of parsed cell-file data turned into the robustness test of Table 5-3, read
    as ``reading`` says: the nominal tables the law's column, [simulation.truth.*] the other."""
    model, truth = (
        (TABLE_5_3_ACTUAL, TABLE_5_3_APPLIED) if reading is Table53Reading.REPRODUCTION else (TABLE_5_3_APPLIED, TABLE_5_3_ACTUAL)
    )
    cell = {key: dict(value) if isinstance(value, dict) else value for key, value in data.items()}
    for table, values in model.items():
        cell[table] = {**cell.get(table, {}), **values}
    simulation = dict(cell.get("simulation", {}))
    simulation["truth"] = {table: dict(values) for table, values in truth.items()}
    cell["simulation"] = simulation
    return cell
