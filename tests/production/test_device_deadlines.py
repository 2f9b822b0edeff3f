"""Every device read has a deadline (docs/reliability.md): a camera whose connection stays
open but sends nothing faults the run within max(2 s, 2 x the watchdog), the robot held,
and Reset works at once after. The virtual cell in its own process, its camera stream
reached through a loopback relay that can go silent as a stalled camera does."""

from __future__ import annotations

import socket
import threading
import time
import tomllib
from pathlib import Path

import pytest

from tests.polling import wait_until
from tests.virtual_cell_process import VirtualCellProcess
from vservo.core.cell.cell_file import dumps_cell
from vservo.core.cell.config import load_cell
from vservo.core.production.assembly import Outcome, Phase
from vservo.core.production.cell_controller import CellController
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.storage import Store

WATCHDOG_S = 1.0
pytestmark = pytest.mark.slow  # a virtual cell and two runs on it


class StallingRelay:
    """A TCP relay on loopback that can stall: a connection open when ``stall`` is called
    never forwards another byte, yet stays open; connections made after ``resume`` flow."""

    def __init__(self, upstream: tuple[str, int]) -> None:
        self.upstream = upstream
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.generation = 0  # a connection forwards only while it is of the current generation
        self.flowing = True
        self.closing = False
        self.sockets: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def stall(self) -> None:
        self.flowing = False
        self.generation += 1

    def resume(self) -> None:
        self.flowing = True

    def close(self) -> None:
        self.closing = True
        self.listener.close()
        for sock in self.sockets:
            sock.close()

    def _accept(self) -> None:
        while not self.closing:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(self.upstream)
            self.sockets += [client, server]
            generation = self.generation
            for source, sink in ((client, server), (server, client)):
                threading.Thread(target=self._pump, args=(source, sink, generation), daemon=True).start()

    def _pump(self, source: socket.socket, sink: socket.socket, generation: int) -> None:
        try:
            while data := source.recv(65536):
                while not (self.flowing and generation == self.generation):
                    if self.closing:
                        return
                    time.sleep(0.02)
                sink.sendall(data)
        except OSError:
            pass


@pytest.fixture
def stalling_cell(tmp_path):
    """The virtual cell, and a copy of its cell file whose camera is reached through a
    StallingRelay and whose watchdog is WATCHDOG_S."""
    cell = VirtualCellProcess("--seed", "3")
    camera_url = cell.addresses["camera_url"]
    host_port = camera_url.split("//")[1].split("/")[0]
    host, port = host_port.rsplit(":", 1)
    relay = StallingRelay((host, int(port)))
    tables = tomllib.loads(Path(cell.addresses["cell_file"]).read_text())
    tables["camera"]["source"]["device"] = camera_url.replace(host_port, f"127.0.0.1:{relay.port}")
    tables.setdefault("safety", {})["watchdog_s"] = WATCHDOG_S
    cell_file = tmp_path / "cell.toml"
    cell_file.write_text(dumps_cell(tables))
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
