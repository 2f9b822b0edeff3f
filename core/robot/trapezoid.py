"""The trapezoidal speed profile a Universal Robots controller runs its moves on.

A ``movel`` or ``movej`` accelerates at a constant rate to its top speed, holds it, and
decelerates at the same rate to stop on its target; a move too short to reach the top speed
is a triangle (the URScript manual: "the speed and acceleration parameters control the
trapezoid speed profile of the move"). The length is the TCP's path (m) for a movel, the
leading joint's turn (rad) for a movej; speed and acceleration are in the same unit per s
and s^2.
"""

from __future__ import annotations

import numpy as np


def duration(length: float, speed: float, acceleration: float) -> float:
    """How long the trapezoid of ``length`` at ``speed`` and ``acceleration`` takes (s)."""
    if length <= 0.0:
        return 0.0
    ramp = speed / acceleration
    if acceleration * ramp * ramp >= length:  # a triangle: the top speed is never reached
        return 2.0 * np.sqrt(length / acceleration)
    return length / speed + ramp


def distance(t: float, length: float, speed: float, acceleration: float) -> float:
    """How far along ``length`` the trapezoid is at time t from its start."""
    total = duration(length, speed, acceleration)
    top = min(speed, np.sqrt(length * acceleration))
    ramp = top / acceleration
    if t <= ramp:
        return 0.5 * acceleration * t * t
    if t >= total - ramp:
        left = max(total - t, 0.0)
        return length - 0.5 * acceleration * left * left
    return 0.5 * acceleration * ramp * ramp + top * (t - ramp)
