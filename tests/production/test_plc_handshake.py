"""The PLC handshake in one process: the simulated cell's controller with its Modbus TCP
server, and a pymodbus client playing the PLC (tests/plc_fixtures.py). Starts go through
the controller's own start, refusals answer not OK, a fault waits for the PLC's reset."""

from __future__ import annotations

import socket

import pytest

from tests.cell.test_config import default_data
from tests.controller_fixtures import simulated_controller
from tests.plc_fixtures import EmulatorPlc, ModbusPlc
from tests.polling import wait_until
from vservo.core.cell.config import parse_cell
from vservo.core.production.plc.handshake import PlcOutputs, job_number
from vservo.core.production.plc.modbus import ModbusLines, ModbusServerError, decode_part_id
from vservo.core.production.plc.service import PlcService
from vservo.core.production.protocol.state import Outcome, Phase

MODBUS_PLC = {
    "transport": "modbus",
    "port": 0,
    "poll_period_s": 0.01,
    "part_id_register": 100,
    "part_id_registers": 4,
    "inputs": {"start": 0, "part_present": 1, "reset": 2, "job_bits": [8, 9, 10]},
    "outputs": {"ready": 0, "busy": 1, "done": 2, "ok": 3, "not_ok": 4, "fault": 5},
    "jobs": {"1": "demo", "2": "no-such-job"},
}


def plc_cell(plc: dict):
    data = default_data()
    data["line"] = {"plc": plc}
    return parse_cell(data, "plc test cell")


@pytest.fixture
def plc_controller(tmp_path, no_leaked_threads):
    """(the controller of the simulated cell with its PLC service, the PLC on a pymodbus client)."""
    config = plc_cell(MODBUS_PLC)
    with simulated_controller(config, tmp_path / "data") as controller:
        service = PlcService(controller, config.plc, ModbusLines(config.plc))
        plc = ModbusPlc(config.plc, *service.lines.address)
        try:
            yield controller, service, plc
        finally:
            plc.close()
            service.close()


def test_job_bits_and_part_ids_decode_as_the_plc_writes_them():
    assert job_number([True, False, True]) == 5 and job_number([]) == 0
    assert decode_part_id([0x4142, 0x2D31, 0, 0]) == "AB-1"
    assert decode_part_id([0, 0x2020]) is None


def test_a_cycle_places_the_part_and_done_ok_holds_until_start_drops(plc_controller):
    controller, service, plc = plc_controller
    assert plc.wait_for(lambda o: o.ready, "ready") == PlcOutputs(ready=True)
    controller.present_part()  # the conveyor brings the part
    plc.write_part_id("P-0042")
    plc.start(job=1)
    outputs = plc.wait_for(lambda o: o.done, "done")
    assert outputs == PlcOutputs(done=True, ok=True)
    assert controller.store.runs_between()[-1].part_id == "P-0042"
    assert plc.outputs() == outputs  # held while start is high
    plc.set(start=False)
    assert plc.wait_for(lambda o: o.ready, "ready again") == PlcOutputs(ready=True)
    assert service.handshake.starts == 1


def test_a_part_missing_or_an_unknown_job_answers_not_ok_and_starts_nothing(plc_controller):
    controller, service, plc = plc_controller
    missing = plc.cycle(job=1, part_present=False)
    assert missing.result == PlcOutputs(done=True, not_ok=True) and not missing.saw_busy
    assert "no part present" in controller.state.detail
    unknown = plc.cycle(job=5)
    assert unknown.result == PlcOutputs(done=True, not_ok=True)
    assert "job number 5 is not in [line.plc.jobs]" in controller.state.detail
    not_stored = plc.cycle(job=2)  # in the table, not in the store: the controller refuses it
    assert not_stored.result == PlcOutputs(done=True, not_ok=True)
    assert "no-such-job" in controller.state.detail
    assert service.handshake.starts == 0 and service.handshake.refusals == 3
    assert controller.store.runs_between() == []


def test_an_estop_latches_fault_and_no_start_is_taken_until_the_plc_resets(plc_controller):
    controller, service, plc = plc_controller
    plc.wait_for(lambda o: o.ready, "ready")
    controller.estop("e-stop pressed on the page")
    assert plc.wait_for(lambda o: o.fault, "fault") == PlcOutputs(not_ok=True, fault=True)
    plc.select_job(1)
    plc.set(part_present=True, start=True)  # ignored: not ready
    wait_until(lambda: service.polls > 5, "polls")
    plc.set(start=False)
    assert controller.state.phase == Phase.ESTOPPED and service.handshake.starts == 0
    plc.reset()
    assert plc.wait_for(lambda o: o.ready, "ready after reset") == PlcOutputs(ready=True)
    assert controller.state.phase == Phase.IDLE
    controller.present_part()
    assert plc.cycle(job=1).result == PlcOutputs(done=True, ok=True)
    assert controller.last_outcome.outcome is Outcome.PLACED


JRC_PLC = {
    "transport": "jrc_io",
    "poll_period_s": 0.01,
    "inputs": {"start": 30, "part_present": 31, "reset": 32, "job_bits": [40, 41]},
    "outputs": {"ready": 27020, "busy": 27021, "done": 27022, "ok": 27023, "not_ok": 27024, "fault": 27025},
    "jobs": {"1": "demo"},
}


def test_on_the_jrcs_io_lines_a_cycle_a_part_missing_and_a_fault_reset(tmp_path, no_leaked_threads):
    """The same handshake on the JRC's I/O: the controller reads the PLC's signals with IOREAD
    and writes its own as network inputs over the JRC link to the emulator, whose I/O panel
    the PLC program drives."""
    data = default_data()
    data["robot"]["backend"] = "jrc"
    data["line"] = {"plc": JRC_PLC}
    config = parse_cell(data, "plc test cell")
    with simulated_controller(config, tmp_path / "data") as controller:
        service = PlcService.start(controller)
        plc = EmulatorPlc(config.plc, controller.rig.emulator)
        try:
            controller.present_part()
            placed = plc.cycle(job=1)
            assert placed.result == PlcOutputs(done=True, ok=True) and placed.saw_busy
            missing = plc.cycle(job=1, part_present=False)
            assert missing.result == PlcOutputs(done=True, not_ok=True)
            plc.wait_for(lambda o: o.ready, "ready")
            controller.estop("e-stop pressed on the page")
            assert plc.wait_for(lambda o: o.fault, "fault") == PlcOutputs(not_ok=True, fault=True)
            plc.reset()
            assert plc.wait_for(lambda o: o.ready, "ready after reset") == PlcOutputs(ready=True)
            assert service.handshake.starts == 1 and service.handshake.refusals == 1
        finally:
            service.close()
        assert plc.outputs() == PlcOutputs()  # a stopped service leaves every output low


def test_while_the_page_teaches_ready_is_low_and_a_start_is_not_taken(plc_controller):
    """One cell, two clients: while the page's operator teaches, the PLC's start finds Ready
    low and starts nothing, even once teaching ends with start still high (no new edge)."""
    controller, service, plc = plc_controller
    plc.wait_for(lambda o: o.ready, "ready")
    controller.begin_teach()
    plc.wait_for(lambda o: not o.ready, "ready to fall while teaching")
    plc.select_job(1)
    plc.set(part_present=True, start=True)
    wait_until(lambda: service.polls > 5, "polls")
    controller.cancel_teach()
    assert plc.wait_for(lambda o: o.ready, "ready after teaching") == PlcOutputs(ready=True)
    assert controller.state.phase == Phase.IDLE and service.handshake.starts == 0
    plc.set(start=False)
    polls = service.polls
    wait_until(lambda: service.polls >= polls + 2, "start low for a poll")  # a PLC holds a level one poll at least
    controller.present_part()
    assert plc.cycle(job=1).result == PlcOutputs(done=True, ok=True)


def test_a_modbus_port_already_taken_is_one_line_naming_it_and_leaves_no_thread(no_leaked_threads):
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        port = taken.getsockname()[1]
        config = plc_cell({**MODBUS_PLC, "port": port}).plc
        with pytest.raises(ModbusServerError, match=rf"line.plc: the Modbus TCP server cannot listen on 127.0.0.1:{port}"):
            ModbusLines(config)
    finally:
        taken.close()
