"""The two commands a robot backend carries out: hold a twist, or move to a target."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vservo.core.geometry.spatial import Matrix, exp_twist


@dataclass(frozen=True)
class VelocityCommand:
    """Hold the flange twist eVe (v, w in E, m/s and rad/s) for dt_s seconds."""

    eVe: Matrix
    dt_s: float

    def target(self, bMe: Matrix) -> Matrix:
        """Where the flange lands from bMe: a constant body twist held for dt_s, exactly."""
        return bMe @ exp_twist(np.asarray(self.eVe, dtype=float) * self.dt_s)


@dataclass(frozen=True)
class PositionCommand:
    """Move the flange linearly to bMe_target; the next command waits for period_s."""

    bMe_target: Matrix
    speed_m_s: float
    period_s: float

    def target(self, bMe: Matrix) -> Matrix:
        """Where the flange lands: the target, wherever it starts."""
        return self.bMe_target


@dataclass(frozen=True)
class StreamedTwist:
    """Move the flange at the twist eVe (v, w in E) from now on, without waiting for it: the
    controller holds it for hold_s at most and stops the arm unless the next twist comes first."""

    eVe: Matrix
    hold_s: float

    def target(self, bMe: Matrix) -> Matrix:
        """Where the flange would be if no twist came after this one: held hold_s from bMe."""
        return bMe @ exp_twist(np.asarray(self.eVe, dtype=float) * self.hold_s)


RobotCommand = VelocityCommand | PositionCommand | StreamedTwist
