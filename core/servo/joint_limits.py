"""The arm's joint limits inside the control law: a step that would take a joint past its
limit is bent, not refused.

A control law commands a camera twist as if the camera flew free; the arm carries it out
through eq. 4-17, q' = J_r^-1 eVe. Near a joint limit that joint step would push the
joint past its limit and the controller refuses the target ("unreachable"), although the
goal itself may lie well inside the arm's reach. Here the step is solved instead as a
least squares with bounds on the controller's kinematic MODEL of the arm:

    dq* = argmin || W (cJc(q) dq - xi_c) ||^2   s.t.   q_min + m <= q + dq <= q_max - m

xi_c is the camera's step the policy commanded (in the camera frame), cJc the camera's
body Jacobian, W = diag(1, 1, 1, rho, rho, rho) weighs a radian of the camera's turn as
rho metres of its travel, and m is the margin kept from each limit. A joint already
inside its margin may only move out. The joints' speed is no constraint here: the
controller times its own moves, and the thesis's tasks turn joint 6 at up to 3.1 rad/s
in the study's velocity steps, past the URDF's 3.0 rad/s (a bound on it would change
Table 5-4). The least squares keeps the camera's motion as close to the commanded one as
the free joints allow (the path bends around the limit), the closed loop corrects the
rest at the next look. This is the inequality-constrained form of the kinematic control
of Kanoun, Lamiraux and Wieber (IEEE T-RO 2011), with the bounded-variable least squares
of Stark and Parker (Comput. Stat. 1995) as the solver. ViSP's joint-limit avoidance
(Marey and Chaumette, ICRA 2010) also acts only within a band near each limit, but
through the task's null space, which a 6-joint arm servoing a 6-dof task does not have.

It acts ONLY when a joint is within a band of its limit and the model's inverse
kinematics of the commanded target would take it past the margin; then every joint is
bounded. Otherwise the policy's command is returned as it came, bit for bit, so the
thesis's tasks, which come near the limits but never cross them, run exactly as before
(docs/thesis-notes.md, "The arm's joint limits in the law"). A bent step lands the
flange on the model's forward kinematics of q + dq*, so the controller's own inverse
kinematics finds joints inside the limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from vservo.core.cell.kinematics import ArmKinematics, UnreachableTarget
from vservo.core.geometry.spatial import Matrix, inverse, twist_transform
from vservo.core.robot.commands import PositionCommand, RobotCommand, StreamedTwist, VelocityCommand

# The controller's IK precision (as the simulated JRC's): far below any arm's repeatability.
IK_TOLERANCE_M = 1e-7
IK_TOLERANCE_RAD = 1e-7


@dataclass(frozen=True)
class JointLimitSettings:
    """How the joint limits bend the servo's steps.

    band_rad: how near its limit a joint must be for the bending to act: a step that leaps
      past a limit from further away is far beyond what its linearisation can be trusted
      for, and is left to the controller to refuse.
    margin_rad: how far from its limit a bent step stops a joint. The bent target is the
      model's exact forward kinematics, so the margin need only keep the controller's
      inverse kinematics off the limit itself; the thesis's task 3 passes 1.6 mrad from
      joint 3's limit on its own, so the margin must stay below that.
    rotation_weight_m: rho, how many metres of camera travel one radian of its turn weighs
      when the bent step cannot keep both (about the camera's distance to the part).
    """

    band_rad: float = float(np.deg2rad(10.0))
    margin_rad: float = 1e-3
    rotation_weight_m: float = 0.1

    def __post_init__(self) -> None:
        if not (np.isfinite(self.margin_rad) and 0.0 <= self.margin_rad < self.band_rad):
            raise ValueError(f"margin_rad must be a finite angle in [0, band_rad = {self.band_rad}), got {self.margin_rad}")
        if not (np.isfinite(self.band_rad) and self.band_rad > 0.0):
            raise ValueError(f"band_rad must be a finite angle > 0, got {self.band_rad}")
        if not (np.isfinite(self.rotation_weight_m) and self.rotation_weight_m > 0.0):
            raise ValueError(f"rotation_weight_m must be a finite length > 0, got {self.rotation_weight_m}")


@dataclass(frozen=True)
class JointBound:
    """A joint the bent step stops at the edge of its margin."""

    joint: str
    side: str  # "lower" or "upper"

    def __str__(self) -> str:
        return f"{self.joint} at its {self.side} limit"


@dataclass(frozen=True)
class LimitedStep:
    """The command to send, and the joints it holds at the edge of their margins."""

    command: RobotCommand
    held: tuple[JointBound, ...] = ()


def bounded_least_squares(A: Matrix, b: Matrix, lower: Matrix, upper: Matrix, max_iterations: int = 50) -> Matrix:
    """argmin ||A x - b||^2 subject to lower <= x <= upper, with lower <= 0 <= upper.

    An active-set method (Stark and Parker's BVLS): from x = 0, solve the least squares on
    the free variables with the others at their bounds; a solution outside the box is
    followed only to the first bound it meets, which fixes that variable; inside the box, a
    bound variable whose gradient points into the box is freed again. For the 5-6 joints
    of an arm it ends in a few iterations.
    """
    A, b = np.asarray(A, dtype=float), np.asarray(b, dtype=float)
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    if np.any(lower > 0.0) or np.any(upper < 0.0):
        raise ValueError(f"the box must contain 0: lower {lower}, upper {upper}")
    n = A.shape[1]
    x = np.zeros(n)
    free = np.ones(n, dtype=bool)
    scale = max(float(np.abs(A).max(initial=0.0)) * float(np.abs(b).max(initial=0.0)), 1e-300)
    for _ in range(max_iterations):
        z = x.copy()
        if free.any():
            z[free] = np.linalg.lstsq(A[:, free], b - A[:, ~free] @ x[~free], rcond=None)[0]
        outside = free & ((z < lower) | (z > upper))
        if outside.any():
            d = z - x
            # How far along x -> z each leaving variable may go before meeting its bound.
            reach = np.where(z < lower, (lower - x) / np.where(d == 0.0, -1.0, d), (upper - x) / np.where(d == 0.0, 1.0, d))
            alpha = float(np.clip(reach[outside].min(), 0.0, 1.0))
            x = np.clip(x + alpha * d, lower, upper)
            stopped = outside & np.isclose(reach, alpha, rtol=1e-12, atol=1e-15)
            x[stopped] = np.where(z[stopped] < lower[stopped], lower[stopped], upper[stopped])  # exactly on it
            free &= ~stopped
            continue
        x = z
        gradient = A.T @ (A @ x - b)
        # A bound variable whose move back into the box would lower the residual.
        release = ~free & (((x >= upper) & (gradient > 1e-12 * scale)) | ((x <= lower) & (gradient < -1e-12 * scale)))
        if not release.any():
            return x
        free[np.flatnonzero(release)[np.argmax(np.abs(gradient[release]))]] = True
    return x


class JointLimitedSteps:
    """Bends the step policy's commands around the joint limits of the arm's model.

    ``arm`` is the controller's kinematic MODEL of the arm with the nominal tool mount
    (never a simulator's truth); its joints' position limits bound the steps.
    """

    def __init__(self, arm: ArmKinematics, settings: JointLimitSettings = JointLimitSettings()) -> None:
        self.arm = arm
        self.settings = settings
        self.cVe = twist_transform(inverse(arm.mount.eMc))
        self.lower = arm.lower + settings.margin_rad
        self.upper = arm.upper - settings.margin_rad
        rho = settings.rotation_weight_m
        self.W = np.diag([1.0, 1.0, 1.0, rho, rho, rho])

    def limit(self, command: RobotCommand, bMe: Matrix, q: Matrix) -> LimitedStep:
        """The command as it may be sent from joints q (whose flange pose is bMe)."""
        q = np.asarray(q, dtype=float)
        if q.shape != (self.arm.dof,) or not np.all(np.isfinite(q)):
            raise ValueError(f"the joint limits need the arm's {self.arm.dof} joint angles, got {q}")
        bMe = np.asarray(bMe, dtype=float)
        near = (q - self.arm.lower < self.settings.band_rad) | (self.arm.upper - q < self.settings.band_rad)
        if not near.any() or self._keeps_clear(command.target(bMe), q, near):
            return LimitedStep(command)

        xi_e = pin.log6(pin.SE3(inverse(bMe) @ command.target(bMe))).vector  # the flange's step, in E
        J = self.arm.jacobian(q, "camera")
        xi_c = self.cVe @ xi_e
        # A joint inside its margin (a start there) may stay or move out, never further in.
        lower, upper = np.minimum(self.lower - q, 0.0), np.maximum(self.upper - q, 0.0)
        dq = bounded_least_squares(self.W @ J, self.W @ xi_c, lower, upper)
        held = tuple(
            JointBound(name, "lower" if step <= low else "upper")
            for name, step, low, high in zip(self.arm.joint_names, dq, lower, upper)
            if step <= low or step >= high
        )
        # The model's motion from q to q + dq, from the flange pose the robot reported.
        bMe_target = bMe @ inverse(self.arm.fk(q)) @ self.arm.fk(q + dq)
        return LimitedStep(_retargeted(command, bMe, bMe_target), held)

    def _keeps_clear(self, bMe_target: Matrix, q: Matrix, near: Matrix) -> bool:
        """Whether the model's joints for bMe_target, followed from q, keep the joints near
        their limits outside the margins. The exact inverse kinematics, not eq. 4-17's
        linearisation: a long step of the thesis's task 3 stops 1.6 mrad short of joint
        3's limit, where the linear prediction of the same step overshoots it by 0.9 deg."""
        try:
            q_next = self.arm.ik(bMe_target, q, tolerance_m=IK_TOLERANCE_M, tolerance_rad=IK_TOLERANCE_RAD, restarts=0).q
        except UnreachableTarget:
            return False
        return not np.any(near & ((q_next < self.lower) | (q_next > self.upper)))


def _retargeted(command: RobotCommand, bMe: Matrix, bMe_target: Matrix) -> RobotCommand:
    """The command of the same kind and timing that lands the flange on bMe_target."""
    if isinstance(command, VelocityCommand):
        eVe = pin.log6(pin.SE3(inverse(bMe) @ bMe_target)).vector / command.dt_s
        return VelocityCommand(eVe, command.dt_s)
    if isinstance(command, StreamedTwist):
        return StreamedTwist(pin.log6(pin.SE3(inverse(bMe) @ bMe_target)).vector / command.hold_s, command.hold_s)
    return PositionCommand(bMe_target, command.speed_m_s, command.period_s)
