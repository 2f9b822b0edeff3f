"""The vacuum cup on the JRC's I/O: suction through a network input, the grip from the pressure switch.

The host cannot switch a general output of the JRC; it writes a network input, and a
ladder line set up once on the pendant copies that input to the output driving the
valve (docs/robot-link.md, I/O). The cup's pressure switch is wired
to a general input that the host reads. Both addresses come from the cell file's
[vacuum] (suction_output, grip_input); the IOREAD / IOWRITE forms are inferred.
"""

from __future__ import annotations

from vservo.core.robot.jrc import JrcBackend, io_byte


class JrcVacuum:
    """A VacuumGripper over a JrcBackend's I/O signals."""

    def __init__(self, jrc: JrcBackend, suction_output: int, grip_input: int) -> None:
        for address in (suction_output, grip_input):
            io_byte(address)  # a bad address fails here, not in the middle of a pick
        self.jrc, self.suction_output, self.grip_input = jrc, suction_output, grip_input

    def set_vacuum(self, on: bool) -> None:
        self.jrc.write_signal(self.suction_output, on)

    def holding(self) -> bool:
        """The pressure switch: True when the cup holds a part."""
        return self.jrc.read_signal(self.grip_input)
