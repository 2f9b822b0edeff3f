"""A Universal Robots controller on the simulated cell: the programs it runs and how it moves the arm.

It runs the URScript subset vservo sends (core/robot/ur_script.py) one control period at a
time (125 Hz, a CB3's rate; 500 Hz an e-Series'), moving the plant's joints with its
NOMINAL arm model, as a real controller moves its arm with its own: ``movel`` on a
trapezoidal profile along the straight line, ``movej`` on one along the straight line in
joint space (a target beyond the joint limits a protective stop before it moves),
``speedl`` by integrating the twist (reached at the program's acceleration, held for at
most its time), ``stopl`` by decelerating. A
new program replaces the running one and the arm keeps its velocity into it. It limits
the TCP's speed to its own safety limits, and a motion that would take a joint out of its
limits or the TCP out of reach is a protective stop: the arm stops at once and waits for
"unlock protective stop" from the dashboard. A "stop" from the dashboard (the host's
hold, vservo's e-stop) aborts the program and stops the arm at the next control period.

Its log (``log``) keeps every program it received and every stop, on the controller's
clock: the figures of a run (commands per second, how long a stop took) are read there.

It speaks its poses and twists in its own base frame u, as a real controller does (a
UR's ``Base``, a half turn about z from the URDF root ``base_link`` that the plant's arm
model is in: robot_models.loader.controller_base).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from vservo.core.cell.config import VacuumDeviceConfig
from vservo.core.cell.kinematics import ArmKinematics, UnreachableTarget
from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix, exp_twist, interpolate, inverse, pose_error, theta_u
from vservo.core.robot import trapezoid
from vservo.core.robot.ur_script import BANK_SIZE, INPUT_BIT_OFFSET, OUTPUT_BIT_OFFSET, DigitalOutputs, pose_from_ur
from vservo.core.sim.plant import SimulatedCell
from vservo.robot_models.loader import controller_base

log = logging.getLogger("vservo.ur_controller")

IK_TOLERANCE = 1e-7


class RobotMode(IntEnum):
    """RTDE robot_mode."""

    POWER_OFF = 3
    IDLE = 5
    RUNNING = 7


class SafetyMode(IntEnum):
    """RTDE safety_mode."""

    NORMAL = 1
    PROTECTIVE_STOP = 3
    ROBOT_EMERGENCY_STOP = 7


class RuntimeState(IntEnum):
    """RTDE runtime_state."""

    STOPPED = 1
    PLAYING = 2


@dataclass(frozen=True)
class UrLimits:
    """The controller's own limits (its safety configuration on a real arm)."""

    max_speed_m_s: float = 1.0
    max_rotation_rad_s: float = np.pi  # a UR's wrist joints turn at 180 deg/s
    max_acceleration_m_s2: float = 5.0
    max_rotation_acceleration_rad_s2: float = 4.0 * np.pi
    max_joint_speed_rad_s: float = np.pi  # a UR5's datasheet: all joints 180 deg/s
    max_joint_acceleration_rad_s2: float = 4.0 * np.pi


@dataclass(frozen=True)
class LogEntry:
    """One event on the controller's clock: a program received ("program") and its first
    statement's name (``what``), or a stop ("stop", "pause", "protective stop",
    "emergency stop", "runtime error", "power off")."""

    time_s: float
    kind: str
    what: str


class ScriptError(VservoError, ValueError):
    """A program the controller cannot run: the message says which line and why."""


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_LIST = rf"\[\s*({_NUMBER}(?:\s*,\s*{_NUMBER})*)\s*\]"
_STATEMENTS: dict[str, re.Pattern[str]] = {
    "movel": re.compile(rf"movel\(\s*p{_LIST}\s*,\s*a\s*=\s*({_NUMBER})\s*,\s*v\s*=\s*({_NUMBER})\s*\)$"),
    "movej": re.compile(
        rf"movej\(\s*{_LIST}\s*,\s*a\s*=\s*({_NUMBER})\s*,\s*v\s*=\s*({_NUMBER})\s*(?:,\s*t\s*=\s*({_NUMBER})\s*)?\)$"
    ),
    "speedl": re.compile(rf"speedl\(\s*{_LIST}\s*,\s*({_NUMBER})\s*,\s*({_NUMBER})\s*\)$"),
    "stopl": re.compile(rf"stopl\(\s*({_NUMBER})\s*\)$"),
    "digital_out": re.compile(r"set_(standard|tool)_digital_out\(\s*(\d+)\s*,\s*(True|False)\s*\)$"),
    "register": re.compile(rf"write_output_integer_register\(\s*(\d+)\s*,\s*({_NUMBER})\s*\)$"),
}


@dataclass
class Statement:
    kind: str
    values: tuple[float, ...]
    target: Matrix | None = None  # movel: the pose uMe; movej: the joints (rad)
    elapsed_s: float = 0.0
    # movel, movej: the straight line's start (the pose, the joints), and its duration on the trapezoidal profile
    start: Matrix | None = None
    duration_s: float = 0.0
    profile: tuple[float, float, float] = (0.0, 1.0, 1.0)  # the trapezoid's length, top speed, acceleration

    def advance(self, dt: float) -> tuple[bool, float]:
        """A movel's or movej's profile one period on: whether it has ended, and the fraction
        of the line it has covered."""
        self.elapsed_s = min(self.elapsed_s + dt, self.duration_s)
        done = self.elapsed_s >= self.duration_s
        length = self.profile[0]
        return done, 1.0 if done or length == 0.0 else trapezoid.distance(self.elapsed_s, *self.profile) / length


def parse_program(text: str) -> list[Statement]:
    """The statements of one program: ``def name():`` ... ``end``, or a single statement."""
    lines = [line.strip() for line in text.strip().splitlines() if line.strip() and not line.strip().startswith("#")]
    if lines and lines[0].startswith("def "):
        if not re.fullmatch(r"def \w+\(\):", lines[0]) or lines[-1] != "end":
            raise ScriptError(f"a program is 'def name():' ... 'end', got {lines[0]!r} ... {lines[-1]!r}")
        lines = lines[1:-1]
    return [_statement(line) for line in lines]


def _statement(line: str) -> Statement:
    for kind, pattern in _STATEMENTS.items():
        match = pattern.match(line)
        if match is None:
            continue
        if kind == "movel":
            pose = [float(v) for v in match.group(1).split(",")]
            if len(pose) != 6:
                raise ScriptError(f"{line!r}: a pose has 6 numbers")
            return Statement(kind, (float(match.group(2)), float(match.group(3))), target=pose_from_ur(pose))
        if kind == "movej":
            q = [float(v) for v in match.group(1).split(",")]
            if len(q) != 6:
                raise ScriptError(f"{line!r}: a joint position has 6 numbers (rad)")
            a, v, t = (float(g) if g is not None else 0.0 for g in match.groups()[1:])
            return Statement(kind, (a, v, t), target=np.array(q))
        if kind == "speedl":
            twist = [float(v) for v in match.group(1).split(",")]
            if len(twist) != 6:
                raise ScriptError(f"{line!r}: a twist has 6 numbers")
            return Statement(kind, (*twist, float(match.group(2)), float(match.group(3))))
        if kind == "digital_out":
            bank = 0.0 if match.group(1) == "standard" else 1.0
            return Statement(kind, (bank, float(match.group(2)), float(match.group(3) == "True")))
        return Statement(kind, tuple(float(g) for g in match.groups()))
    raise ScriptError(f"{line!r}: not a statement this controller runs")


@dataclass
class ControllerState:
    """What RTDE reports, as the controller knows it."""

    robot_mode: RobotMode = RobotMode.POWER_OFF
    safety_mode: SafetyMode = SafetyMode.NORMAL
    standard_outputs: int = 0
    tool_outputs: int = 0
    registers: dict[int, int] = field(default_factory=dict)


class UrController:
    """The controller on ``cell``: ``tick`` runs one control period; ``start`` ticks on a thread.

    ``vacuum``: the cell file's [vacuum] device; when it is "ur_io", the cup's valve is on
    its ``suction_output`` (of the bank ``io``) and its pressure switch on ``grip_input``.
    ``time_scale``: the controller's clock runs this many times faster than the wall's.
    """

    def __init__(
        self,
        cell: SimulatedCell,
        frequency_hz: float = 125.0,
        limits: UrLimits = UrLimits(),
        vacuum: VacuumDeviceConfig | None = None,
        time_scale: float = 1.0,
    ) -> None:
        self.cell, self.frequency_hz, self.limits, self.time_scale = cell, frequency_hz, limits, time_scale
        self.period_s = 1.0 / frequency_hz
        self.vacuum = vacuum if vacuum is not None and vacuum.device == "ur_io" else None
        self.state = ControllerState()
        self.program: list[Statement] = []
        self.bMu = controller_base(cell.jrc_arm.name)  # its base frame u in the arm model's root b
        self.uMb = inverse(self.bMu)
        self.twist_u = np.zeros(6)  # the twist a speedl or stopl drives the TCP at (v, w in u)
        self.tcp_speed = np.zeros(6)  # the TCP's velocity over the last period, whatever moved it (RTDE's)
        self.time_s = 0.0  # the controller's clock
        self.log: list[LogEntry] = []
        self.last_moved_s = 0.0  # the controller's clock when the arm last moved
        self.lock = threading.RLock()
        self.on_tick: list[Callable[[], None]] = []  # called after each period, the lock held
        self._moved_this_tick = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- the plant as the controller sees it ---------------------------------------------

    @property
    def arm(self) -> ArmKinematics:
        return self.cell.jrc_arm  # the controller's nominal model of its arm

    @property
    def q(self) -> Matrix:
        return self.cell.state.q

    def tcp_pose(self) -> Matrix:
        """uMe: the TCP (flange) pose the controller computes from its joints, with its model."""
        return self.uMb @ self.arm.fk(self.cell.state.q)

    @property
    def running(self) -> bool:
        return bool(self.program)

    @property
    def motion(self) -> object | None:
        """Something while the arm moves (a program runs or the arm still has speed), else None."""
        return True if self.program or np.any(self.twist_u != 0.0) or np.any(self.tcp_speed != 0.0) else None

    def advance(self) -> None:
        """The plant is brought up to date by the ticks themselves."""

    def digital_input_bits(self) -> int:
        if self.vacuum is None or self.vacuum.grip_input is None or not self.cell.holding_part:
            return 0
        return 1 << (INPUT_BIT_OFFSET[DigitalOutputs(self.vacuum.io)] + self.vacuum.grip_input)

    def digital_output_bits(self) -> int:
        state = self.state
        return state.standard_outputs << OUTPUT_BIT_OFFSET[DigitalOutputs.STANDARD] | (
            state.tool_outputs << OUTPUT_BIT_OFFSET[DigitalOutputs.TOOL]
        )

    # -- the host's requests -----------------------------------------------------------

    def run_program(self, text: str) -> None:
        """A program from the script port: it replaces the running one (ScriptError: nothing changes)."""
        statements = parse_program(text)
        with self.lock:
            self.log.append(LogEntry(self.time_s, "program", statements[0].kind if statements else ""))
            if self.state.robot_mode is not RobotMode.RUNNING or self.state.safety_mode is not SafetyMode.NORMAL:
                log.warning(
                    "program refused: robot mode %s, safety mode %s", self.state.robot_mode.name, self.state.safety_mode.name
                )
                return
            self.program = statements

    def stop_program(self, kind: str = "stop") -> None:
        """Abort the program; the arm stops at the next control period."""
        with self.lock:
            self.program = []
            self._halt(kind)

    def _halt(self, kind: str) -> None:
        """The arm stops where it is: no period after this one moves it."""
        self.twist_u = np.zeros(6)
        self.log.append(LogEntry(self.time_s, kind, ""))

    def power(self, on: bool) -> None:
        with self.lock:
            if not on:
                self.stop_program("power off")
            self.state.robot_mode = RobotMode.RUNNING if on else RobotMode.POWER_OFF

    def unlock_protective_stop(self) -> bool:
        with self.lock:
            if self.state.safety_mode is not SafetyMode.PROTECTIVE_STOP:
                return False
            self.state.safety_mode = SafetyMode.NORMAL
            return True

    def emergency_stop(self, pressed: bool) -> None:
        """The robot's emergency stop button: pressed, the arm stops and power drops."""
        with self.lock:
            if pressed:
                self.stop_program("emergency stop")
                self.state.safety_mode = SafetyMode.ROBOT_EMERGENCY_STOP
                self.state.robot_mode = RobotMode.POWER_OFF
            elif self.state.safety_mode is SafetyMode.ROBOT_EMERGENCY_STOP:
                self.state.safety_mode = SafetyMode.NORMAL

    # -- running -----------------------------------------------------------------------

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="ur-controller", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _run(self) -> None:
        wall_period_s = self.period_s / self.time_scale
        next_s = time.monotonic()
        while not self._stop.is_set():
            next_s += wall_period_s
            late_s = time.monotonic() - next_s
            if late_s > 10 * wall_period_s:  # a loaded host: skip what cannot be caught up, as time
                next_s = time.monotonic()
            with self.lock:
                self.tick()
                for callback in self.on_tick:
                    callback()
            self._stop.wait(max(next_s - time.monotonic(), 0.0))

    def tick(self) -> None:
        """One control period: the program's statement runs on, the arm moves."""
        dt = self.period_s
        uMe_before = self.tcp_pose()
        while self.program:
            statement = self.program[0]
            if not self._step(statement, dt):
                break  # the statement goes on next period
            self.program.pop(0)
        if not self.program and np.any(self.twist_u != 0.0):
            # The program has ended (a speedl's time ran out) with the arm still moving: it stops.
            self._decelerate(self.limits.max_acceleration_m_s2, dt)
        self.time_s += dt
        if self._moved_this_tick:
            self.last_moved_s = self.time_s
            uMe = self.tcp_pose()
            turn = theta_u(uMe[:3, :3] @ uMe_before[:3, :3].T)
            self.tcp_speed = np.r_[uMe[:3, 3] - uMe_before[:3, 3], turn] / dt
        else:
            self.cell.pass_time(dt)
            self.tcp_speed = np.zeros(6)
        self._moved_this_tick = False

    def _step(self, statement: Statement, dt: float) -> bool:
        """Run ``statement`` for one period; True once it has ended."""
        kind, values = statement.kind, statement.values
        if kind == "movel":
            return self._movel(statement, dt)
        if kind == "movej":
            return self._movej(statement, dt)
        if kind == "speedl":
            *twist, acceleration, hold_s = values
            statement.elapsed_s += dt
            self._accelerate_to(np.asarray(twist), acceleration, dt)
            return statement.elapsed_s >= hold_s
        if kind == "stopl":
            self._decelerate(values[0], dt)
            return not np.any(self.twist_u != 0.0)
        if kind == "digital_out":
            self._set_output(
                DigitalOutputs.STANDARD if values[0] == 0.0 else DigitalOutputs.TOOL, int(values[1]), bool(values[2])
            )
            return True
        if kind == "register":
            self.state.registers[int(values[0])] = int(values[1])
            return True
        raise ScriptError(f"no statement {kind!r}")

    def _set_output(self, bank: DigitalOutputs, n: int, on: bool) -> None:
        if not 0 <= n < BANK_SIZE[bank]:
            self._fault(f"{bank} digital output {n} does not exist (0..{BANK_SIZE[bank] - 1})")
            return
        bits = self.state.standard_outputs if bank is DigitalOutputs.STANDARD else self.state.tool_outputs
        bits = bits | 1 << n if on else bits & ~(1 << n)
        if bank is DigitalOutputs.STANDARD:
            self.state.standard_outputs = bits
        else:
            self.state.tool_outputs = bits
        vacuum = self.vacuum
        if vacuum is not None and vacuum.io == bank and vacuum.suction_output == n:
            self.cell.vacuum(on)

    def _fault(self, why: str) -> None:
        log.warning("runtime error: %s", why)
        self.program = []
        self._halt("runtime error")

    # -- motion ------------------------------------------------------------------------

    def _accelerate_to(self, twist: Matrix, acceleration: float, dt: float) -> None:
        twist = self._within_speed_limits(twist)
        change = twist - self.twist_u
        # The angular part ramps as the linear one does, scaled by the ratio of the limits.
        reach = (
            np.array([acceleration] * 3 + [acceleration * self.limits.max_rotation_rad_s / self.limits.max_speed_m_s] * 3) * dt
        )
        linear, angular = np.linalg.norm(change[:3]), np.linalg.norm(change[3:])
        scale = min(1.0, reach[0] / linear if linear > 0 else 1.0, reach[3] / angular if angular > 0 else 1.0)
        self._move_by_twist(self.twist_u + scale * change, dt)

    def _decelerate(self, acceleration: float, dt: float) -> None:
        self._accelerate_to(np.zeros(6), acceleration, dt)

    def _within_speed_limits(self, twist: Matrix) -> Matrix:
        twist = np.asarray(twist, dtype=float).copy()
        speed, rotation = np.linalg.norm(twist[:3]), np.linalg.norm(twist[3:])
        scale = min(1.0, self.limits.max_speed_m_s / speed if speed > 0 else 1.0)
        scale = min(scale, self.limits.max_rotation_rad_s / rotation if rotation > 0 else 1.0)
        return twist * scale

    def _move_by_twist(self, twist_u: Matrix, dt: float) -> None:
        """Hold the base-frame twist for dt: p += v dt, R = exp(w dt) R, through the model's IK."""
        self.twist_u = twist_u
        if not np.any(twist_u != 0.0):
            return
        uMe = self.tcp_pose()
        target = uMe.copy()
        target[:3, 3] += twist_u[:3] * dt
        target[:3, :3] = exp_twist(np.r_[0.0, 0.0, 0.0, twist_u[3:] * dt])[:3, :3] @ uMe[:3, :3]
        self._move_to(target, dt, settle=False)

    def _move_to(self, uMe_target: Matrix, dt: float, settle: bool) -> bool:
        """The TCP to uMe_target (in the controller's base frame) this period, through the model's IK."""
        try:
            q = self.arm.ik(self.bMu @ uMe_target, self.q, tolerance_m=IK_TOLERANCE, tolerance_rad=IK_TOLERANCE, restarts=0).q
        except UnreachableTarget as exc:
            self._protective_stop(f"the TCP cannot go on: {exc}")
            return False
        self.cell.move_joints(q, dt, settle=settle)
        self._moved_this_tick = True
        return True

    def _protective_stop(self, why: str) -> None:
        log.warning("protective stop: %s", why)
        self.program = []
        self.state.safety_mode = SafetyMode.PROTECTIVE_STOP
        self._halt("protective stop")

    def _movel(self, statement: Statement, dt: float) -> bool:
        """A linear move on a trapezoidal profile: of the path's length at the move's speed
        and acceleration, or of its turn at the controller's turning limits where that takes longer."""
        acceleration, speed = statement.values
        speed = min(speed, self.limits.max_speed_m_s)
        target = statement.target
        if target is None:
            raise ScriptError("movel without a target pose")
        if statement.start is None:
            statement.start = self.tcp_pose()
            translation, rotation = pose_error(statement.start, target)
            limits = self.limits
            by_length = (translation, speed, acceleration)
            by_turn = (rotation, limits.max_rotation_rad_s, limits.max_rotation_acceleration_rad_s2)
            statement.profile = max(by_length, by_turn, key=lambda profile: trapezoid.duration(*profile))
            statement.duration_s = trapezoid.duration(*statement.profile)
        done, s = statement.advance(dt)
        if not self._move_to(interpolate(statement.start, target, s), dt, settle=done):
            return False
        return done

    def _movej(self, statement: Statement, dt: float) -> bool:
        """Every joint on the straight line to the target joints, on the leading joint's
        trapezoid (_joint_profile); a target beyond the joint limits is a protective stop
        before the arm moves (the line between joints within a box stays within it)."""
        q_target = statement.target
        if q_target is None:
            raise ScriptError("movej without target joints")
        if statement.start is None:
            acceleration, speed, _ = statement.values
            if q_target.shape != self.q.shape or not (acceleration > 0.0 and speed > 0.0):
                self._fault(
                    f"movej: {q_target.size} joints at a={acceleration:g}, v={speed:g} (this arm: {self.q.size}, a and v > 0)"
                )
                return False
            beyond = (q_target < self.arm.lower) | (q_target > self.arm.upper)
            if beyond.any():
                k = int(np.argmax(beyond))
                self._protective_stop(
                    f"movej: joint {self.arm.joint_names[k]} to {np.degrees(q_target[k]):.2f} deg, beyond its limits "
                    f"{np.degrees(self.arm.lower[k]):.2f} .. {np.degrees(self.arm.upper[k]):.2f} deg"
                )
                return False
            statement.start = self.q.copy()
            self.twist_u = np.zeros(6)  # the joint move takes the arm over from any twist
            statement.profile = self._joint_profile(float(np.max(np.abs(q_target - statement.start))), *statement.values)
            statement.duration_s = trapezoid.duration(*statement.profile)
        done, s = statement.advance(dt)
        self.cell.move_joints(statement.start + s * (q_target - statement.start), dt, settle=done)
        self._moved_this_tick = True
        return done

    def _joint_profile(
        self, length_rad: float, acceleration: float, speed: float, duration_s: float
    ) -> tuple[float, float, float]:
        """The leading joint's trapezoid for a movej: of its a and v, scaled in time to last
        t when t is given (the time has priority), within the controller's joint speed and
        acceleration (a move that would exceed them takes longer)."""
        if duration_s > 0.0 and length_rad > 0.0:
            k = trapezoid.duration(length_rad, speed, acceleration) / duration_s
            speed, acceleration = speed * k, acceleration * k * k
        limits = self.limits
        return length_rad, min(speed, limits.max_joint_speed_rad_s), min(acceleration, limits.max_joint_acceleration_rad_s2)
