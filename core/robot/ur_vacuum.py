"""The vacuum cup on a Universal Robots controller's digital I/O: the valve on an output,
the pressure switch on an input, both of the control box's standard bank or the tool
flange's ([vacuum] device = "ur_io", io, suction_output, grip_input)."""

from __future__ import annotations

from vservo.core.robot.ur import UrBackend
from vservo.core.robot.ur_script import DigitalOutputs


class UrVacuum:
    """A VacuumGripper on a UrBackend's digital signals."""

    def __init__(self, ur: UrBackend, bank: DigitalOutputs, suction_output: int, grip_input: int) -> None:
        self.ur, self.bank, self.suction_output, self.grip_input = ur, bank, suction_output, grip_input

    def set_vacuum(self, on: bool) -> None:
        self.ur.set_output(self.bank, self.suction_output, on)

    def holding(self) -> bool:
        """The pressure switch: True when the cup holds a part."""
        return self.ur.read_input(self.bank, self.grip_input)
