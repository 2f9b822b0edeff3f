"""The PLC handshake on the line, with real processes: `vservo virtual-cell` and `vservo
controller` (its cell file with [line.plc]), and a PLC program (tests/plc_fixtures.py) on
a pymodbus client against the controller's Modbus TCP server, or on the virtual cell's I/O
panel for the JRC's I/O lines. The conveyor is the virtual cell's fixture (a new part for
each cycle); the E-STOP is the page's, sent over the controller's channel."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import urllib.request
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.cell.test_config import default_data
from tests.plc_fixtures import ModbusPlc, PanelPlc, Plc
from tests.polling import wait_until
from tests.virtual_cell_process import VirtualCellProcess
from vservo.core.cell.cell_file import dumps_cell
from vservo.core.cell.config import load_cell
from vservo.core.production.plc.handshake import PlcOutputs
from vservo.core.production.protocol import KEY_ENVIRONMENT
from vservo.core.production.protocol.client import ControllerClient, new_key
from vservo.core.production.protocol.commands import Estop
from vservo.core.production.protocol.state import Phase
from vservo.core.production.storage import Store

ROOT = Path(__file__).resolve().parents[2]
TIME_SCALE = "200"  # the virtual cell's fastest pace its camera keeps up with; a run is then about 1 s of wall time
CYCLES = 20

LINES = {
    "modbus": {
        "transport": "modbus",
        "port": 0,
        "poll_period_s": 0.02,
        "inputs": {"start": 0, "part_present": 1, "reset": 2, "job_bits": [8, 9, 10, 11]},
        "outputs": {"ready": 0, "busy": 1, "done": 2, "ok": 3, "not_ok": 4, "fault": 5},
        "jobs": {"3": "demo"},
    },
    "jrc_io": {
        "transport": "jrc_io",
        "poll_period_s": 0.02,
        "inputs": {"start": 30, "part_present": 31, "reset": 32, "job_bits": [40, 41, 42, 43]},
        "outputs": {"ready": 27020, "busy": 27021, "done": 27022, "ok": 27023, "not_ok": 27024, "fault": 27025},
        "jobs": {"3": "demo"},
    },
}
JOB = 3


class Line:
    """The virtual cell, the controller on its cell file, the PLC, and the channel's key."""

    def __init__(self, cell: VirtualCellProcess, controller: subprocess.Popen, announced: dict, key: bytes, data: Path) -> None:
        self.cell, self.controller, self.announced, self.key, self.data = cell, controller, announced, key, data
        config = load_cell(cell.addresses["cell_file"]).plc
        assert config is not None
        self.config = config
        plc = announced["plc"]
        self.plc: Plc = (
            ModbusPlc(config, plc["host"], plc["port"])
            if plc["transport"] == "modbus"
            else PanelPlc(config, cell.addresses["fixture"])
        )

    def new_part(self) -> None:
        """The conveyor brings a part (the virtual cell's fixture puts one on the table)."""
        request = urllib.request.Request(f"{self.cell.addresses['fixture']}/part", data=b"{}", method="POST")
        with urllib.request.urlopen(request, timeout=30) as reply:
            assert reply.status == 200

    def channel(self) -> ControllerClient:
        address = self.announced["controller"]
        return ControllerClient((address["host"], address["port"]), self.key)


@contextmanager
def line(transport: str, folder: Path, thesis_policy: bool = False) -> Iterator[Line]:
    data = default_data()
    data["line"] = {"plc": LINES[transport]}
    if thesis_policy:  # hundreds of servo cycles: a run long enough to press E-STOP in
        data["motion"]["policy"] = "thesis"
    source = folder / "line-cell.toml"
    source.write_text(dumps_cell(data, "a cell on a line, its PLC on [line.plc]"))
    cell = VirtualCellProcess("--cell", str(source), "--time-scale", TIME_SCALE, "--seed", "5")
    key = new_key()
    controller = None
    try:
        command = [sys.executable, "-m", "vservo.app.cli", "--cell", cell.addresses["cell_file"], "controller"]
        command += ["--data", str(folder / "data"), "--cycle-period", "0"]
        log = tempfile.TemporaryFile("w+")
        controller = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=log, text=True, cwd=ROOT, env={**os.environ, KEY_ENVIRONMENT: key.hex()}
        )
        first = controller.stdout.readline()
        if not first:
            log.seek(0)
            raise AssertionError(f"the controller did not start: {log.read()[-3000:]}")
        announced = json.loads(first)
        assert announced["plc"]["transport"] == transport
        running = Line(cell, controller, announced, key, folder / "data")
        try:
            yield running
        finally:
            running.plc.close()
    finally:
        if controller is not None:
            controller.terminate()
            controller.wait(30)
            controller.stdout.close()
        cell.stop()


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["modbus", "jrc_io"])
def test_twenty_cycles_placed_then_a_part_missing(tmp_path, transport):
    """20 cycles of start / busy / done with OK, each run stored; then a start without the
    part: done with not OK, and no run."""
    with line(transport, tmp_path) as running:
        plc = running.plc
        results = Counter()
        for _ in range(CYCLES):
            running.new_part()
            cycle = plc.cycle(JOB)
            assert cycle.saw_busy, cycle
            results[cycle.result] += 1
        assert results == {PlcOutputs(done=True, ok=True): CYCLES}
        missing = plc.cycle(JOB, part_present=False)
        assert missing.result == PlcOutputs(done=True, not_ok=True) and not missing.saw_busy
        assert plc.wait_for(lambda o: o.ready, "ready after the refusal") == PlcOutputs(ready=True)
    store = Store(running.data)
    try:
        runs = store.runs_between()
    finally:
        store.close()
    assert [(run.job, run.outcome.value) for run in runs] == [("demo", "placed")] * CYCLES


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["modbus", "jrc_io"])
def test_an_estop_in_the_middle_of_a_run_faults_and_no_start_is_taken_until_the_plcs_reset(tmp_path, transport):
    with line(transport, tmp_path, thesis_policy=True) as running:
        plc, page = running.plc, running.channel()
        try:
            running.new_part()
            plc.start(JOB)
            plc.wait_for(lambda o: o.busy, "busy")
            assert page.call(Estop()).ok
            assert plc.wait_for(lambda o: o.fault, "fault") == PlcOutputs(not_ok=True, fault=True)
            plc.set(start=False)
            plc.set(start=True)  # a new start while the fault stands: not taken
            assert plc.outputs() == PlcOutputs(not_ok=True, fault=True)
            wait_until(lambda: page.state.phase == Phase.ESTOPPED, "the page to show e-stopped")
            # The reset, read with start still high: the handshake has seen that start, and
            # starts nothing after the reset either (no new rising edge).
            plc.reset()
            assert plc.wait_for(lambda o: o.ready, "ready after the PLC's reset") == PlcOutputs(ready=True)
            plc.set(start=False)
            wait_until(lambda: page.state.phase == Phase.IDLE, "the page to show idle")
        finally:
            page.close()
    store = Store(running.data)
    try:
        runs = store.runs_between()
    finally:
        store.close()
    assert [run.outcome.value for run in runs] == ["e-stopped"]
