"""Forward and inverse kinematics of a serial arm with its tool mount, on Pinocchio.

Generic for any arm that ``robot_models.loader`` describes: nothing here knows the
UPJ. The tools hang on the flange E at fixed poses (ToolMount) and become Pinocchio
operational frames, so every query takes a frame name: "flange" (the arm's flange
frame, whatever its URDF calls it), "camera" (C), "laser" (L) or "vacuum_cup" (V).
Poses are in the base frame b, the Pinocchio universe; twists are (v, w).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from itertools import chain

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike

from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix, exp_twist
from vservo.robot_models.loader import ArmDescription


def _pose(M: ArrayLike, name: str) -> Matrix:
    M = np.array(M, dtype=float)
    if M.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 homogeneous matrix, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return M


@dataclass(frozen=True)
class ToolMount:
    """Poses of the end-effector tools in the flange frame E."""

    eMc: Matrix = field(default_factory=lambda: np.eye(4))  # camera C
    eMl: Matrix = field(default_factory=lambda: np.eye(4))  # laser pointer L
    eMv: Matrix = field(default_factory=lambda: np.eye(4))  # vacuum cup V

    def __post_init__(self) -> None:
        for name in ("eMc", "eMl", "eMv"):
            object.__setattr__(self, name, _pose(getattr(self, name), name))


class KinematicsError(VservoError):
    """A kinematic query that cannot be answered."""


class UnreachableTarget(KinematicsError):
    """No joint configuration within the limits puts the frame at the target pose.

    ``best_q``: the joints of the IK's closest attempt (None when the target is beyond the
    arm's reach and no attempt was made), which joints it left at their limits says."""

    def __init__(self, message: str, best_q: Matrix | None = None) -> None:
        super().__init__(message)
        self.best_q = best_q


@dataclass(frozen=True)
class IkSolution:
    """A converged IK: q (rad), the iterations summed over all seeds tried, final errors."""

    q: Matrix
    iterations: int
    translation_error_m: float
    rotation_error_rad: float


class ArmKinematics:
    """Kinematics of one serial arm of revolute joints carrying one tool mount.

    The description's model is copied before the tool frames are added, so several
    ArmKinematics (nominal, perturbed, other mounts) can share one ArmDescription.
    """

    TOOL_FRAMES = ("camera", "laser", "vacuum_cup")

    def __init__(self, description: ArmDescription, mount: ToolMount) -> None:
        model = description.model.copy()
        serial = all(model.parents[j] == j - 1 for j in range(1, model.njoints))
        # Bounded revolute joints (RX, RY, RZ, RevoluteUnaligned) have nq = nv = 1.
        revolute = model.nq == model.nv and all(
            model.joints[j].shortname().startswith("JointModelR") for j in range(1, model.njoints)
        )
        if not (serial and revolute):
            raise ValueError(f"arm {description.name!r} is not a serial chain of bounded revolute joints")
        flange_id = model.getFrameId(description.flange_frame)
        flange = model.frames[flange_id]
        for name, eMx in zip(self.TOOL_FRAMES, (mount.eMc, mount.eMl, mount.eMv)):
            if model.existFrame(name):
                raise ValueError(f"arm {description.name!r} already has a frame named {name!r}")
            placement = flange.placement * pin.SE3(eMx)
            model.addFrame(pin.Frame(name, flange.parentJoint, flange_id, placement, pin.FrameType.OP_FRAME))

        self.description = description
        self.mount = mount
        self.model = model
        self.data = model.createData()
        self.name = description.name
        self.dof = model.nq
        self.lower = model.lowerPositionLimit.copy()
        self.upper = model.upperPositionLimit.copy()
        self.joint_names = tuple(model.names[1:])
        self.frame_names = ("flange", *self.TOOL_FRAMES)
        self._shoulders: dict[int, tuple[Matrix, Matrix, float, float, float]] = {}

    def with_mount(self, mount: ToolMount) -> ArmKinematics:
        """The same arm carrying another tool mount."""
        return ArmKinematics(self.description, mount)

    def with_joint_placement_errors(
        self, rng: np.random.Generator, sigma_translation_m: float, sigma_rotation_rad: float
    ) -> ArmKinematics:
        """A copy of the arm whose every joint placement is off by a small random rigid motion.

        Each placement parentMjoint becomes parentMjoint @ exp_twist((v, w)), v and w drawn
        from zero-mean normals of the given sigmas per axis: the true arm of the simulator
        against which the nominal model is calibrated. This arm is left unchanged.
        """
        model = self.description.model.copy()
        for j in range(1, model.njoints):
            twist = np.concatenate((rng.normal(0.0, sigma_translation_m, 3), rng.normal(0.0, sigma_rotation_rad, 3)))
            model.jointPlacements[j] = model.jointPlacements[j] * pin.SE3(exp_twist(twist))
        return ArmKinematics(replace(self.description, model=model), self.mount)

    def within_limits(self, q: ArrayLike) -> bool:
        """Whether every joint of q lies within its limits (bounds included)."""
        q = self._joint_vector(q)
        return bool(np.all((self.lower <= q) & (q <= self.upper)))

    def unwound(self, q: ArrayLike) -> Matrix:
        """q with every joint whose range spans more than a turn (the UPJ's wrist roll,
        +-360 deg) moved by whole turns to the value nearest the middle of its range: the
        same flange pose, with the most travel left either way. A controller that follows
        its joints by continuity winds such a joint a turn further whenever half-turns in
        the same sense add up, run after run, until the servo meets its limit."""
        q = self._joint_vector(q)
        middle = (self.lower + self.upper) / 2
        turns = np.round((q - middle) / (2 * np.pi))
        unwound = q - 2 * np.pi * turns
        return np.where((self.upper - self.lower > 2 * np.pi) & (self.lower <= unwound) & (unwound <= self.upper), unwound, q)

    def fk(self, q: ArrayLike, frame: str = "flange") -> Matrix:
        """bM<frame>: pose of the frame in the base at joint configuration q (rad)."""
        frame_id = self._frame_id(frame)
        pin.forwardKinematics(self.model, self.data, self._joint_vector(q))
        return pin.updateFramePlacement(self.model, self.data, frame_id).homogeneous.copy()

    def jacobian(self, q: ArrayLike, frame: str = "flange") -> Matrix:
        """Body Jacobian (6 x dof): the frame's twist (v, w), expressed in the frame, is J @ qdot.

        For the flange this is eJe, the Jacobian of eq. 4-15 in the end-effector frame.
        """
        return pin.computeFrameJacobian(self.model, self.data, self._joint_vector(q), self._frame_id(frame), pin.LOCAL)

    def ik(
        self,
        bMf_target: ArrayLike,
        q_seed: ArrayLike,
        frame: str = "flange",
        *,
        tolerance_m: float = 1e-9,
        tolerance_rad: float = 1e-9,
        max_iterations: int = 50,
        restarts: int = 20,
        rng: np.random.Generator | None = None,
    ) -> IkSolution:
        """Joint configuration within the limits that puts ``frame`` at bMf_target.

        Levenberg-Marquardt on the pose residual r(q) = log(bMf(q)^-1 bMf_target), a
        twist in the frame's own axes, with the exact residual Jacobian
        -Jlog6(bMf_target^-1 bMf) fJf; each step is clamped into the joint limits. The
        seed is tried first, then ``restarts`` uniform random configurations within the
        limits (from ``rng``, seeded 0 by default so a failure is reproducible).
        Raises UnreachableTarget saying why when none converges.
        """
        bMt = pin.SE3(_pose(bMf_target, "bMf_target"))
        frame_id = self._frame_id(frame)
        q_seed = np.clip(self._joint_vector(q_seed), self.lower, self.upper)
        self._check_reach(bMt, frame_id)

        rng = np.random.default_rng(0) if rng is None else rng
        seeds = chain([q_seed], (rng.uniform(self.lower, self.upper) for _ in range(restarts)))
        best: IkSolution | None = None
        iterations = 0
        for seed in seeds:
            attempt = self._levenberg_marquardt(bMt, frame_id, seed, max_iterations, tolerance_m, tolerance_rad)
            iterations += attempt.iterations
            if attempt.translation_error_m <= tolerance_m and attempt.rotation_error_rad <= tolerance_rad:
                return replace(attempt, iterations=iterations)
            if best is None or self._cost(attempt) < self._cost(best):
                best = attempt

        assert best is not None  # the chain of seeds starts with q_seed: one attempt at least was made
        at_limits = [
            f"{name} at its {'lower' if abs(q - lo) < abs(q - hi) else 'upper'} limit"
            for name, q, lo, hi in zip(self.joint_names, best.q, self.lower, self.upper)
            if min(abs(q - lo), abs(q - hi)) < 1e-6
        ]
        raise UnreachableTarget(
            f"IK of {frame!r} did not converge from {restarts + 1} seeds: remaining error "
            f"{best.translation_error_m * 1e3:.1f} mm / {np.rad2deg(best.rotation_error_rad):.1f} deg"
            + (f", {', '.join(at_limits)}" if at_limits else ", no joint at a limit (singular or out of the workspace)"),
            best.q.copy(),
        )

    @staticmethod
    def _cost(solution: IkSolution) -> float:
        # Compares failed attempts only: 1 mm weighs as much as 1 mrad.
        return solution.translation_error_m + solution.rotation_error_rad

    def _levenberg_marquardt(
        self, bMt: pin.SE3, frame_id: int, q: Matrix, max_iterations: int, tolerance_m: float, tolerance_rad: float
    ) -> IkSolution:
        """One damped least-squares descent from q; returns where it stopped."""

        def residual(q: Matrix) -> tuple[Matrix, pin.SE3]:
            pin.forwardKinematics(self.model, self.data, q)
            bMf = pin.updateFramePlacement(self.model, self.data, frame_id)
            return pin.log6(bMf.actInv(bMt)).vector, bMf.copy()

        def errors() -> tuple[float, float]:
            # The rotation angle is |w| of the log: unlike arccos of the trace it keeps
            # full precision below 1e-8 rad.
            return float(np.linalg.norm(bMt.translation - bMf.translation)), float(np.linalg.norm(r[3:]))

        def converged() -> bool:
            translation, rotation = errors()
            return translation <= tolerance_m and rotation <= tolerance_rad

        r, bMf = residual(q)
        damping, steps = 1e-3, 0
        while steps < max_iterations and damping <= 1e6 and not converged():
            steps += 1
            fJf = pin.computeFrameJacobian(self.model, self.data, q, frame_id, pin.LOCAL)
            Jr = -pin.Jlog6(bMt.actInv(bMf)) @ fJf
            step = np.linalg.solve(Jr.T @ Jr + damping * np.eye(self.dof), -Jr.T @ r)
            q_next = np.clip(q + step, self.lower, self.upper)
            r_next, bMf_next = residual(q_next)
            if r_next @ r_next < r @ r:
                q, r, bMf = q_next, r_next, bMf_next
                damping = max(damping / 3.0, 1e-12)
            else:
                # A clamped or too long step: lean towards gradient descent.
                damping *= 10.0
        return IkSolution(q, steps, *errors())

    def _check_reach(self, bMt: pin.SE3, frame_id: int) -> None:
        """Necessary condition for reachability, from the triangle inequality.

        Past joint 2's origin (the shoulder) the chain is rigid links joined by
        rotations, so the frame's origin stays within the sum of their lengths of the
        shoulder, which itself circles the axis of joint 1 at a fixed radius and height.
        """
        if self.dof < 2:
            return
        axis_point, w, shoulder_height, shoulder_radius, reach = self._shoulder(frame_id)
        p = bMt.translation - axis_point
        target_height, target_radius = float(p @ w), float(np.linalg.norm(p - (p @ w) * w))
        distance = np.hypot(target_height - shoulder_height, target_radius - shoulder_radius)
        if distance > reach:
            raise UnreachableTarget(
                f"target is {distance:.3f} m from the shoulder ({self.joint_names[1]} origin), "
                f"beyond the reach {reach:.3f} m of the links after it"
            )

    def _shoulder(self, frame_id: int) -> tuple[Matrix, Matrix, float, float, float]:
        """A point on joint 1's axis, its unit direction w, the shoulder's height along
        and radius about that axis, and the reach from the shoulder to ``frame_id``: fixed
        by the model, so computed once per frame (every IK checks them)."""
        if frame_id not in self._shoulders:
            frame = self.model.frames[frame_id]
            reach = np.linalg.norm(frame.placement.translation) + sum(
                np.linalg.norm(self.model.jointPlacements[j].translation) for j in range(3, frame.parentJoint + 1)
            )
            q0 = pin.neutral(self.model)
            pin.forwardKinematics(self.model, self.data, q0)
            pin.computeJointJacobians(self.model, self.data, q0)
            # Joint 1's twist at unit speed, (v, w) at the base origin: its axis passes
            # through the point w x v (w a unit vector).
            v, w = np.split(pin.getJointJacobian(self.model, self.data, 1, pin.WORLD)[:, 0], 2)
            axis_point = np.cross(w, v)
            shoulder = self.data.oMi[2].translation - axis_point
            radius = float(np.linalg.norm(shoulder - (shoulder @ w) * w))
            self._shoulders[frame_id] = (axis_point, w.copy(), float(shoulder @ w), radius, float(reach))
        return self._shoulders[frame_id]

    def _frame_id(self, frame: str) -> int:
        if frame not in self.frame_names:
            raise ValueError(f"unknown frame {frame!r} of arm {self.name!r}: choose one of {self.frame_names}")
        return self.model.getFrameId(self.description.flange_frame if frame == "flange" else frame)

    def _joint_vector(self, q: ArrayLike) -> Matrix:
        q = np.asarray(q, dtype=float)
        if q.shape != (self.dof,):
            raise ValueError(f"{self.name} expects q of shape ({self.dof},), got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"{self.name} joint vector contains NaN or infinite values: {q}")
        return q
