"""The safety layer: every move of every backend passes its checks first.

It wraps any RobotBackend and is one itself, so the loop and the app drive a guarded
robot exactly as they would drive a bare one. Before a move reaches the JRC it
checks, in order: a latched stop (e-stop or watchdog), the requested speed, that the
target is a finite pose, that the flange and every tool frame (camera, laser, vacuum
cup) stay inside the workspace box, the size of the step from where the robot is, and
that the NOMINAL arm's IK finds joints within their limits less a margin. A refused move
raises a SafetyRefusal subclass naming the limit and the values, and nothing moves. A
taught move of any length (move_linear) passes the same checks at points of its straight
line no further apart than one step may be, and then goes out as one linear move; a
transfer on the joint-space line (move_joint) is checked whole the same way, and goes out
as one joint move to a robot that runs one (JointMotionBackend), else in steps.

The e-stop holds the robot at once and refuses every move, servo power on and hold
release until it is reset. The watchdog does the same when, during a servo, the camera
stops delivering frames or the robot link stops answering for longer than its timeout;
the loop feeds it with every frame, and every successful call to the robot feeds the
link side.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from vservo.core.cell.config import CellConfig, SafetyConfig
from vservo.core.cell.kinematics import ArmKinematics, UnreachableTarget
from vservo.core.geometry.spatial import Matrix, exp_twist, interpolate, pose_error, theta_u, transform
from vservo.core.robot.backend import (
    JointLine,
    JointMotionBackend,
    RobotBackend,
    RobotError,
    RobotStatus,
    StreamingBackend,
    apply_increment,
    move_and_wait,
    wait_for_the_end,
)
from vservo.robot_models.loader import load_arm

log = logging.getLogger("vservo.safety")

# The safety check asks only whether joints within the limits exist: a micrometre and a
# microradian are far inside any arm's repeatability.
CHECK_TOLERANCE = 1e-6
# A path is checked at points this share of the step limits apart (a joint-space path's
# steps end there too: the rest absorbs where the arm really stopped); a joint-space path
# is sampled this finely to place them.
STEP_FILL = 0.9
JOINT_SAMPLE_RAD = np.deg2rad(0.5)
# The most one linear move may turn the flange: near a half turn the short way round is a
# toss-up, which the controller and the arm's model may call differently (a turn of joint 6
# apart afterwards); a taught move that turns more goes out as a few moves within this.
LINEAR_TURN_RAD = np.deg2rad(160.0)
# A joint-space line sent as one motion starts at the joints the controller reports: the
# model's joints for its pose must be these (a turn or another branch apart, the line run
# would not be the line checked); a degree allows the controller's own calibrated model.
JOINTS_AGREE_RAD = np.deg2rad(1.0)
# Within this of a half turn either way round is as short: the one that leaves the
# multi-turn joints nearer their ranges' middles (ArmKinematics.unwound) is taken.
HALF_TURN_TOSS_RAD = np.deg2rad(10.0)


class SafetyRefusal(RobotError):
    """The safety layer refused a request; the message names the limit and the values."""


class OutsideWorkspace(SafetyRefusal):
    """The target puts the flange or a tool outside the workspace box."""


class BeyondJointLimits(SafetyRefusal):
    """The target needs joints beyond their limits (less the margin), or no joints reach it."""


class JointsDisagree(SafetyRefusal):
    """The controller reports joints other than the arm model's for its pose (a turn or another
    branch apart): a joint-space line checked from the model's would not be the one it runs."""


class StepTooLarge(SafetyRefusal):
    """The move is larger than one step may be."""


class TooFast(SafetyRefusal):
    """The move asks for more than the maximum speed."""


class SafetyStopActive(SafetyRefusal):
    """An e-stop or a watchdog stop is latched: nothing moves until it is reset."""


class Watchdog:
    """Calls ``on_quiet(reason)`` once when a fed source stays quiet longer than timeout_s.

    Armed for a servo run and disarmed after it; ``feed(source)`` marks a source alive.
    A background thread checks every tenth of the timeout.
    """

    SOURCES = ("camera", "link")

    def __init__(self, timeout_s: float, on_quiet: Callable[[str], None]) -> None:
        self.timeout_s = timeout_s
        self._on_quiet = on_quiet
        self._last_fed = dict.fromkeys(self.SOURCES, 0.0)
        self._disarmed = threading.Event()
        self._disarmed.set()
        self._thread: threading.Thread | None = None

    @property
    def armed(self) -> bool:
        return not self._disarmed.is_set()

    def feed(self, source: str) -> None:
        if source not in self._last_fed:
            raise ValueError(f"unknown watchdog source {source!r}: one of {', '.join(self.SOURCES)}")
        self._last_fed[source] = time.monotonic()

    def arm(self) -> None:
        """Start watching; every source counts as fed now."""
        self.disarm()
        now = time.monotonic()
        self._last_fed = dict.fromkeys(self.SOURCES, now)
        self._disarmed.clear()
        self._thread = threading.Thread(target=self._watch, name="vservo-watchdog", daemon=True)
        self._thread.start()

    def disarm(self) -> None:
        self._disarmed.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None

    def _watch(self) -> None:
        while not self._disarmed.wait(self.timeout_s / 10.0):
            now = time.monotonic()
            quiet = {source: now - fed for source, fed in self._last_fed.items() if now - fed > self.timeout_s}
            if quiet:
                source, silence = max(quiet.items(), key=lambda item: item[1])
                self._disarmed.set()
                self._on_quiet(f"watchdog: the {source} has been quiet for {silence:.1f} s (limit {self.timeout_s:g} s)")
                return


class SafetyLayer:
    """A RobotBackend that checks every move against ``limits`` before ``robot`` sees it.

    ``arm`` is the NOMINAL arm (the model the JRC uses) for the joint-limit check;
    ``q_seed`` seeds its first IK (later ones start from the previous solution).
    """

    def __init__(self, robot: RobotBackend, limits: SafetyConfig, arm: ArmKinematics, q_seed: Matrix) -> None:
        self.robot = robot
        self.limits = limits
        self.arm = arm
        self.name = robot.name
        self.watchdog = Watchdog(limits.watchdog_s, self._stop_from_watchdog)
        self._q_seed = np.asarray(q_seed, dtype=float).copy()
        self._stop_reason: str | None = None
        # Where the robot stands, while it is known without a reading (pose()): the pose last
        # read, or the target of the last move once the robot reported it done.
        self._pose: Matrix | None = None
        self._aim: Matrix | None = None  # the target of the move under way
        self._tool_frames = {"camera": arm.mount.eMc, "laser": arm.mount.eMl, "vacuum cup": arm.mount.eMv}

    @classmethod
    def from_config(cls, robot: RobotBackend, config: CellConfig) -> SafetyLayer:
        """The cell file's [safety] limits around ``robot``, with the cell's nominal arm."""
        arm = ArmKinematics(load_arm(config.arm), config.nominal.mount)
        return cls(robot, config.safety, arm, config.home_q)

    # -- stops -------------------------------------------------------------------------

    @property
    def stop_reason(self) -> str | None:
        """Why moves are refused (an e-stop or the watchdog), or None."""
        return self._stop_reason

    def emergency_stop(self, reason: str = "operator e-stop") -> None:
        """Hold the robot now and refuse every move until reset_emergency_stop()."""
        self._latch(f"e-stop: {reason}")

    def reset_emergency_stop(self) -> None:
        """Accept moves again. The robot stays held until hold(False)."""
        if self._stop_reason is not None:
            log.info("safety stop reset (was: %s)", self._stop_reason)
        self._stop_reason = None

    def _stop_from_watchdog(self, reason: str) -> None:
        try:
            self._latch(reason)
        except RobotError:
            pass  # _latch has logged it; the stop stays latched

    def _latch(self, reason: str) -> None:
        self._stop_reason = reason  # first: whatever happens to the hold, nothing moves any more
        self._forget_pose()
        log.warning("safety stop: %s", reason)
        try:
            self.robot.hold(True)
        except RobotError as exc:
            log.error("safety stop: the hold did not reach the robot: %s", exc)
            raise RobotError(f"{reason}; the hold did not reach the robot: {exc}") from exc

    def _refuse_if_stopped(self, what: str) -> None:
        if self._stop_reason is not None:
            raise SafetyStopActive(f"{what} refused: {self._stop_reason} (reset the stop first)")

    # -- checks ------------------------------------------------------------------------

    def check_target(
        self, bMe_target: Matrix, speed_m_s: float, bMe_now: Matrix | None = None, q_seed: Matrix | None = None
    ) -> Matrix:
        """Raise a SafetyRefusal unless a linear move to bMe_target at speed_m_s is allowed;
        returns the joints the nominal IK finds for it. ``bMe_now`` defaults to the robot's
        pose, ``q_seed`` (where the IK starts) to the joints of the last move sent."""
        self._refuse_if_stopped("move")
        bMe_target = np.asarray(bMe_target, dtype=float)
        limits = self.limits
        if not (np.isfinite(speed_m_s) and speed_m_s > 0.0):
            raise TooFast(f"move refused: speed {speed_m_s!r} m/s is not a positive number")
        if speed_m_s > limits.max_speed_m_s:
            raise TooFast(
                f"move refused: speed {speed_m_s * 1000:.1f} mm/s exceeds the maximum {limits.max_speed_m_s * 1000:.1f} mm/s"
            )
        self._check_in_workspace(bMe_target)
        bMe_now = self.read_pose() if bMe_now is None else bMe_now
        translation, rotation = pose_error(bMe_now, bMe_target)
        if translation > limits.max_step_m:
            raise StepTooLarge(
                f"move refused: a step of {translation * 1000:.1f} mm exceeds the maximum {limits.max_step_m * 1000:.1f} mm"
            )
        if rotation > limits.max_step_rad:
            raise StepTooLarge(
                f"move refused: a step of {np.degrees(rotation):.2f} deg exceeds the maximum "
                f"{np.degrees(limits.max_step_rad):.2f} deg"
            )

        try:
            q = self.arm.ik(
                bMe_target, self._q_seed if q_seed is None else q_seed, tolerance_m=CHECK_TOLERANCE, tolerance_rad=CHECK_TOLERANCE
            ).q
        except UnreachableTarget as exc:
            raise BeyondJointLimits(f"move refused: no joints within the limits reach the target ({exc})") from exc
        margins = np.minimum(q - self.arm.lower, self.arm.upper - q)
        worst = int(np.argmin(margins))
        if margins[worst] < limits.joint_margin_rad:
            raise BeyondJointLimits(
                f"move refused: joint {self.arm.joint_names[worst]} would be {np.degrees(margins[worst]):.2f} deg from "
                f"its limit, closer than the margin {np.degrees(limits.joint_margin_rad):.2f} deg"
            )
        return q

    def _check_in_workspace(self, bMe_target: Matrix) -> None:
        """OutsideWorkspace unless bMe_target is a finite pose that keeps the flange and every
        tool frame inside the workspace box."""
        limits = self.limits
        if bMe_target.shape != (4, 4) or not np.all(np.isfinite(bMe_target)):
            raise OutsideWorkspace(f"move refused: the target is not a finite 4x4 pose: {bMe_target.tolist()}")
        points = {"flange": bMe_target[:3, 3]}
        points.update({name: (bMe_target @ eMx)[:3, 3] for name, eMx in self._tool_frames.items()})
        for name, p in points.items():
            outside = (p < limits.workspace_min_m) | (p > limits.workspace_max_m)
            if outside.any():
                axis = "xyz"[int(np.argmax(outside))]
                raise OutsideWorkspace(
                    f"move refused: the {name} would be at {np.round(p * 1000, 1).tolist()} mm, outside the "
                    f"workspace box on {axis} ({np.round(limits.workspace_min_m * 1000, 1).tolist()} .. "
                    f"{np.round(limits.workspace_max_m * 1000, 1).tolist()} mm)"
                )

    def model_joints(self, bMe: Matrix) -> Matrix:
        """The joints the nominal arm model puts the flange at bMe with, on the branch of the
        last move sent (the JRC reports only the flange pose); NaN where no joints reach it."""
        try:
            return self.arm.ik(bMe, self._q_seed, tolerance_m=CHECK_TOLERANCE, tolerance_rad=CHECK_TOLERANCE).q
        except UnreachableTarget:
            return np.full(self.arm.dof, np.nan)

    # -- the RobotBackend interface ----------------------------------------------------

    def _link(self, call: Callable, *args):
        """Call the robot; a call that returns feeds the watchdog's link side."""
        result = call(*args)
        self.watchdog.feed("link")
        return result

    def connect(self) -> None:
        self._forget_pose()
        self._link(self.robot.connect)

    def close(self) -> None:
        self.watchdog.disarm()
        self.robot.close()

    def status(self) -> RobotStatus:
        status = self._link(self.robot.status)
        if self._stop_reason is None:
            return status
        return replace(status, detail="; ".join(filter(None, (status.detail, self._stop_reason))))

    def read_pose(self) -> Matrix:
        self._pose = self._link(self.robot.read_pose)
        return self._pose.copy()

    def pose(self) -> Matrix:
        """The flange pose, read from the robot only when it is not known: the pose last
        read while no move was sent since, or the target of the last move once the robot
        reported it done (a controller that reports a move done stands at its target, and
        reads it back to its resolution). Servo power, holds, alarms and a new connection
        forget it: the next call reads."""
        return (self._pose if self._pose is not None else self.read_pose()).copy()

    def _forget_pose(self) -> None:
        self._pose = self._aim = None

    def servo(self, on: bool) -> None:
        if on:
            self._refuse_if_stopped("servo power on")
        self._forget_pose()
        self._link(self.robot.servo, on)

    def hold(self, on: bool) -> None:
        if not on:
            self._refuse_if_stopped("hold release")
        self._forget_pose()
        self._link(self.robot.hold, on)

    def reset_alarms(self) -> None:
        self._forget_pose()
        self._link(self.robot.reset_alarms)

    def move_to(self, bMe_target: Matrix, speed_m_s: float) -> None:
        self._q_seed = self.check_target(bMe_target, speed_m_s, self._current_pose())
        self._sending(bMe_target)
        self._link(self.robot.move_to, bMe_target, speed_m_s)

    def move_by(self, bMe_increment: Matrix, speed_m_s: float) -> None:
        bMe_now = self._current_pose()
        bMe_target = apply_increment(bMe_now, bMe_increment)
        self._q_seed = self.check_target(bMe_target, speed_m_s, bMe_now)
        self._sending(bMe_target)
        self._link(self.robot.move_by, bMe_increment, speed_m_s)

    def _sending(self, bMe_target: Matrix) -> None:
        """A move to bMe_target goes out: where the robot stands is unknown until it ends."""
        self._pose, self._aim = None, np.array(bMe_target, dtype=float)

    def move_linear(self, bMe_target: Matrix, speed_m_s: float) -> None:
        """A taught move of any length (to a start, pick or place pose) on the straight line,
        as one linear move (MOVL keeps to the straight line). The whole line is checked
        first, at points within max_step_m / max_step_rad of each other (linear_path), so
        a refusal (SafetyRefusal) moves nothing and the one move needs no step limit of
        its own; then it is sent and waited for (MotionStopped if the robot stops short).
        A move that turns the flange more than LINEAR_TURN_RAD goes out as that many
        moves along the same line, so the controller turns the way the checks did."""
        bMe_target = np.array(bMe_target, dtype=float)
        bMe_from = self._current_pose()
        checked = self._turn_checks(bMe_from, bMe_target, speed_m_s)
        turned = sum(pose_error(a, b)[1] for a, b in zip([bMe_from, *(bMe for bMe, _ in checked)], (bMe for bMe, _ in checked)))
        moves = max(1, int(np.ceil(turned / LINEAR_TURN_RAD - 1e-9)))
        for k in range(1, moves + 1):  # the line's points the checks passed, each way the model turns
            bMe_segment, self._q_seed = checked[round(k * len(checked) / moves) - 1]
            bMe_segment = bMe_target if k == moves else bMe_segment
            self._refuse_if_stopped("move")  # a stop latched while the path was checked
            self._sending(bMe_segment)
            self._link(self.robot.move_to, bMe_segment, speed_m_s)
            wait_for_the_end(self)

    def move_joint(self, bMe_target: Matrix, speed_m_s: float, unwind: bool = False) -> None:
        """A long move on the joint-space line (joint_path), checked whole first (a refusal,
        SafetyRefusal, moves nothing): the way a transfer between two far poses keeps to the
        arm's workspace where the straight line between them leaves it. A robot that runs a
        joint-space line as one motion (JointMotionBackend, a UR's movej) is sent its end
        joints once, the line starting at the joints it reports; any other follows the
        line's steps, each a short linear move. Either is waited for (MotionStopped if the
        robot stops short). ``unwind``: end with the multi-turn joints nearest their ranges'
        middles."""
        bMe_from = self._current_pose()
        if not isinstance(self.robot, JointMotionBackend):
            self._follow(self.joint_path(bMe_from, bMe_target, speed_m_s, unwind=unwind), speed_m_s)
            return
        q_now = np.asarray(self._link(self.robot.read_joints), dtype=float)
        _, line = self._joint_line(bMe_from, bMe_target, speed_m_s, q_now, unwind)
        apart = np.abs(line.q_from - q_now)
        if apart.max() > JOINTS_AGREE_RAD:  # the line checked would not be the one the controller runs
            worst = int(np.argmax(apart))
            raise JointsDisagree(
                f"move refused: the controller reports joint {self.arm.joint_names[worst]} at "
                f"{np.degrees(q_now[worst]):.2f} deg, {np.degrees(apart[worst]):.2f} deg from the arm model's "
                f"{np.degrees(line.q_from[worst]):.2f} deg for its pose (at most {np.degrees(JOINTS_AGREE_RAD):g} deg)"
            )
        self._refuse_if_stopped("move")  # a stop latched while the path was checked
        self._q_seed = line.q_to
        self._sending(np.asarray(bMe_target, dtype=float))
        self._link(self.robot.move_joints, line, speed_m_s)
        wait_for_the_end(self)

    def wound(self, bMe_target: Matrix) -> bool:
        """Whether the joints a move to bMe_target reaches by continuity (model_joints)
        leave a multi-turn joint a turn or more from the middle of its range
        (ArmKinematics.unwound): the move to a run's start then unwinds it."""
        q = self.model_joints(bMe_target)
        return bool(np.all(np.isfinite(q)) and not np.allclose(self.arm.unwound(q), q))

    def linear_path(self, bMe_from: Matrix, bMe_target: Matrix, speed_m_s: float) -> list[Matrix]:
        """The points of a straight move from bMe_from to bMe_target at which it is checked,
        each within the step limits of the one before (check_target; SafetyRefusal names
        the first refused), no motion. The target is checked against the workspace first:
        from the robot's pose to a target in the box, the path's length, and so the work of
        checking it, is bounded whatever was asked."""
        return [bMe for bMe, _ in self._turn_checks(bMe_from, bMe_target, speed_m_s)]

    def _turn_checks(self, bMe_from: Matrix, bMe_target: Matrix, speed_m_s: float) -> list[tuple[Matrix, Matrix]]:
        """_linear_checks, except that a move within HALF_TURN_TOSS_RAD of a half turn is
        checked both ways round (the other through the pose halfway that way) and goes the
        way that passes, of two the one ending with the multi-turn joints nearer their
        middles: the short way is then a toss-up, and one way may meet joint 6's limit."""
        bMe_target = np.asarray(bMe_target, dtype=float)
        self._check_in_workspace(bMe_target)  # a target that is no pose fails here, not in the turn
        _, rotation = pose_error(bMe_from, bMe_target)
        if rotation < np.pi - HALF_TURN_TOSS_RAD:
            return self._linear_checks(bMe_from, bMe_target, speed_m_s)
        axis = theta_u(bMe_from[:3, :3].T @ bMe_target[:3, :3]) / rotation
        bMe_halfway = transform(
            bMe_from[:3, :3] @ exp_twist(np.concatenate([np.zeros(3), -(2 * np.pi - rotation) / 2 * axis]))[:3, :3],
            (bMe_from[:3, 3] + bMe_target[:3, 3]) / 2,
        )
        ways, refusals = [], []
        for route in ([bMe_target], [bMe_halfway, bMe_target]):
            try:
                checked, bMe_before = [], bMe_from
                for bMe_end in route:
                    checked += self._linear_checks(bMe_before, bMe_end, speed_m_s)
                    bMe_before = bMe_end
                ways.append(checked)
            except SafetyRefusal as exc:
                refusals.append(exc)
        if not ways:
            raise refusals[0]
        return min(ways, key=lambda checked: float(np.abs(checked[-1][1] - self.arm.unwound(checked[-1][1])).sum()))

    def _linear_checks(self, bMe_from: Matrix, bMe_target: Matrix, speed_m_s: float) -> list[tuple[Matrix, Matrix]]:
        """linear_path's points, each with the joints the nominal IK finds for it."""
        bMe_target = np.asarray(bMe_target, dtype=float)
        self._check_in_workspace(bMe_target)
        translation, rotation = pose_error(bMe_from, bMe_target)
        fill = max(translation / self.limits.max_step_m, rotation / self.limits.max_step_rad) / STEP_FILL
        steps = max(1, int(np.ceil(fill)))
        waypoints = [interpolate(bMe_from, bMe_target, k / steps) for k in range(1, steps + 1)]
        checked: list[tuple[Matrix, Matrix]] = []
        q = None  # each point's IK starts from the point before, as the controller's does
        for bMe_before, bMe_waypoint in zip([bMe_from, *waypoints], waypoints):
            q = self.check_target(bMe_waypoint, speed_m_s, bMe_before, q)
            checked.append((bMe_waypoint, q))
        return checked

    def joint_path(
        self, bMe_from: Matrix, bMe_target: Matrix, speed_m_s: float, q_seed: Matrix | None = None, unwind: bool = False
    ) -> list[Matrix]:
        """The steps of a move from bMe_from to bMe_target on the straight line between
        their joints (the nominal IK of each, the target's from the start's), each step
        checked (check_target), no motion.

        The joint limits are a box, so every point of the joint-space line between two
        poses within them is within them too, where the straight Cartesian line between
        the same poses can cut through the hole inside an arm's thin tool-down shell (the
        UPJ's at the table's heights); the workspace box is checked at every step.
        The line is sampled every JOINT_SAMPLE_RAD (of the joint that moves most) and a
        step ends at the last sample within STEP_FILL of the step limits; the arm goes
        from step to step on short straight lines (the chord of a 45 mm step strays less
        than a millimetre from the joint-space curve). ``q_seed``: where the start's IK
        starts (the joints of the last move sent by default); ``unwind``: the target's joints
        moved by whole turns nearest their ranges' middles (ArmKinematics.unwound), the steps
        small enough that a controller following its joints by continuity turns them back.
        """
        steps, _ = self._joint_line(bMe_from, bMe_target, speed_m_s, q_seed, unwind)
        return steps

    def _joint_line(
        self, bMe_from: Matrix, bMe_target: Matrix, speed_m_s: float, q_seed: Matrix | None, unwind: bool
    ) -> tuple[list[Matrix], JointLine]:
        """joint_path's steps, and the line they lie on: its end joints and the peak of the
        flange's |dp/ds| from each chord of JOINT_SAMPLE_RAD of the leading joint (within a
        fraction of a per cent of the derivative's peak on an arm's smooth kinematics)."""
        bMe_target = np.asarray(bMe_target, dtype=float)
        self._check_in_workspace(bMe_target)  # before any IK: a far target costs nothing
        try:
            q_from = self.arm.ik(
                bMe_from, self._q_seed if q_seed is None else q_seed, tolerance_m=CHECK_TOLERANCE, tolerance_rad=CHECK_TOLERANCE
            ).q
            q_to = self.arm.ik(bMe_target, q_from, tolerance_m=CHECK_TOLERANCE, tolerance_rad=CHECK_TOLERANCE).q
            q_to = self.arm.unwound(q_to) if unwind else q_to
        except UnreachableTarget as exc:
            raise BeyondJointLimits(f"move refused: no joints within the limits reach the path's ends ({exc})") from exc
        samples = max(1, int(np.ceil(np.max(np.abs(q_to - q_from)) / JOINT_SAMPLE_RAD)))
        qs = [q_from + (k / samples) * (q_to - q_from) for k in range(1, samples + 1)]
        poses = [self.arm.fk(q) for q in qs[:-1]] + [bMe_target]
        max_m, max_rad = STEP_FILL * self.limits.max_step_m, STEP_FILL * self.limits.max_step_rad
        steps, bMe_last = [], np.asarray(bMe_from, dtype=float)
        for k in range(samples):
            if k < samples - 1:
                translation, rotation = pose_error(bMe_last, poses[k + 1])
                if translation <= max_m and rotation <= max_rad:
                    continue  # the next sample is still within one step
            steps.append((bMe_last, poses[k], qs[k]))
            bMe_last = poses[k]
        for bMe_before, bMe_step, q in steps:
            self.check_target(bMe_step, speed_m_s, bMe_before, q)
        points = np.array([np.asarray(bMe_from, dtype=float)[:3, 3], *(bMe[:3, 3] for bMe in poses)])
        chords = np.linalg.norm(np.diff(points, axis=0), axis=1)
        line = JointLine(q_from, q_to, float(chords.max(initial=0.0) * samples))
        return [bMe_step for _, bMe_step, _ in steps], line

    def _follow(self, waypoints: list[Matrix], speed_m_s: float) -> None:
        for bMe_waypoint in waypoints:
            move_and_wait(self, bMe_waypoint, speed_m_s)

    def move_timed(self, bMe_target: Matrix, duration_s: float) -> None:
        bMe_now = self._current_pose()
        translation, _ = pose_error(bMe_now, np.asarray(bMe_target, dtype=float))
        if not (np.isfinite(duration_s) and duration_s > 0.0):
            raise TooFast(f"move refused: duration {duration_s!r} s is not a positive number")
        # A pure rotation asks no linear speed: check it at the slowest positive speed.
        self._q_seed = self.check_target(bMe_target, max(translation / duration_s, np.finfo(float).tiny), bMe_now)
        self._sending(bMe_target)
        self._link(self.robot.move_timed, bMe_target, duration_s)

    def stream_twist(self, eVe: Matrix, hold_s: float) -> None:
        """A streamed twist (a velocity-controlled robot), checked as a move: its linear speed,
        and the pose it would reach if no other came after it (held hold_s from the pose
        the robot last reported) against the workspace, the step limits and the joints."""
        if not isinstance(self.robot, StreamingBackend):
            raise RobotError(f"the {self.robot.name} robot takes no streamed twist: it is not velocity-controlled")
        eVe = np.asarray(eVe, dtype=float)
        if eVe.shape != (6,) or not np.all(np.isfinite(eVe)) or not (np.isfinite(hold_s) and hold_s > 0.0):
            raise TooFast(f"twist refused: {eVe.tolist()} held {hold_s!r} s is not a finite twist held a positive time")
        bMe_now = self.robot.read_pose()
        target = bMe_now @ exp_twist(eVe * hold_s)
        self._q_seed = self.check_target(target, max(float(np.linalg.norm(eVe[:3])), np.finfo(float).tiny), bMe_now)
        self._pose = None
        self._link(self.robot.stream_twist, eVe, hold_s)

    def stop_motion(self) -> None:
        """Bring a streamed motion to a standstill and wait for it (a backend that streams
        nothing stands still after each move already)."""
        stop = getattr(self.robot, "stop_motion", None)
        if stop is not None:
            self._link(stop)

    def pose_at(self, t_s: float) -> Matrix:
        """The flange pose at the robot's clock t_s, where the backend keeps its history
        (a UR's RTDE states); else the pose it reports now."""
        pose_at = getattr(self.robot, "pose_at", None)
        return self.read_pose() if pose_at is None else self._link(pose_at, t_s)

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        aim, self._aim = self._aim, None
        done = self._link(self.robot.wait_motion, timeout_s)
        if done and aim is not None:
            self._pose = aim  # it stands at the target: no reading needed to know where
        return done

    def clock_s(self) -> float:
        return self.robot.clock_s()

    def cell_clock_s(self) -> float:
        return self.robot.cell_clock_s()

    def dwell(self, seconds: float) -> None:
        self.robot.dwell(seconds)

    def _current_pose(self) -> Matrix:
        """pose(), without the copy: for the checks, which do not change it."""
        return self._pose if self._pose is not None else self.read_pose()
