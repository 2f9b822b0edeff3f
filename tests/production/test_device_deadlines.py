"""Every device read has a deadline (docs/reliability.md): a camera whose connection stays
open but sends nothing faults the run within max(2 s, 2 x the watchdog), the robot held,
and Reset works at once after. The virtual cell in its own process, its camera stream
reached through a loopback relay that can go silent as a stalled camera does
(tests/camera_relays.py)."""

from __future__ import annotations

import time

import pytest

from tests.camera_relays import StallingRelay, camera_through
from tests.polling import wait_until
from tests.virtual_cell_process import VirtualCellProcess
from vservo.core.cell.config import load_cell
from vservo.core.production.assembly import Outcome, Phase
from vservo.core.production.cell_controller import CellController
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.storage import Store

WATCHDOG_S = 1.0
pytestmark = pytest.mark.slow  # a virtual cell and two runs on it


@pytest.fixture
def stalling_cell(tmp_path):
    """The virtual cell, and a copy of its cell file whose camera is reached through a
    StallingRelay and whose watchdog is WATCHDOG_S."""
    cell = VirtualCellProcess("--seed", "3")
    cell_file = tmp_path / "cell.toml"
    relay = camera_through(cell, StallingRelay, cell_file, safety={"watchdog_s": WATCHDOG_S})
    yield cell_file, relay
    relay.close()
    assert cell.stop() == 0


def test_a_stalled_camera_faults_the_run_within_the_deadline_and_reset_works_at_once(stalling_cell, tmp_path):
    cell_file, relay = stalling_cell
    store = Store(tmp_path / "data")
    controller = CellController(build_rig(load_cell(cell_file), 3), store, seed=3)
    try:
        controller.present_part()
        controller.start("demo")
        wait_until(lambda: controller.state.run.iteration >= 2, "two servo cycles", timeout_s=120)
        relay.stall()
        stalled_at = time.monotonic()
        controller.wait(60)
        faulted_after_s = time.monotonic() - stalled_at
        outcome = controller.last_outcome
        assert outcome.outcome is Outcome.FAULT and "stalled" in outcome.reason, outcome.reason
        # A deadline, not a speed: the product promises the fault within this bound.
        assert faulted_after_s <= max(2.0, 2 * WATCHDOG_S), faulted_after_s
        assert controller.rig.robot.status().held
        relay.resume()
        controller.reset()  # at once: the run is over, and the camera opens anew
        assert controller.state.phase == Phase.IDLE.value
        controller.present_part()
        controller.start("demo")
        controller.wait(300)
        assert controller.last_outcome.outcome is Outcome.PLACED, controller.last_outcome.reason
    finally:
        controller.close()
        store.close()
