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
import queue
import socket
import threading
import time
import tomllib
from pathlib import Path

import pytest

from tests.virtual_cell_process import VirtualCellProcess
from vservo.core.cell.cell_file import dumps_cell
from vservo.core.cell.config import load_cell
from vservo.core.production.assembly import Outcome
from vservo.core.production.cell_controller import CellController
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.storage import Store

LATE_S = 0.5  # five times the cell file's exposure_latency_s, half the confirming look's wait
pytestmark = pytest.mark.slow  # a virtual cell and a run on it


class DelayingRelay:
    """A TCP relay on loopback that hands what the server sends on ``delay_s`` after it came
    (none at first): a stream as a reader that fell behind sees it."""

    def __init__(self, upstream: tuple[str, int]) -> None:
        self.upstream = upstream
        self.delay_s = 0.0
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.sockets: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def close(self) -> None:
        self.listener.close()
        for sock in self.sockets:
            sock.close()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(self.upstream)
            self.sockets += [client, server]
            held: queue.Queue[tuple[float, bytes]] = queue.Queue()
            threading.Thread(target=self._pump, args=(client, server, None), daemon=True).start()
            threading.Thread(target=self._pump, args=(server, None, held), daemon=True).start()
            threading.Thread(target=self._hand_on, args=(held, client), daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket | None, held: queue.Queue | None) -> None:
        """Forward at once (the requests), or queue each chunk with when it is due (the frames)."""
        try:
            while data := source.recv(65536):
                if held is not None:
                    held.put((time.monotonic() + self.delay_s, data))
                elif sink is not None:
                    sink.sendall(data)
        except OSError:
            pass

    def _hand_on(self, held: queue.Queue, sink: socket.socket) -> None:
        try:
            while True:
                due_s, data = held.get()
                time.sleep(max(0.0, due_s - time.monotonic()))
                sink.sendall(data)
        except OSError:
            pass


@pytest.fixture
def late_cell(tmp_path):
    """The virtual cell, and a copy of its cell file whose camera is reached through a DelayingRelay."""
    cell = VirtualCellProcess("--seed", "3")
    camera_url = cell.addresses["camera_url"]
    host_port = camera_url.split("//")[1].split("/")[0]
    host, port = host_port.rsplit(":", 1)
    relay = DelayingRelay((host, int(port)))
    tables = tomllib.loads(Path(cell.addresses["cell_file"]).read_text())
    assert tables["camera"]["source"]["exposure_latency_s"] < LATE_S
    tables["camera"]["source"]["device"] = camera_url.replace(host_port, f"127.0.0.1:{relay.port}")
    cell_file = tmp_path / "cell.toml"
    cell_file.write_text(dumps_cell(tables))
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
