"""A controller of the simulated cell with its own store, closed with it."""

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from vservo.core.cell.config import CellConfig
from vservo.core.production.cell_controller import CellController
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import Store


@contextmanager
def simulated_controller(config: CellConfig, data: Path, seed: int = 3) -> Iterator[CellController]:
    """A CellController of ``config``'s simulated cell (its rig and the controller seeded alike),
    its SQLite store in ``data``; both closed at the end."""
    store = Store(data)
    controller = CellController(simulated_rig(config, seed=seed), store, seed=seed)
    try:
        yield controller
    finally:
        controller.close()
        store.close()
