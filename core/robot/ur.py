"""A Universal Robots controller: a RobotBackend on ur-rtde, reading RTDE and sending URScript.

ur-rtde (PyPI ``ur_rtde``, SDU Robotics) is the field's maintained library for a UR's wire
protocols. Its control interface (``RTDEControlInterface``) is not used: it uploads its own
URScript control program of some 2000 lines (threads, loops, a register protocol) to the
controller and drives it through RTDE input registers, so serving it honestly takes a URScript
interpreter, which no emulator of ours can be (docs/connecting-your-cell.md). vservo uses
what a controller offers without a program of its own:

- the robot's state from RTDE (``RTDEReceiveInterface``, port 30004) at the controller's
  rate (125 Hz, 500 Hz on an e-Series): the TCP pose, the modes, the I/O, the clock; every
  package is kept a short while with the host's time it arrived, so a camera frame is
  matched with the pose at its exposure (``pose_at``);
- one small URScript program a command (core/robot/ur_script.py), sent with ur-rtde's
  ``ScriptClient`` to the secondary interface (30002); its last statement writes its
  sequence number to an output register, which RTDE reads back when it has run to its end;
- the dashboard server (``DashboardClient``, 29999): power, brakes, the stop (the host's
  hold and vservo's e-stop), unlocking a protective stop.

The controller speaks its poses and twists in its own base frame u (``Base`` on the
pendant); vservo's are in the arm model's root frame b, and the backend turns one into
the other with bMu (robot_models.loader.controller_base: a half turn about z on a UR5 or
UR10 from example-robot-data, whose root is ROS's ``base_link``).

A protective or safeguard stop reads as held, an emergency stop, a violation or a fault as
an alarm; the host's own hold (a dashboard "stop") as held until released.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from vservo.core.cell.config import UrConfig
from vservo.core.geometry.spatial import Matrix, interpolate, inverse
from vservo.core.robot import ur_script
from vservo.core.robot.backend import JointLine, RobotError, RobotNotReady, RobotStatus, apply_increment
from vservo.core.robot.ur_script import DONE_REGISTER, DigitalOutputs

RTDE_VARIABLES = [
    "timestamp",
    "actual_q",
    "actual_TCP_pose",
    "actual_TCP_speed",
    "robot_mode",
    "safety_mode",
    "runtime_state",
    "actual_digital_input_bits",
    "actual_digital_output_bits",
    f"output_int_register_{DONE_REGISTER}",
]
ROBOT_MODE_RUNNING = 7  # powered, brakes released
RUNTIME_PLAYING = 2
SAFETY_MODES = {
    1: "normal",
    2: "reduced",
    3: "protective stop",
    4: "recovery",
    5: "safeguard stop",
    6: "system emergency stop",
    7: "robot emergency stop",
    8: "violation",
    9: "fault",
    10: "validate joint id",
    11: "undefined safety mode",
    12: "automatic mode safeguard stop",
    13: "system three position enabling stop",
}
HELD_SAFETY_MODES = frozenset({3, 5, 12, 13})  # stops the arm recovers from when released
NORMAL_SAFETY_MODES = frozenset({1, 2})
# How long the state history is kept: longer than a camera's latency and a frame.
HISTORY_S = 2.0
# How often the reader looks for a new RTDE package: a quarter of a CB3's period (8 ms).
POLL_S = 0.002
# The fastest a movej turns its leading joint: a UR5's datasheet, all joints 180 deg/s (the
# controller slows a faster one to its own limits; this bounds a turn the flange's speed
# does not, a wrist turning in place).
JOINT_SPEED_RAD_S = np.pi
# Below this TCP speed the arm stands still (m/s, rad/s).
STANDING_SPEED = 1e-6


class UrLinkError(RobotError):
    """The controller cannot be reached or stopped answering; the message names the port."""


@dataclass(frozen=True)
class UrState:
    """One RTDE package, with the host's monotonic time it was read at."""

    received_s: float
    timestamp_s: float
    q: Sequence[float]  # the joints (rad), as RTDE sends them
    tcp_pose: Sequence[float]  # [x, y, z, rx, ry, rz] as RTDE sends it: made a matrix when read (uMe)
    tcp_speed: Matrix
    robot_mode: int
    safety_mode: int
    runtime_state: int
    input_bits: int
    output_bits: int
    done_register: int

    @cached_property
    def uMe(self) -> Matrix:
        """The TCP pose in the controller's base frame u; computed once, and only for the
        packages read: the reader keeps every package the controller sends (125 or 500 a
        second), the loop reads a few."""
        return ur_script.pose_from_ur(self.tcp_pose)


class UrBackend:
    """The controller of [ur]; ``connect`` opens its three ports. Thread-safe: programs go
    out one at a time, and a hold from another thread (e-stop, watchdog) goes straight to
    the dashboard. ``bMu``: the controller's base frame u in vservo's base frame b, the
    arm model's root (robot_models.loader.controller_base of the cell's arm)."""

    name = "ur"
    # movel keeps the TCP on the straight line however long the move: the safety layer
    # checks a taught move's steps and sends it whole (SafetyLayer.move_linear)
    linear_segments = True

    def __init__(self, config: UrConfig, bMu: Matrix) -> None:
        self.config = config
        self.bMu = np.array(bMu, dtype=float)
        self.uMb = inverse(self.bMu)
        self.acceleration_m_s2 = config.acceleration_m_s2
        # ur-rtde's clients (its modules come without type information)
        self._receive: Any = None
        self._script: Any = None
        self._dashboard: Any = None
        self._history: deque[UrState] = deque()
        self._latest: UrState | None = None
        self._fresh = threading.Condition()
        self._send_lock = threading.Lock()
        self._dashboard_lock = threading.Lock()
        self._sequence = 0
        self._last: tuple[int | None, float] = (None, 0.0)  # the last program's sequence number and when it went out
        self._host_held = False
        self._stop = threading.Event()
        self._reader: threading.Thread | None = None

    # -- the ports ---------------------------------------------------------------------

    def connect(self) -> None:
        """Open the dashboard, RTDE and the script port, and wait for the first state."""
        import dashboard_client
        import rtde_receive
        import script_client

        if self._receive is not None:
            self.status()
            return
        host = self.config.host
        try:
            self._dashboard = dashboard_client.DashboardClient(host, self.config.dashboard_port)
            self._dashboard.connect(2000)
        except RuntimeError as exc:
            self._dashboard = None
            raise UrLinkError(f"the UR controller's dashboard server at {host}:{self.config.dashboard_port}: {exc}") from exc
        try:
            self._receive = rtde_receive.RTDEReceiveInterface(host, -1.0, RTDE_VARIABLES)
        except RuntimeError as exc:
            self.close()
            raise UrLinkError(f"the UR controller's RTDE at {host}:30004: {exc}") from exc
        try:
            self._script = script_client.ScriptClient(host, 3, 15, self.config.script_port)
            self._script.connect()
        except RuntimeError as exc:
            self.close()
            raise UrLinkError(f"the UR controller's script port {host}:{self.config.script_port}: {exc}") from exc
        self._stop.clear()
        self._reader = threading.Thread(target=self._read_states, name="ur-rtde-reader", daemon=True)
        self._reader.start()
        self._state(newer_than_s=0.0)

    def close(self) -> None:
        self._stop.set()
        if self._reader is not None:
            self._reader.join()
            self._reader = None
        for client in (self._receive, self._script, self._dashboard):
            if client is not None:
                try:
                    client.disconnect()
                except RuntimeError:
                    pass
        self._receive = self._script = self._dashboard = None

    def _read_states(self) -> None:
        """Keep each new RTDE package (a new controller timestamp) with the host's time."""
        receive, last = self._receive, None
        while not self._stop.wait(POLL_S):
            if receive is None or not receive.isConnected():
                continue
            timestamp = receive.getTimestamp()
            if timestamp == last:
                continue
            last = timestamp
            state = UrState(
                received_s=time.monotonic(),
                timestamp_s=timestamp,
                q=receive.getActualQ(),
                tcp_pose=receive.getActualTCPPose(),
                tcp_speed=np.asarray(receive.getActualTCPSpeed(), dtype=float),
                robot_mode=receive.getRobotMode(),
                safety_mode=receive.getSafetyMode(),
                runtime_state=receive.getRuntimeState(),
                input_bits=receive.getActualDigitalInputBits(),
                output_bits=receive.getActualDigitalOutputBits(),
                done_register=receive.getOutputIntRegister(DONE_REGISTER),
            )
            with self._fresh:
                self._history.append(state)
                while self._history and self._history[0].received_s < state.received_s - HISTORY_S:
                    self._history.popleft()
                self._latest = state
                self._fresh.notify_all()

    def _state(self, newer_than_s: float | None = None, timeout_s: float = 2.0) -> UrState:
        """The latest state; with ``newer_than_s``, one that arrived after that host time."""
        deadline = time.monotonic() + timeout_s
        with self._fresh:
            while self._latest is None or (newer_than_s is not None and self._latest.received_s <= newer_than_s):
                if self._receive is None:
                    raise UrLinkError("the UR controller is not connected")
                remaining = deadline - time.monotonic()
                if remaining <= 0.0:
                    raise UrLinkError(f"no RTDE state from the UR controller at {self.config.host} for {timeout_s:g} s")
                self._fresh.wait(remaining)
            return self._latest

    def _dashboard_command(self, command: str) -> str:
        if self._dashboard is None:
            raise UrLinkError("the UR controller is not connected")
        with self._dashboard_lock:
            try:
                self._dashboard.send(command + "\n")
                return self._dashboard.receive().strip()
            except RuntimeError as exc:
                raise UrLinkError(f"the dashboard server at {self.config.host}: {command!r} failed: {exc}") from exc

    def _send(self, statements: list[str]) -> tuple[int, float]:
        """One program of ``statements``; its sequence number and the host time it went out."""
        if self._script is None:
            raise UrLinkError("the UR controller is not connected")
        with self._send_lock:
            self._sequence += 1
            sent_s = time.monotonic()
            if not self._script.sendScriptCommand(ur_script.program("vservo", statements, self._sequence)):
                raise UrLinkError(f"the script port {self.config.host}:{self.config.script_port} did not take the program")
            return self._sequence, sent_s

    # -- RobotBackend ------------------------------------------------------------------

    def status(self) -> RobotStatus:
        state = self._state()
        safety = state.safety_mode
        held = safety in HELD_SAFETY_MODES or self._host_held
        alarm = safety not in NORMAL_SAFETY_MODES and safety not in HELD_SAFETY_MODES
        detail = [SAFETY_MODES.get(safety, f"safety mode {safety}")] if safety not in NORMAL_SAFETY_MODES else []
        if self._host_held:
            detail.append("host hold (dashboard stop)")
        return RobotStatus(
            servo_on=state.robot_mode == ROBOT_MODE_RUNNING,
            running=state.runtime_state == RUNTIME_PLAYING,
            held=held,
            alarm=alarm,
            detail="; ".join(detail),
        )

    def read_pose(self) -> Matrix:
        return self.bMu @ self._state().uMe

    def pose_at(self, t_s: float) -> Matrix:
        """The TCP pose at host time t_s, between the two RTDE packages around it (the
        newest if t_s is later, the oldest kept if earlier)."""
        with self._fresh:
            history = self._history
            if not history:
                before = after = None
            else:
                k = bisect.bisect_left(history, t_s, key=lambda state: state.received_s)
                before, after = history[max(k - 1, 0)], history[min(k, len(history) - 1)]
        if before is None or after is None:
            return self.read_pose()
        if before is after:  # t_s before the oldest package kept, or after the newest
            return self.bMu @ before.uMe
        return self.bMu @ interpolate(before.uMe, after.uMe, (t_s - before.received_s) / (after.received_s - before.received_s))

    def servo(self, on: bool) -> None:
        if not on:
            self._dashboard_command("power off")
            return
        self._dashboard_command("power on")
        self._dashboard_command("brake release")
        deadline = time.monotonic() + 10.0
        while self._state(newer_than_s=time.monotonic()).robot_mode != ROBOT_MODE_RUNNING:
            if time.monotonic() > deadline:
                raise RobotNotReady(f"the UR arm did not power up and release its brakes: {self.status().describe()}")

    def hold(self, on: bool) -> None:
        """On: the dashboard's stop (the program aborted, the arm stopped); off: moves may go again."""
        if on:
            self._host_held = True
            self._dashboard_command("stop")
        else:
            self._host_held = False

    def reset_alarms(self) -> None:
        """Unlock a protective stop and close the safety pop-up (an emergency stop is released on the arm)."""
        self._dashboard_command("unlock protective stop")
        self._dashboard_command("close safety popup")

    def _refuse_unless_ready(self) -> None:
        status = self.status()
        if not status.ready:
            raise RobotNotReady(f"the UR arm cannot move: {status.describe()}")

    def move_to(self, bMe_target: Matrix, speed_m_s: float) -> None:
        self._refuse_unless_ready()
        self._last = self._send([ur_script.movel(self.uMb @ bMe_target, self.acceleration_m_s2, speed_m_s)])

    def read_joints(self) -> Matrix:
        """The joints RTDE reports (actual_q, rad): the arm model's joints, example-robot-data's
        UR joint zeros being the real arm's (and the UPJ's, the model's, when a UR plays it)."""
        return np.array(self._state().q, dtype=float)

    def move_joints(self, line: JointLine, speed_m_s: float) -> None:
        """One movej to line.q_to, timed so that the flange keeps within speed_m_s along the line.

        On the line q(s) = q_from + s (q_to - q_from) the flange moves at |dp/ds| ds/dt, at
        most D ds/dt (D = line.tcp_peak_m, the peak of |dp/ds| over the checked samples,
        at least the path's length). With ds/dt within speed / D and
        d2s/dt2 within acceleration / D (the [ur] acceleration) the flange's speed stays
        within speed_m_s and its acceleration along the path within the movel's: s then runs
        the trapezoid of a movel D long at the move's speed and acceleration, as long as
        that movel takes. The leading joint (L = max |q_to - q_from|) runs it at
        v = speed L / D and a = acceleration L / D, v at most JOINT_SPEED_RAD_S (a with it,
        the ramps as long as the flange's). No time t is sent: with t the manual says the
        time has priority but not how the controller then shapes the ramps, and a longer
        ramp would raise the peak speed; a and v alone are the trapezoid it documents.
        """
        self._refuse_unless_ready()
        q_to = np.asarray(line.q_to, dtype=float)
        turn = float(np.max(np.abs(q_to - np.asarray(line.q_from, dtype=float))))
        speed = JOINT_SPEED_RAD_S if line.tcp_peak_m <= 0.0 else min(speed_m_s * turn / line.tcp_peak_m, JOINT_SPEED_RAD_S)
        speed = max(speed, np.finfo(float).tiny)  # no turn: a move of no length, at any speed
        acceleration = speed * self.acceleration_m_s2 / speed_m_s
        self._last = self._send([ur_script.movej(q_to.tolist(), acceleration, speed)])

    def move_by(self, bMe_increment: Matrix, speed_m_s: float) -> None:
        self.move_to(apply_increment(self.read_pose(), bMe_increment), speed_m_s)

    def move_timed(self, bMe_target: Matrix, duration_s: float) -> None:
        """The twist that lands on bMe_target in duration_s, held that long, then a stop."""
        from pinocchio import SE3, log6

        self._refuse_unless_ready()
        uMe = self._state().uMe
        eVe = log6(SE3(inverse(self.bMu @ uMe) @ np.asarray(bMe_target, dtype=float))).vector / duration_s
        acceleration = self.acceleration_m_s2
        self._last = self._send(
            [ur_script.speedl(self._in_base(uMe, eVe), acceleration, duration_s), ur_script.stopl(acceleration)]
        )

    def stream_twist(self, eVe: Matrix, hold_s: float) -> None:
        """Move the flange at the body twist eVe (v, w in E) from now on, without waiting:
        the controller holds it for hold_s at most, then stops, unless the next comes first."""
        state = self._state()
        if self._host_held or state.safety_mode not in NORMAL_SAFETY_MODES or state.robot_mode != ROBOT_MODE_RUNNING:
            self._refuse_unless_ready()
        self._last = self._send([ur_script.speedl(self._in_base(state.uMe, eVe), self.acceleration_m_s2, hold_s)])

    def stop_motion(self) -> None:
        """Decelerate to a standstill (stopl) and wait for it."""
        self._last = self._send([ur_script.stopl(self.acceleration_m_s2)])
        self.wait_motion(timeout_s=5.0)

    @staticmethod
    def _in_base(uMe: Matrix, eVe: Matrix) -> list[float]:
        """The flange's body twist as speedl takes it: v and w in the controller's base frame u
        (the TCP's origin moving), the TCP at uMe."""
        R = np.asarray(uMe, dtype=float)[:3, :3]
        eVe = np.asarray(eVe, dtype=float)
        return [*(R @ eVe[:3]), *(R @ eVe[3:])]

    def wait_motion(self, timeout_s: float | None = None) -> bool:
        """Until the last program has run to its end and the arm stands: True; False when it
        stopped short (a hold, a protective stop, an alarm, another program in its place)."""
        sequence, sent_s = self._last
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        seen_running = False
        while True:
            state = self._state(newer_than_s=time.monotonic())
            if sequence is None or state.done_register == sequence:
                if np.all(np.abs(state.tcp_speed) < STANDING_SPEED):
                    return True
            elif state.runtime_state == RUNTIME_PLAYING:
                seen_running = True
            elif seen_running or time.monotonic() - sent_s > 2.0:
                return False  # the program ended without its last statement, or never ran
            if self._host_held or state.safety_mode not in NORMAL_SAFETY_MODES:
                return False
            if deadline is not None and time.monotonic() > deadline:
                self.hold(True)
                raise RobotError(f"the motion has not ended after {timeout_s:g} s: the robot is held")

    # -- I/O ---------------------------------------------------------------------------

    def set_output(self, bank: DigitalOutputs, n: int, on: bool) -> None:
        """Switch a digital output; returns when the controller has done it."""
        self._last = self._send([ur_script.set_digital_out(bank, n, on)])
        if not self.wait_motion(timeout_s=5.0):
            raise RobotError(f"the UR controller did not switch {bank} digital output {n}: {self.status().describe()}")

    def read_input(self, bank: DigitalOutputs, n: int) -> bool:
        state = self._state(newer_than_s=time.monotonic())
        return bool(state.input_bits >> (ur_script.INPUT_BIT_OFFSET[bank] + n) & 1)

    # -- clocks ------------------------------------------------------------------------

    def clock_s(self) -> float:
        return time.monotonic()

    def cell_clock_s(self) -> float:
        """The controller's own clock (RTDE's timestamp), on which an emulator's speed-up is real time."""
        return self._state().timestamp_s

    def dwell(self, seconds: float) -> None:
        if seconds > 0.0:
            time.sleep(seconds / self.config.time_scale)
