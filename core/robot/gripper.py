"""The vacuum cup: suction on and off, and the vacuum sensor that says whether it holds.

On the thesis's cell a vacuum pump picks the plastic part (section 5.3). A gripper is a
separate device from the arm's controller here: the simulator models the cup on the
true flange; a real cell wires the pump and its pressure switch to I/O that a gripper
backend of its own drives.
"""

from __future__ import annotations

from typing import Protocol

from core.simulator import SimulatedCell


class VacuumGripper(Protocol):
    def set_vacuum(self, on: bool) -> None: ...
    def holding(self) -> bool:
        """The vacuum sensor: True when the cup holds a part."""
        ...


class SimulatedVacuum:
    """The simulated cell's cup: it grips only where the true cup meets the true part."""

    def __init__(self, cell: SimulatedCell) -> None:
        self.cell = cell

    def set_vacuum(self, on: bool) -> None:
        self.cell.vacuum(on)

    def holding(self) -> bool:
        return self.cell.holding_part
