"""Frames later than the cell file says (docs/vision.md, "No stale frames"): a host too busy
to read its camera leaves frames waiting in the stream's buffers, and the first frame it
reads after a move can show the arm before the move, stamped as if it were fresh. The
check view then sees the part in the wrong place; a miss stops the line, so it is called
only when a second look, a second later, agrees.

The virtual cell in its own process; its camera reached through a loopback relay that
starts holding every byte half a second as the run goes to its check pose (the cell file
bounds the latency at 0.1 s), so the check view's first frame is one from before that move.
"""

from __future__ import annotations

import logging

import pytest

from tests.camera_relays import DelayingRelay, camera_through
from tests.virtual_cell_process import VirtualCellProcess
from vservo.core.cell.config import load_cell
from vservo.core.production.assembly import Outcome
from vservo.core.production.cell_controller import CellController
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.storage import Store

LATE_S = 0.5  # five times the cell file's exposure_latency_s, half the confirming look's wait
pytestmark = pytest.mark.slow  # a virtual cell and a run on it


@pytest.fixture
def late_cell(tmp_path):
    """The virtual cell, and a copy of its cell file whose camera is reached through a DelayingRelay."""
    cell = VirtualCellProcess("--seed", "3")
    cell_file = tmp_path / "cell.toml"
    relay = camera_through(cell, DelayingRelay, cell_file)
    assert load_cell(cell_file).camera_source.exposure_latency_s < LATE_S
    yield cell, cell_file, relay
    relay.close()
    assert cell.stop() == 0


def test_frames_late_at_the_check_view_are_not_called_a_miss_before_a_second_look(late_cell, tmp_path, caplog):
    cell, cell_file, relay = late_cell
    store = Store(tmp_path / "data")
    controller = CellController(build_rig(load_cell(cell_file), 3), store, seed=3)

    def fall_behind_at_the_check_pose(state) -> None:
        if "from the check pose" in state.detail:
            relay.delay_s = LATE_S

    controller.state_subscribers.append(fall_behind_at_the_check_pose)
    try:
        controller.present_part()
        with caplog.at_level(logging.INFO, logger="vservo.assembly"):
            controller.start("demo")
            controller.wait(300)
        outcome = controller.last_outcome
        released = cell.next_event()
    finally:
        controller.close()
        store.close()
    assert relay.delay_s == LATE_S, "the run never reached its check pose"
    # The first look saw the arm before its move to the check pose ...
    assert any("looking again" in record.getMessage() for record in caplog.records), outcome.reason
    # ... and the second, on a frame exposed after it, judged the part where the gauge has it.
    assert released["event"] == "released" and released["inside"], released
    assert outcome.outcome is Outcome.PLACED, outcome.reason
    assert outcome.placement_error_mm is not None and outcome.placement_error_mm < 0.3, outcome
