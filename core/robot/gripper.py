"""The vacuum cup: suction on and off, and the vacuum sensor that says whether it holds.

On the thesis's cell a vacuum pump picks the plastic part (section 5.3). A gripper is a
separate device from the arm's controller here: the simulator models the cup on the
true flange; a real cell wires the pump and its pressure switch to I/O that a gripper
backend of its own drives.
"""

from __future__ import annotations

from typing import Protocol


class VacuumGripper(Protocol):
    def set_vacuum(self, on: bool) -> None: ...
    def holding(self) -> bool:
        """The vacuum sensor: True when the cup holds a part."""
        ...


