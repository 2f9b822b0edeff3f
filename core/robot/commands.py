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


RobotCommand = VelocityCommand | PositionCommand
