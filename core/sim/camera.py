"""The simulated cell's camera: 8-bit frames of the TRUE view, as any camera source.

It is a sensor of the plant: it renders with the true intrinsics and distortion from the
true camera pose, the laser spot where the true beam lands, and hands out only the
image, so the vision that reads it works exactly as on a real camera.
"""

from __future__ import annotations

import numpy as np

from vservo.core.perception.camera_source import BaseSource, Frame, Size
from vservo.core.sim.plant import SimulatedCell
from vservo.core.sim.render import SceneRenderer
from vservo.core.sim.render_settings import RenderSettings
from vservo.core.sim.sensor import FrameFault


class SimulatedCamera(BaseSource):
    """Frames of ``cell`` rendered with ``settings``; seeded from the cell's seed by default."""

    def __init__(self, cell: SimulatedCell, settings: RenderSettings = RenderSettings(), seed: int | None = None) -> None:
        self.cell = cell
        self.renderer = SceneRenderer(cell.truth.model.camera, settings)
        self.rng = np.random.default_rng(seed if seed is not None else cell.rng.integers(2**31))
        self._index = 0

    @property
    def image_size(self) -> Size:
        return self.cell.truth.model.camera.image_size

    def read(self, fault: FrameFault | None = None) -> Frame:
        """The current view; ``fault`` injects a dropped or smeared frame."""
        self._check_open()
        bMc, spot_b = self.cell.ground_truth_view()
        image = self.renderer.render(self.cell.state.scene, bMc, spot_b, self.rng, fault=fault)
        frame = Frame(image, self.cell.state.time_s, self._index)
        self._index += 1
        return frame

    def read_after(self, t_s: float) -> Frame:
        """The current view: rendered at the moment of reading, it is exposed after any
        motion that has ended, whichever clock ``t_s`` is on (the plant's for the
        simulated robot, the host's for the JRC link to the emulator)."""
        return self.read()
