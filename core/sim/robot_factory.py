"""The robot a cell file asks for: [robot] backend, behind the [safety] limits."""

from __future__ import annotations

from vservo.core.cell.config import CellConfig
from vservo.core.robot.jrc import JrcBackend
from vservo.core.robot.safety import SafetyLayer
from vservo.core.sim.backend import SimulatedBackend
from vservo.core.sim.plant import SimulatedCell


def robot_from_config(config: CellConfig, cell: SimulatedCell | None = None, port: str | None = None) -> SafetyLayer:
    """The cell's robot behind its safety layer, not yet connected.

    backend = "sim" drives ``cell`` (required); "jrc" the JRC on ``port``, by
    default the cell file's [jrc] port.
    """
    if config.robot_backend == "sim":
        if cell is None:
            raise ValueError(f"{config.source}: robot.backend = 'sim' needs the simulated cell to drive")
        return SafetyLayer.from_config(SimulatedBackend(cell), config)
    return SafetyLayer.from_config(JrcBackend(config.jrc, port), config)
