"""The simulated cell: the plant that vservo's control laws and calibrations act on.

It holds the TRUE cell (camera intrinsics and distortion, eMc, cMl, the arm with its
kinematic errors, repeatability and pixel noise, where the cube lies) and hands out only
what a real cell would: joint and Cartesian readouts from the JRC, which
computes them with its NOMINAL model, and pixel measurements of the cube corners and the
laser spot. Nothing nominal is used to produce a measurement, and nothing true leaks
into one, except through the ``ground_truth_*`` accessors that exist for evaluation
(path lengths, final pose errors) and are never to be called by a control law.

Moves follow the JRC's logic: the target flange pose is turned into joints
by the JRC's nominal inverse kinematics, and the real arm ends where its true
kinematics put those joints, plus a settling (repeatability) error.

With ``Arm.NONE`` no arm carries the camera: the flange flies free (core/sim/free_camera.py
moves it), exactly where it is sent, with no joints, limits or settling; the camera, the
laser, the scene and the pixel noise stay what they are.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from vservo.core.cell.config import CellConfig, CellModel, ConfigError
from vservo.core.cell.kinematics import ArmKinematics
from vservo.core.cell.scene import Scene
from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix, exp_twist, interpolate, inverse, pose_error, rot_z, transform
from vservo.core.perception.features import ObjectRegion, polygon_moments
from vservo.core.perception.measurement import Measurement
from vservo.core.robot.commands import PositionCommand, RobotCommand, VelocityCommand
from vservo.core.sim import Arm
from vservo.robot_models.loader import load_arm

# The vacuum cup sits on a spring-loaded level compensator: it grips when its face is
# on the cube's top face, from VACUUM_GAP_M above it to VACUUM_STROKE_M pushed in, and
# its axis within VACUUM_TILT_RAD of the face's normal (the bellows take up the rest).
VACUUM_GAP_M = 0.001
VACUUM_STROKE_M = 0.010
VACUUM_TILT_RAD = np.deg2rad(10.0)
# Rotation rate a MOVL uses when the rotation, not the translation, sets the duration.
ROTATION_SPEED_RAD_S = 0.5
# The robot controller's own IK precision: far below any arm's repeatability, and loose
# enough to converge near singularities where 1e-9 takes too many iterations.
IK_TOLERANCE_M = 1e-7
IK_TOLERANCE_RAD = 1e-7
# A linear move's joints are followed along its line at most this turn apart (jrc_ik).
LINE_IK_STEP_RAD = np.deg2rad(20.0)


class CellStateError(VservoError, RuntimeError):
    """The plant refuses what it is asked in its present state (the cup holds the part,
    the board lies on the table); the message says what is in the way."""


@dataclass(frozen=True)
class CellTruth:
    """What the cell really is. Only the simulator holds one."""

    arm: ArmKinematics
    model: CellModel
    pixel_noise_px: float
    repeatability_m: float
    repeatability_rad: float

    @classmethod
    def from_config(cls, config: CellConfig, nominal_arm: ArmKinematics, rng: np.random.Generator) -> CellTruth:
        sim = config.plant()
        arm = nominal_arm.with_mount(sim.truth.mount)
        if sim.joint_placement_error_m > 0.0 or sim.joint_placement_error_rad > 0.0:
            arm = arm.with_joint_placement_errors(rng, sim.joint_placement_error_m, sim.joint_placement_error_rad)
        return cls(arm, sim.truth, sim.pixel_noise_px, sim.repeatability_m, sim.repeatability_rad)


def _clip(polygon: list[Matrix], axis: int, limit: float, keep_below: bool) -> list[Matrix]:
    """One Sutherland-Hodgman pass: the part of a polygon on one side of a border line."""

    def inside(p: Matrix) -> bool:
        return p[axis] <= limit if keep_below else p[axis] >= limit

    clipped = []
    for previous, current in zip(polygon[-1:] + polygon[:-1], polygon):
        if inside(current) != inside(previous):
            s = (limit - previous[axis]) / (current[axis] - previous[axis])
            clipped.append(previous + s * (current - previous))
        if inside(current):
            clipped.append(current)
    return clipped


def visible_region(polygon_px: Matrix, image_size: tuple[int, int]) -> ObjectRegion:
    """The part of a projected face inside the image, and its moments (eqs. 4-33 .. 4-35).

    A face with a vertex behind the camera (NaN projection) is not seen as a region.
    """
    if np.isnan(polygon_px).any():
        return ObjectRegion(0.0, np.full(2, np.nan))
    width, height = image_size
    polygon = list(np.asarray(polygon_px, dtype=float))
    # The sensor's edges: pixel centres are integers (OpenCV), so they lie at -0.5 and size - 0.5.
    borders = ((0, -0.5, False), (0, width - 0.5, True), (1, -0.5, False), (1, height - 0.5, True))
    for axis, limit, keep_below in borders:
        polygon = _clip(polygon, axis, limit, keep_below)
        if len(polygon) < 3:
            return ObjectRegion(0.0, np.full(2, np.nan))
    return ObjectRegion(*polygon_moments(np.array(polygon)))


@dataclass(frozen=True)
class PlantState:
    """The plant's state between two moves."""

    time_s: float
    q: Matrix
    eMe_settle: Matrix  # repeatability: where the true flange sits relative to fk_true(q)
    scene: Scene  # where the table, the cube and the metal part really are
    vMo_held: Matrix | None = None  # the cube on the vacuum cup: its pose in the true cup frame V
    bMe_free: Matrix | None = None  # with no arm: the flange's pose (q then stays at home, unused)


@dataclass(frozen=True)
class Placement:
    """Where a released cube came to rest against the metal part's pocket (evaluation only).

    offset_m is the cube's bottom-face centre minus the pocket floor's centre in the
    pocket frame P (x, y); yaw_rad its turn about P's z axis; inside means its whole
    footprint lies within the pocket, so it sits on the pocket floor.
    """

    inside: bool
    offset_m: Matrix
    yaw_rad: float

    @property
    def error_m(self) -> float:
        return float(np.hypot(*self.offset_m))


@dataclass(frozen=True)
class MoveReport:
    """What one executed move did, as the JRC knows it."""

    duration_s: float
    q: Matrix
    bMe: Matrix


class SimulatedCell:
    """The plant. ``execute`` one command at a time, ``measure`` in between.

    The nominal arm is the JRC's own model (it computes joint angles
    itself); the truth is built from the configuration's [simulation] section with the
    seeded generator, so a cell is reproducible from (config, seed).
    """

    def __init__(self, config: CellConfig, seed: int | None = None, arm: Arm = Arm.UPJ) -> None:
        simulation = config.plant()
        self.rng = np.random.default_rng(simulation.seed if seed is None else seed)
        self.jrc_arm = ArmKinematics(load_arm(config.arm), config.nominal.mount)
        self.truth = CellTruth.from_config(config, self.jrc_arm, self.rng)
        self.arm = Arm(arm)
        bMe_free = self.jrc_arm.fk(config.home_q) if self.arm is Arm.NONE else None
        self.state = PlantState(0.0, config.home_q.copy(), np.eye(4), simulation.scene, bMe_free=bMe_free)
        self.source = config.source
        self.board = simulation.board  # the TRUE board, where it lies when laid

    # -- the table -------------------------------------------------------------------

    def lay_board(self, laid: bool) -> None:
        """Lay the checkerboard at its true pose, clearing the table of the cube and the
        metal part to make room (as an integrator does), or take it away and put them back
        where they were. Refused while the cup holds the part."""
        if self.board is None:
            raise ConfigError(f"{self.source}: no [board] table: this cell has no checkerboard to lay")
        if self.holding_part:
            raise CellStateError("the cup holds the part: release it before the table is cleared for the board")
        self.state = replace(self.state, scene=self.state.scene.with_board(self.board if laid else None))

    @property
    def board_laid(self) -> bool:
        return self.state.scene.board is not None

    # -- sensors ---------------------------------------------------------------------

    def measure(self, look: bool = True) -> Measurement:
        """Read the JRC and take one (noisy) look through the true camera.

        ``look=False`` reads the robot only (a loop whose features come from camera
        images has no use for the projected ones): the camera fields are then unseen.
        """
        if not look:
            unseen = np.full(2, np.nan)
            return Measurement(
                self.state.time_s,
                self.state.q.copy(),
                self.flange_readout(),
                np.full((4, 2), np.nan),
                unseen,
                ObjectRegion(0.0, unseen),
                np.full(4, np.nan),
                unseen,
            )
        bMc = self.ground_truth_bMe() @ self.truth.model.eMc
        cMb = inverse(bMc)
        camera = self.truth.model.camera
        eye_b = bMc[:3, 3]

        scene = self.state.scene
        corners_b = scene.cube.corners_b
        corners_c = corners_b @ cMb[:3, :3].T + cMb[:3, 3]
        if scene.parts_on_table:
            projected = camera.project(corners_c)
            corners_px = self._observe(projected)
            hidden = [not scene.visible_from(eye_b, corner_b) for corner_b in corners_b]
            corners_px[hidden] = np.nan
            region = visible_region(projected, camera.image_size)
            reference_b = scene.cube.reference_b
            reference_px = self._observe(camera.project(cMb[:3, :3] @ reference_b + cMb[:3, 3]))[0]
            if not scene.visible_from(eye_b, reference_b):
                reference_px[:] = np.nan
        else:  # the board is laid: no cube on the table to see
            corners_px, reference_px = np.full((4, 2), np.nan), np.full(2, np.nan)
            corners_c[:, 2] = np.nan
            region = ObjectRegion(0.0, np.full(2, np.nan))

        spot_px = np.full(2, np.nan)
        spot_b = self._visible_spot_b(bMc)
        if spot_b is not None:
            spot_px = self._observe(camera.project((cMb[:3, :3] @ spot_b + cMb[:3, 3])[None, :]))[0]

        return Measurement(
            self.state.time_s,
            self.state.q.copy(),
            self.flange_readout(),
            corners_px,
            spot_px,
            region,
            corners_c[:, 2].copy(),
            reference_px,
        )

    def flange_readout(self) -> Matrix:
        """The flange pose the robot reports: the JRC's nominal model of its joints; a free
        camera's own pose (no arm, so no model to be wrong)."""
        if self.state.bMe_free is not None:
            return self.state.bMe_free.copy()
        return self.jrc_arm.fk(self.state.q)

    def _visible_spot_b(self, bMc: Matrix) -> Matrix | None:
        """Where the true beam lands, in B, if the true camera sees that point."""
        hit = self.state.scene.raycast(self.truth.model.laser.beam(bMc))
        if hit is None or not self.state.scene.visible_from(bMc[:3, 3], hit.point_b):
            return None
        return hit.point_b

    def ground_truth_view(self) -> tuple[Matrix, Matrix | None]:
        """(bMc, laser spot in B or None): what a synthetic camera renders, the true view."""
        bMc = self.ground_truth_bMe() @ self.truth.model.eMc
        return bMc, self._visible_spot_b(bMc)

    def _observe(self, uv: Matrix) -> Matrix:
        """Pixel noise, then the image bounds: what falls outside is not measured."""
        uv = uv + self.rng.normal(0.0, self.truth.pixel_noise_px, uv.shape) if self.truth.pixel_noise_px else uv
        return np.where(self.truth.model.camera.in_view(uv)[:, None], uv, np.nan)

    # -- actuation -------------------------------------------------------------------

    def execute(self, command: RobotCommand) -> MoveReport:
        """Carry out one command (see vservo.core.servo.step_policy); raises UnreachableTarget unmoved."""
        bMe = self.flange_readout()
        if isinstance(command, VelocityCommand):
            return self.move(command.target(bMe), command.dt_s)
        if isinstance(command, PositionCommand):
            return self.move(command.bMe_target, max(self.travel_time_s(command.bMe_target, command.speed_m_s), command.period_s))
        raise TypeError(f"not a robot command: {command!r}")

    def travel_time_s(self, bMe_target: Matrix, speed_m_s: float) -> float:
        """How long a linear move from here to bMe_target takes at speed_m_s (or at the
        controller's rotation rate, when the rotation takes longer)."""
        translation, rotation = pose_error(self.flange_readout(), bMe_target)
        return max(translation / speed_m_s, rotation / ROTATION_SPEED_RAD_S)

    def jrc_ik(self, bMe_target: Matrix) -> Matrix:
        """The joints the JRC ends a linear move to a flange target at, with its nominal
        model: followed by continuity along the straight line from where it puts the
        flange, as a MOVL turns the wrist the short way round. Solved at the target alone,
        a half turn of the wrist could end a turn of joint 6 away from where the line
        leads. Raises UnreachableTarget."""
        arm, q = self.jrc_arm, self.state.q
        bMe_now = arm.fk(q)
        _, rotation = pose_error(bMe_now, bMe_target)
        steps = max(1, int(np.ceil(rotation / LINE_IK_STEP_RAD)))
        for k in range(1, steps + 1):
            bMe = interpolate(bMe_now, bMe_target, k / steps)
            q = arm.ik(bMe, q, tolerance_m=IK_TOLERANCE_M, tolerance_rad=IK_TOLERANCE_RAD).q
        return q

    def move(self, bMe_target: Matrix, duration_s: float) -> MoveReport:
        """The arm moves to the JRC's joints for bMe_target in duration_s and settles."""
        self._require_arm()
        return self.move_joints(self.jrc_ik(bMe_target), duration_s)

    def fly(self, bMe_target: Matrix, duration_s: float) -> MoveReport:
        """The free camera's flange reaches bMe_target exactly after duration_s."""
        if self.state.bMe_free is None:
            raise CellStateError(f"an arm carries this cell's camera ({self.arm}): it moves by its joints, not free")
        bMe = np.array(bMe_target, dtype=float)
        self.state = replace(self.state, time_s=self.state.time_s + duration_s, bMe_free=bMe)
        self._carry_held_part()
        return MoveReport(duration_s, self.state.q.copy(), bMe.copy())

    def move_joints(self, q: Matrix, duration_s: float, settle: bool = True) -> MoveReport:
        """The arm reaches joints q after duration_s; ``settle=False`` passes through q
        (a point along a move in progress), without a repeatability error."""
        self._require_arm()
        q = np.array(q, dtype=float)
        eMe_settle = self._settle() if settle else np.eye(4)
        self.state = replace(self.state, time_s=self.state.time_s + duration_s, q=q, eMe_settle=eMe_settle)
        self._carry_held_part()
        return MoveReport(duration_s, q.copy(), self.jrc_arm.fk(q))

    def _require_arm(self) -> None:
        if self.state.bMe_free is not None:
            raise CellStateError("no arm carries this cell's camera (arm none): it has no joints to move")

    def pass_time(self, seconds: float) -> None:
        """Time passes with the arm standing still (a host's sampling period, a pause)."""
        self.state = replace(self.state, time_s=self.state.time_s + max(seconds, 0.0))

    # -- the vacuum cup --------------------------------------------------------------

    def _true_bMv(self) -> Matrix:
        return self.ground_truth_bMe() @ self.truth.model.eMv

    def _carry_held_part(self) -> None:
        if self.state.vMo_held is not None:
            self.place_cube(self._true_bMv() @ self.state.vMo_held)

    @property
    def holding_part(self) -> bool:
        """The vacuum sensor: whether the cup holds the part."""
        return self.state.vMo_held is not None

    def vacuum(self, on: bool) -> bool:
        """Switch the vacuum; returns whether the cup holds the part afterwards.

        Suction grips the cube only if the TRUE cup sits on its top face (the cup's centre
        over the face, between VACUUM_GAP_M above it and VACUUM_STROKE_M into the level
        compensator, its axis against the face's normal within VACUUM_TILT_RAD), and not
        while the board is laid (the cube is off the table); the part then hangs on the
        cup's face. Releasing drops the part: it comes to rest level, on the pocket floor
        if its footprint fits the pocket, else on whatever lies below it.
        """
        if on:
            if self.state.vMo_held is None and self.state.scene.parts_on_table:
                bMv = self._true_bMv()
                cube = self.state.scene.cube
                oMv = inverse(cube.bMo) @ bMv
                x, y, z = oMv[:3, 3]
                over_face = 0.0 <= x <= cube.side_m and 0.0 <= y <= cube.side_m
                facing = np.arccos(np.clip(-oMv[2, 2], -1.0, 1.0)) <= VACUUM_TILT_RAD  # cup z into the face
                if over_face and -VACUUM_STROKE_M <= z <= VACUUM_GAP_M and facing:
                    oMv[2, 3] = 0.0  # the compensator extends again once the part is lifted
                    self.state = replace(self.state, vMo_held=inverse(oMv))
            return self.holding_part
        if self.state.vMo_held is not None:
            self.state = replace(self.state, vMo_held=None)
            self.place_cube(self._resting_pose(self.state.scene.cube.bMo))
        return False

    def _resting_pose(self, bMo: Matrix) -> Matrix:
        """Where a released cube settles: level, yaw kept, on the highest surface below it."""
        cube = self.state.scene.cube
        level = transform(rot_z(np.arctan2(bMo[1, 0], bMo[0, 0])), bMo[:3, 3])
        placement = self._placement_of(level)
        part = self.state.scene.metal_part
        if placement.inside:
            floor_z = part.bMp[2, 3]
        elif np.all(np.abs(placement.offset_m) <= part.pocket_side_m / 2 + part.wall_m + cube.side_m):
            floor_z = part.bMp[2, 3] + part.pocket_depth_m  # on the walls' top
        else:
            floor_z = self.state.scene.table_height_m
        level[2, 3] = floor_z + cube.side_m
        return level

    def _placement_of(self, bMo: Matrix) -> Placement:
        """The cube's bottom face, were the cube at bMo, against the pocket."""
        cube, part = self.state.scene.cube, self.state.scene.metal_part
        pMo = inverse(part.bMp) @ bMo
        footprint_p = (cube.corners_o - [0.0, 0.0, cube.side_m]) @ pMo[:3, :3].T + pMo[:3, 3]
        inside = bool(np.all(np.abs(footprint_p[:, :2]) <= part.pocket_side_m / 2))
        yaw_p = np.arctan2(pMo[1, 0], pMo[0, 0])
        return Placement(inside, footprint_p[:, :2].mean(axis=0), float(np.angle(np.exp(1j * yaw_p))))

    def _settle(self) -> Matrix:
        """A fresh repeatability error: a small random rigid motion of the flange."""
        if not (self.truth.repeatability_m or self.truth.repeatability_rad):
            return np.eye(4)
        twist = np.concatenate(
            [
                self.rng.normal(0.0, self.truth.repeatability_m, 3),
                self.rng.normal(0.0, self.truth.repeatability_rad, 3),
            ]
        )
        return exp_twist(twist)

    def place_cube(self, bMo: Matrix) -> None:
        """Put the part somewhere else on the table (a new task, or after a pick)."""
        cube = self.state.scene.cube.moved_to(np.asarray(bMo, dtype=float))
        self.state = replace(self.state, scene=self.state.scene.with_cube(cube))

    def set_joints(self, q: Matrix) -> MoveReport:
        """Move straight to a joint configuration (set-up of a scenario, not a servo step)."""
        self._require_arm()
        q = np.asarray(q, dtype=float)
        if not self.jrc_arm.within_limits(q):
            raise ValueError(f"joints {np.rad2deg(q).round(2).tolist()} deg are outside the joint limits")
        self.state = replace(self.state, q=q.copy(), eMe_settle=self._settle())
        self._carry_held_part()
        return MoveReport(0.0, q.copy(), self.jrc_arm.fk(q))

    def place_camera(self, cMo: Matrix) -> None:
        """Scenario set-up: put the TRUE camera at cMo from the true cube, as an operator
        jogging the arm until the view is right would (teaching, a task's initial pose).

        Solved with the true arm, so it is exact even when the nominal model is wrong;
        a control law never calls it.
        """
        bMc = self.state.scene.cube.bMo @ inverse(np.asarray(cMo, dtype=float))
        bMe = bMc @ inverse(self.truth.model.eMc)
        if self.state.bMe_free is not None:
            self.state = replace(self.state, bMe_free=bMe)
            return
        q = self.truth.arm.ik(bMe, self.state.q).q
        self.state = replace(self.state, q=q, eMe_settle=np.eye(4))

    # -- evaluation only: what no control law may read -------------------------------

    def ground_truth_bMe(self) -> Matrix:
        """The true flange pose."""
        if self.state.bMe_free is not None:
            return self.state.bMe_free.copy()
        return self.truth.arm.fk(self.state.q) @ self.state.eMe_settle

    def ground_truth_placement(self) -> Placement:
        """Where the cube lies relative to the metal part's pocket."""
        return self._placement_of(self.state.scene.cube.bMo)

    def ground_truth_cMo(self) -> Matrix:
        """The true pose of the cube frame O in the true camera frame."""
        bMc = self.ground_truth_bMe() @ self.truth.model.eMc
        return inverse(bMc) @ self.state.scene.cube.bMo
