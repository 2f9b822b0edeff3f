"""Step policies: how a control law's end-effector twist becomes one robot command.

A velocity-controlled robot integrates the twist over the control period. The JRC of
the thesis cannot: it takes one Cartesian target at a time and ignores a new one until
the previous is reached (section 5.3). The thesis therefore divided "the calculated value
of each iteration" by a constant factor (50) and sampled every 2 s: with all gains 1
the control law's output is the whole estimated correction, and each step moves a
fiftieth of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from vservo.core.cell.config import MotionConfig
from vservo.core.geometry.spatial import Matrix, exp_twist
from vservo.core.robot.commands import PositionCommand, RobotCommand, VelocityCommand


class StepPolicy(Protocol):
    def command(self, bMe: Matrix, eVe: Matrix) -> RobotCommand:
        """The command that carries out one control step from the flange pose bMe."""
        ...


@dataclass(frozen=True)
class IntegratedVelocity:
    """A real-time robot: the twist is held for one control period dt_s."""

    dt_s: float

    def command(self, bMe: Matrix, eVe: Matrix) -> VelocityCommand:
        return VelocityCommand(np.asarray(eVe, dtype=float), self.dt_s)


@dataclass(frozen=True)
class DividedPositionStep:
    """The JRC style: target = bMe exp(eVe / divide_factor), one target per sampling period."""

    divide_factor: float = 50.0
    sampling_period_s: float = 2.0
    speed_m_s: float = 0.05

    def command(self, bMe: Matrix, eVe: Matrix) -> PositionCommand:
        step = np.asarray(eVe, dtype=float) / self.divide_factor
        return PositionCommand(bMe @ exp_twist(step), self.speed_m_s, self.sampling_period_s)


def step_policy_from_config(motion: MotionConfig) -> StepPolicy:
    if motion.mode == "velocity":
        return IntegratedVelocity(motion.dt_s)
    return DividedPositionStep(motion.divide_factor, motion.sampling_period_s, motion.speed_m_s)
