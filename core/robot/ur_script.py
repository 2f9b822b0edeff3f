"""The URScript a Universal Robots controller is sent, and the poses it speaks in.

A UR controller runs URScript programs; a host sends one as text to the controller's
secondary interface (TCP port 30002), and a new program replaces the one running. vservo
sends a small set of statements (the URScript manual's names and arguments):

- ``movel(p[x, y, z, rx, ry, rz], a=..., v=...)``: a linear move of the TCP to a pose;
- ``movej([q1, ..., q6], a=..., v=..., t=...)``: every joint on the straight line in joint
  space to the joints q (rad), on a trapezoid of the leading joint's acceleration a
  (rad/s^2) and speed v (rad/s), or lasting t seconds when t is not 0 (the time comes
  first: "the time setting has priority over speed and acceleration");
- ``speedl([vx, vy, vz, wx, wy, wz], a, t)``: the TCP at a twist in the base frame,
  reached at acceleration a, for at most t seconds, after which the controller stops the
  arm (a twist streamed every frame that stops coming stops the arm by itself);
- ``stopl(a)``: decelerate to a standstill;
- ``set_standard_digital_out(n, b)``, ``set_tool_digital_out(n, b)``: a digital output;
- ``write_output_integer_register(n, v)``: an output register read back over RTDE; a
  program's last statement writes its sequence number there, the sign that it ran to its end.

A pose ``p[x, y, z, rx, ry, rz]`` is in metres, its rotation a rotation vector (axis times
angle, rad) in the controller's base frame u (``Base`` on the pendant); with a zero TCP
offset (set it so on the pendant) the controller's TCP is vservo's flange E, its pose uMe.
The backend (core/robot/ur.py) turns vservo's base-frame poses bMe into uMe and back.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import StrEnum

import numpy as np

from vservo.core.geometry.spatial import Matrix, exp_twist, theta_u, transform

# The output integer register a program's last statement writes its sequence number to.
DONE_REGISTER = 12  # ur-rtde reads 12..19 of the lower range (it keeps 0..11 for its own control script)


class DigitalOutputs(StrEnum):
    """The controller's banks of digital outputs (and the inputs beside them)."""

    STANDARD = "standard"  # the control box's DO0..DO7, DI0..DI7
    TOOL = "tool"  # the tool flange's connector: TO0..TO1, TI0..TI1


# How many outputs (and inputs) a bank has, and where its inputs sit in RTDE's
# actual_digital_input_bits (the standard ones from bit 0, the tool's from bit 16).
BANK_SIZE = {DigitalOutputs.STANDARD: 8, DigitalOutputs.TOOL: 2}
INPUT_BIT_OFFSET = {DigitalOutputs.STANDARD: 0, DigitalOutputs.TOOL: 16}
OUTPUT_BIT_OFFSET = {DigitalOutputs.STANDARD: 0, DigitalOutputs.TOOL: 16}


def ur_pose(uMe: Matrix) -> list[float]:
    """[x, y, z, rx, ry, rz] of a pose: metres and a rotation vector (rad)."""
    uMe = np.asarray(uMe, dtype=float)
    return [*map(float, uMe[:3, 3]), *map(float, theta_u(uMe[:3, :3]))]


def pose_from_ur(values: Sequence[float]) -> Matrix:
    """The pose of [x, y, z, rx, ry, rz] (metres, rotation vector)."""
    pose = np.asarray(values, dtype=float)
    if pose.shape != (6,) or not np.all(np.isfinite(pose)):
        raise ValueError(f"a UR pose is 6 finite numbers [x, y, z, rx, ry, rz], got {pose.tolist()}")
    return transform(exp_twist(np.r_[0.0, 0.0, 0.0, pose[3:]])[:3, :3], pose[:3])


def _numbers(values: Sequence[float]) -> str:
    return ", ".join(f"{float(v):.7g}" for v in values)


def movel(uMe: Matrix, acceleration_m_s2: float, speed_m_s: float) -> str:
    return f"movel(p[{_numbers(ur_pose(uMe))}], a={acceleration_m_s2:.6g}, v={speed_m_s:.6g})"


def movej(q: Sequence[float], acceleration_rad_s2: float, speed_rad_s: float, duration_s: float = 0.0) -> str:
    """Every joint on the straight line in joint space to q (rad, the controller's joints),
    the leading joint at acceleration_rad_s2 and speed_rad_s, the move lasting duration_s
    (0: as long as that trapezoid takes)."""
    return f"movej([{_numbers(q)}], a={acceleration_rad_s2:.6g}, v={speed_rad_s:.6g}, t={duration_s:.6g})"


def speedl(uVe: Sequence[float], acceleration_m_s2: float, hold_s: float) -> str:
    """The TCP at the twist uVe (v, w in the controller's base frame) for at most hold_s."""
    return f"speedl([{_numbers(uVe)}], {acceleration_m_s2:.6g}, {hold_s:.6g})"


def stopl(acceleration_m_s2: float) -> str:
    return f"stopl({acceleration_m_s2:.6g})"


def set_digital_out(bank: DigitalOutputs, n: int, on: bool) -> str:
    return f"set_{bank}_digital_out({n}, {'True' if on else 'False'})"


def program(name: str, statements: Sequence[str], sequence: int) -> str:
    """One program: the statements, then its sequence number written to DONE_REGISTER."""
    body = [*statements, f"write_output_integer_register({DONE_REGISTER}, {sequence})"]
    return "\n".join([f"def {name}():", *(f"  {line}" for line in body), "end", ""])
