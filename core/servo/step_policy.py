"""Step policies: how a control law's end-effector twist becomes one robot command.

A velocity-controlled robot integrates the twist over the control period. The JRC of
the thesis cannot: it takes one Cartesian target at a time and ignores a new one until
the previous is reached (section 5.3). The thesis therefore divided "the calculated value
of each iteration" by a constant factor (50) and sampled every 2 s: with all gains 1
the control law's output is the whole estimated correction, and each step moves a
fiftieth of it. The fast policy moves the whole correction at once, within a step limit
(docs/robot-link.md, "Servo steps").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from vservo.core.cell.config import MotionConfig, StepPolicyKind
from vservo.core.geometry.spatial import Matrix, exp_twist
from vservo.core.robot.commands import PositionCommand, RobotCommand, StreamedTwist, VelocityCommand


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


@dataclass(frozen=True)
class LargestSafeStep:
    """Fewer, larger JRC steps: target = bMe exp(s eVe), s = min(1, max_step_m / |v|, max_step_rad / |w|).

    With all gains 1, holding the law's twist for 1 s is the whole correction its
    interaction matrix predicts (eq. 4-14), so s = 1 is one look-and-move step to the
    goal as far as the linearisation holds. Far from the goal it does not hold: there the
    twist is scaled down as a whole (its direction kept) to the step limits, so the
    camera approaches in long straight steps and a wrong prediction costs one bounded
    step, seen and corrected by the next look. The steps shrink with the error; the fine
    ones come only at the end. No sampling period: the JRC takes the next target as soon
    as the last is reached, and the next look waits for that anyway.
    """

    max_step_m: float
    max_step_rad: float
    speed_m_s: float

    def command(self, bMe: Matrix, eVe: Matrix) -> PositionCommand:
        step = np.asarray(eVe, dtype=float)
        # |translation of exp(step)| <= |v|: bounding v and w bounds the move the safety layer checks.
        sizes = (float(np.linalg.norm(step[:3])), float(np.linalg.norm(step[3:])))
        scale = min([1.0] + [limit / size for limit, size in zip((self.max_step_m, self.max_step_rad), sizes) if size > 0.0])
        return PositionCommand(bMe @ exp_twist(scale * step), self.speed_m_s, 0.0)


@dataclass(frozen=True)
class StreamedVelocity:
    """A robot under real-time velocity control, servoed at the camera's rate: each frame's
    twist, times ``gain``, is streamed at once and held until the next (``hold_s`` at
    most), scaled down as a whole (its direction kept) to ``max_speed_m_s`` and
    ``max_rotation_rad_s``. With the laws' gain 1 the twist is the whole correction per
    second (eq. 4-14), so ``gain`` is the rate (1/s) at which the error falls: far above
    1/latency the loop would oscillate on the camera's delay."""

    hold_s: float
    gain: float
    max_speed_m_s: float
    max_rotation_rad_s: float

    def command(self, bMe: Matrix, eVe: Matrix) -> StreamedTwist:
        twist = self.gain * np.asarray(eVe, dtype=float)
        sizes = (float(np.linalg.norm(twist[:3])), float(np.linalg.norm(twist[3:])))
        limits = (self.max_speed_m_s, self.max_rotation_rad_s)
        scale = min([1.0] + [limit / size for limit, size in zip(limits, sizes) if size > 0.0])
        return StreamedTwist(scale * twist, self.hold_s)


PositionStepPolicy = DividedPositionStep | LargestSafeStep
"""The policies a JRC can be servoed with: one Cartesian target at a time."""


def step_policy_from_config(motion: MotionConfig) -> StepPolicy:
    if motion.mode == "streaming":
        return StreamedVelocity(
            motion.stream_hold_s, motion.stream_gain, motion.stream_max_speed_m_s, motion.stream_max_rotation_rad_s
        )
    if motion.mode == "velocity":
        return IntegratedVelocity(motion.dt_s)
    if motion.policy is StepPolicyKind.FAST:
        fast = motion.fast
        return LargestSafeStep(fast.max_step_m, fast.max_step_rad, fast.speed_m_s)
    return DividedPositionStep(motion.divide_factor, motion.sampling_period_s, motion.speed_m_s)
