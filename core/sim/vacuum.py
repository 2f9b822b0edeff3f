"""The simulated cell's vacuum cup."""

from __future__ import annotations

from vservo.core.sim.plant import SimulatedCell


class SimulatedVacuum:
    """The simulated cell's cup: it grips only where the true cup meets the true part."""

    def __init__(self, cell: SimulatedCell) -> None:
        self.cell = cell

    def set_vacuum(self, on: bool) -> None:
        self.cell.vacuum(on)

    def holding(self) -> bool:
        return self.cell.holding_part
