"""The vacuum cup: suction on and off, and the vacuum sensor that says whether it holds.

On the thesis's cell a vacuum pump picks the plastic part (section 5.3). The simulator
models the cup on the true flange; a real cell wires the valve and its pressure switch
to the JRC's I/O (core/robot/jrc_vacuum.py); a cell without a cup has ``NoVacuum``.
"""

from __future__ import annotations

from typing import Protocol

from vservo.core.robot.backend import RobotError


class VacuumGripper(Protocol):
    def set_vacuum(self, on: bool) -> None: ...
    def holding(self) -> bool:
        """The vacuum sensor: True when the cup holds a part."""
        ...


class NoVacuum:
    """A cell without a vacuum cup ([vacuum] device = "none"): it can jog, teach views and
    servo, and refuses to pick."""

    def set_vacuum(self, on: bool) -> None:
        if on:
            raise RobotError('this cell has no vacuum cup ([vacuum] device = "none"): it cannot pick a part')

    def holding(self) -> bool:
        return False
